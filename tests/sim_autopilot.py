"""A simulated flight controller for the tests: a pymavlink peer speaking for PX4 or ArduPilot.

It plays an IMU recording as the autopilot would stream it: HEARTBEAT (1 Hz, autopilot type
PX4 or ArduPilot), HIGHRES_IMU and/or SCALED_IMU once asked for with SET_MESSAGE_INTERVAL
(answered with COMMAND_ACK, the interval honoured by sending every k-th sample), its own
ATTITUDE_QUATERNION, and TIMESYNC replies. Its clock is its "boot": the monotonic clock minus
the moment it started, in whole microseconds, like an autopilot's ``hrt_absolute_time`` or
``AP_HAL::micros64``.

Transports: a UDP socket on 127.0.0.1 (:class:`UdpTransport`, the autopilot sends first, like
PX4 SITL to its offboard port) or a pseudo-terminal pair (:class:`PtyTransport`, 921 600 baud
set on both ends with termios; a pty ignores the rate, so nothing here measures it). A pty can
be "unplugged" and "plugged in" again under the same path (a symlink the service opens), to
test a serial device vanishing.

Every loop is bounded: the recording's length plus ``time_limit_s``.
"""

from __future__ import annotations

import math
import os
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from ahrs_service.core.quaternion import quat_from_euler, quat_mul

G = 9.80665


@dataclass
class Recording:
    """What the autopilot streams: per sample its offset from the stream start (whole µs) and
    its readings in the message's units (float32, as on the wire) — gyr rad/s, acc m/s²,
    mag gauss — and the autopilot's own attitude q_earth←body [w, x, y, z]."""

    rel_us: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag_gauss: np.ndarray
    q: np.ndarray

    @property
    def period_us(self) -> int:
        return int(np.median(np.diff(self.rel_us)))

    @classmethod
    def uniform(cls, gyr, acc, mag_ut, q, period_us: int) -> "Recording":
        """Readings rounded to float32 in the wire units, on a grid ``period_us`` apart."""
        n = len(gyr)
        return cls(np.arange(n, dtype=np.int64) * int(period_us), np.asarray(gyr, np.float32),
                   np.asarray(acc, np.float32), (np.asarray(mag_ut) / 100.0).astype(np.float32),
                   np.asarray(q, float))

    def highres_mag(self, kind: str) -> np.ndarray:
        """HIGHRES_IMU's field values as the autopilot sends them (float32): gauss (PX4), or
        ArduPilot's mgauss × 1000 (GCS_MAVLINK::send_highres_imu)."""
        if kind == "ardupilot":
            return (self.mag_gauss.astype(np.float64) * 1e6).astype(np.float32)
        return self.mag_gauss

    def wire_values(self, kind: str = "px4") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """gyr rad/s, acc m/s², mag µT as the service decodes HIGHRES_IMU from ``kind``
        (float64 of the float32 values; the field ×100 from gauss, ×1e-4 from ArduPilot's)."""
        scale = 1e-4 if kind == "ardupilot" else 100.0
        return (self.gyr.astype(np.float64), self.acc.astype(np.float64),
                self.highres_mag(kind).astype(np.float64) * scale)


class UdpTransport:
    """The autopilot's UDP socket on 127.0.0.1, sending to ``peer_port`` until a peer speaks."""

    def __init__(self, peer_port: int) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.peer = ("127.0.0.1", int(peer_port))

    def write(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.peer)
        except OSError:
            pass  # nobody listening yet: an autopilot keeps sending

    def read(self) -> bytes:
        try:
            data, addr = self.sock.recvfrom(65535)
        except (BlockingIOError, ConnectionRefusedError):
            return b""
        self.peer = addr
        return data

    def close(self) -> None:
        self.sock.close()


class PtyTransport:
    """A pseudo-terminal pair: the autopilot holds the master, the service opens ``path`` (a
    symlink to the slave). ``unplug`` closes both ends (the service's reads fail as for a
    USB adapter pulled out), ``plug`` opens a new pair under the same path."""

    BAUD = termios.B921600

    def __init__(self, directory: Path) -> None:
        self.path = Path(directory) / "ttyFC"
        self.master: int | None = None
        self.slave: int | None = None
        self.plug()

    def plug(self) -> None:
        master, slave = os.openpty()
        for fd in (master, slave):
            tty.setraw(fd)
            attrs = termios.tcgetattr(fd)
            attrs[4] = attrs[5] = self.BAUD  # ispeed, ospeed
            termios.tcsetattr(fd, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        tmp = self.path.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(slave))
        tmp.replace(self.path)
        self.master, self.slave = master, slave

    def unplug(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None
        self.path.unlink(missing_ok=True)

    @property
    def url(self) -> str:
        return f"{self.path},921600"

    def write(self, data: bytes) -> None:
        """Writes all of ``data``, waiting (at most 2 s) while the reader is slow: a pty's buffer
        is a few kB, and a router lagging on a busy host must not lose the stream here (a real
        UART at 921 600 baud paces the autopilot instead). A reader gone: dropped."""
        view = memoryview(data)
        end = time.monotonic() + 2.0
        while view and self.master is not None and time.monotonic() < end:
            try:
                view = view[os.write(self.master, view):]
            except BlockingIOError:
                select.select([], [self.master], [], 0.05)
            except OSError:
                return

    def read(self) -> bytes:
        if self.master is None:
            return b""
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def close(self) -> None:
        self.unplug()


@dataclass
class SimStats:
    heartbeats: int = 0
    imu_sent: dict[str, int] = field(default_factory=dict)
    imu_dropped: int = 0
    attitudes: int = 0
    interval_requests: list[tuple[int, float]] = field(default_factory=list)  # (msg id, interval µs)
    timesync_replies: int = 0
    odometry_times_us: list[int] = field(default_factory=list)  # ODOMETRY.time_usec received
    imu_stamps_us: list[int] = field(default_factory=list)  # the time each IMU message carried
    received: dict[str, int] = field(default_factory=dict)


class SimAutopilot:
    """Streams ``recording`` over ``transport`` on a thread (``start``/``join``/``stop``).

    kind: "px4" or "ardupilot" (HEARTBEAT.autopilot). drop: sample indices never sent (lost
    samples the service must count). attitude_offset_deg: a heading offset added to the
    autopilot's own attitude (the monitor's test). pause: (sample index, seconds) — the
    autopilot stops sending for that long before that sample (a silent link); with a
    :class:`PtyTransport` the device is unplugged during the pause. answer_timesync: False
    leaves TIMESYNC requests unanswered (an autopilot or router that does not pass them).
    """

    def __init__(self, transport, recording: Recording, *, kind: str = "px4", system_id: int = 1,
                 component_id: int = 1, drop: frozenset[int] = frozenset(), attitude_hz: float = 50.0,
                 attitude_offset_deg: float = 0.0, pause: tuple[int, float] | None = None,
                 refuse_streams: bool = False, send_jitter_us: int = 0, seed: int = 0,
                 time_limit_s: float = 30.0, answer_timesync: bool = True,
                 attitude_on_request: bool = False) -> None:
        self.t = transport
        self.rec = recording
        self.kind = kind
        self.mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
        self.mav.robust_parsing = True
        self.drop = frozenset(drop)
        self.highres_mag = recording.highres_mag(kind)
        self.attitude_period_us = int(1e6 / attitude_hz)
        self.q_offset = quat_from_euler(0.0, 0.0, math.radians(attitude_offset_deg))
        self.pause = pause
        self.refuse_streams = refuse_streams  # answer SET_MESSAGE_INTERVAL with DENIED, stream nothing
        # ArduPilot stamps a message when it sends it (AP_HAL::micros64 / millis), not when the
        # sample was taken: a random 0..send_jitter_us after the sample (its scheduler's delay)
        self.send_jitter_us = int(send_jitter_us)
        self._rng = np.random.default_rng(seed)
        self.time_limit_s = time_limit_s
        self.answer_timesync = answer_timesync  # False: TIMESYNC requests go unanswered
        # True: ATTITUDE_QUATERNION only once asked for, at the asked interval (ArduPilot, whose
        # links stream only what their MAVn_* rates or a request set); False: always (PX4 onboard)
        self.attitude_on_request = attitude_on_request
        self.stats = SimStats()
        self.intervals: dict[int, float] = {}  # msg id -> µs (0 = off)
        self.boot_ns = time.monotonic_ns()
        self.stream_start_us: int | None = None
        self.finished = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-autopilot", daemon=True)

    # ------------------------------------------------------------------ clock
    def now_us(self) -> int:
        return (time.monotonic_ns() - self.boot_ns) // 1000

    def sample_time_us(self, i: int) -> int:
        """The autopilot time of sample ``i`` (µs since its boot)."""
        return int(self.stream_start_us + self.rec.rel_us[i])  # type: ignore[operator]

    # ------------------------------------------------------------------ sending
    def send(self, msg) -> None:
        self.t.write(msg.pack(self.mav))

    def heartbeat(self) -> None:
        autopilot = mavlink.MAV_AUTOPILOT_PX4 if self.kind == "px4" else mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
        self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, autopilot, 0, 0,
                                                    mavlink.MAV_STATE_ACTIVE, 3))
        self.stats.heartbeats += 1

    def _send_imu(self, i: int) -> None:
        t_us = self.sample_time_us(i)
        if self.send_jitter_us:
            t_us += int(self._rng.integers(0, self.send_jitter_us + 1))
        g, a, m = self.rec.gyr[i], self.rec.acc[i], self.rec.mag_gauss[i]
        hm = self.highres_mag[i]
        for name, msg_id in (("HIGHRES_IMU", mavlink.MAVLINK_MSG_ID_HIGHRES_IMU),
                             ("SCALED_IMU", mavlink.MAVLINK_MSG_ID_SCALED_IMU)):
            interval = self.intervals.get(msg_id, 0.0)
            if interval <= 0:
                continue
            every = max(1, int(round(interval / self.rec.period_us)))
            if i % every:
                continue
            if name == "HIGHRES_IMU":
                msg = mavlink.MAVLink_highres_imu_message(
                    t_us, float(a[0]), float(a[1]), float(a[2]), float(g[0]), float(g[1]), float(g[2]),
                    float(hm[0]), float(hm[1]), float(hm[2]), 1013.0, 0.0, 0.0, 25.0, 0x1FFF, 0)
            else:
                msg = mavlink.MAVLink_scaled_imu_message(
                    t_us // 1000, *(int(round(x / G * 1000)) for x in a), *(int(round(x * 1000)) for x in g),
                    *(int(round(x * 1000)) for x in m), 2500)
            self.send(msg)
            self.stats.imu_sent[name] = self.stats.imu_sent.get(name, 0) + 1
            self.stats.imu_stamps_us.append(t_us if name == "HIGHRES_IMU" else t_us // 1000 * 1000)

    def _attitude_period_us(self) -> int:
        """µs between ATTITUDE_QUATERNIONs; 0: none now."""
        if not self.attitude_on_request:
            return self.attitude_period_us
        return max(0, int(self.intervals.get(mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, 0.0)))

    def _send_attitude(self, i: int) -> None:
        q = quat_mul(self.q_offset, tuple(self.rec.q[i].tolist()))
        self.send(mavlink.MAVLink_attitude_quaternion_message(self.sample_time_us(i) // 1000, *map(float, q),
                                                             0.0, 0.0, 0.0))
        self.stats.attitudes += 1

    # ------------------------------------------------------------------ receiving
    def _poll(self) -> None:
        for _ in range(64):
            data = self.t.read()
            if not data:
                return
            for msg in self.mav.parse_buffer(data) or []:
                name = msg.get_type()
                self.stats.received[name] = self.stats.received.get(name, 0) + 1
                if name == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
                    self.stats.interval_requests.append((int(msg.param1), float(msg.param2)))
                    if not self.refuse_streams:
                        self.intervals[int(msg.param1)] = float(msg.param2)
                    result = mavlink.MAV_RESULT_DENIED if self.refuse_streams else mavlink.MAV_RESULT_ACCEPTED
                    self.send(mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0,
                                                                  msg.get_srcSystem(), msg.get_srcComponent()))
                elif name == "ODOMETRY":
                    self.stats.odometry_times_us.append(int(msg.time_usec))
                elif name == "TIMESYNC" and msg.tc1 == 0 and self.answer_timesync:
                    self.send(mavlink.MAVLink_timesync_message(self.now_us() * 1000, msg.ts1))
                    self.stats.timesync_replies += 1

    # ------------------------------------------------------------------ the thread
    def start(self) -> "SimAutopilot":
        self._thread.start()
        return self

    def _run(self) -> None:
        deadline = time.monotonic() + self.time_limit_s + self.rec.rel_us[-1] * 1e-6
        next_hb = 0
        n = len(self.rec.rel_us)
        i = 0
        next_att_us = 0
        try:
            while not self._stop.is_set() and time.monotonic() < deadline and i < n:
                now = self.now_us()
                if now >= next_hb:
                    self.heartbeat()
                    next_hb = now + 1_000_000
                self._poll()
                if self.stream_start_us is None:
                    if any(v > 0 for v in self.intervals.values()):
                        self.stream_start_us = now + 20_000
                    else:
                        time.sleep(0.002)
                    continue
                if self.pause is not None and i == self.pause[0]:
                    self._pause(self.pause[1])
                    self.pause = None
                    continue
                pause_at = self.pause[0] if self.pause is not None else n
                while i < n and i != pause_at and self.sample_time_us(i) <= now:  # a late pass stops at the pause
                    if i in self.drop:
                        self.stats.imu_dropped += 1
                    else:
                        self._send_imu(i)
                    attitude_period_us = self._attitude_period_us()
                    if attitude_period_us and self.sample_time_us(i) >= next_att_us:
                        self._send_attitude(i)
                        next_att_us = self.sample_time_us(i) + attitude_period_us
                    i += 1
                if i < n:
                    time.sleep(max(0.0, min(0.002, (self.sample_time_us(i) - self.now_us()) * 1e-6)))
        finally:
            self.finished.set()

    def _pause(self, seconds: float) -> None:
        """Silence for ``seconds``: the stream's clock goes on (the samples of the pause are
        never sent: the service counts them lost); a pty is unplugged meanwhile."""
        unplug = isinstance(self.t, PtyTransport)
        if unplug:
            self.t.unplug()
        end = time.monotonic() + seconds
        while time.monotonic() < end and not self._stop.is_set():
            time.sleep(0.01)
        if unplug:
            self.t.plug()
        # the samples due during the pause are skipped: they are lost, as on a real link
        now = self.now_us()
        skip = int(np.searchsorted(self.rec.rel_us + self.stream_start_us, now))  # type: ignore[operator]
        self.drop = self.drop | frozenset(range(self.pause[0], skip))  # type: ignore[index]

    def join(self, timeout: float) -> bool:
        return self.finished.wait(timeout)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.t.close()
