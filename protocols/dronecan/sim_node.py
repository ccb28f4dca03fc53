"""A simulated DroneCAN IMU node: publishes a simulator's readings as RawIMU and magnetometer messages.

Used by the tests, for bench work without hardware, and to exercise the CAN input's fault
handling. RawIMU and MagneticFieldStrength2 use the fast ``struct`` encoders of
:mod:`ahrs_service.protocols.dronecan.messages` (a node at 1 kHz cannot afford the ``dronecan``
package's bit-string packing; the tests check both give the same bytes); NodeStatus goes
through the ``dronecan`` reference encoder.

The node's sensor clock is the simulation time plus ``sensor_epoch_us`` (a node's clock
starts at its boot, not at the host's), so a receiver must map it onto its own clock.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from typing import Any

import can
import dronecan

from ahrs_service.protocols.dronecan.messages import (
    DEFAULT_PRIORITY,
    GAUSS_TO_UT,
    MAG2_ID,
    NODE_STATUS_ID,
    RAW_IMU_ID,
    build_message_id,
    encode_message,
    pack_mag2,
    pack_raw_imu,
    transfer_crc_seed,
    transfer_frames,
)

#: fault kinds understood by :meth:`SimulatedDroneCanImuNode.inject` and ``faults=``
FAULTS = ("corrupt", "drop_middle", "swap_middle", "foreign")

_EPS = 1e-9  # float slack when deciding whether a publication time has been reached


class SimulatedDroneCanImuNode:
    """Publishes ``simulated_imu.physics(t)`` on a python-can bus as DroneCAN node ``node_id``.

    simulated_imu: any object with ``physics(t)`` → {"gyr", "acc", "mag"} ((3,), rad/s,
        m/s² specific force, µT; body FRD) and, for the background thread, ``clock.now()`` (s).
    rate_hz, mag_rate_hz: RawIMU and MagneticFieldStrength2 rates; the k-th RawIMU is the
        reading at t = k / rate_hz.
    sensor_epoch_us: the node clock's reading at simulation time 0 (µs).
    node_status: also publish NodeStatus (341) at 1 Hz.
    publish_imu: False for a compass node: the magnetometer (and status) messages only, still
        paced by ``rate_hz``.
    faults: periodic faults {kind: every_n_th RawIMU transfer}, kinds in :data:`FAULTS`:
        "corrupt" flips a payload bit (CRC error), "drop_middle" leaves out a middle frame,
        "swap_middle" sends two middle frames in swapped order (toggle error),
        "foreign" additionally sends the transfer from ``foreign_node_id``.

    Counters: ``sent_transfers``, ``sent_frames``, ``send_errors``, ``injected`` (per kind).
    """

    def __init__(
        self,
        bus: can.BusABC,
        simulated_imu: Any,
        node_id: int = 42,
        rate_hz: float = 200.0,
        mag_rate_hz: float = 50.0,
        *,
        node_status: bool = False,
        sensor_epoch_us: int = 1_000_000,
        priority: int = DEFAULT_PRIORITY,
        faults: Mapping[str, int] | None = None,
        foreign_node_id: int = 99,
        mag_sensor_id: int = 0,
        publish_imu: bool = True,
    ) -> None:
        if not 1 <= node_id <= 127 or not 1 <= foreign_node_id <= 127:
            raise ValueError("node ids must be in 1..127")
        if rate_hz <= 0 or mag_rate_hz < 0:
            raise ValueError("rate_hz must be > 0 and mag_rate_hz >= 0")
        self.faults = dict(faults or {})
        for kind, every in self.faults.items():
            if kind not in FAULTS or int(every) < 1:
                raise ValueError(f"fault {kind!r}: every {every}; kinds are {FAULTS}, every >= 1")
        self.bus = bus
        self.imu = simulated_imu
        self.node_id = node_id
        self.rate_hz = float(rate_hz)
        self.mag_rate_hz = float(mag_rate_hz)
        self.node_status = node_status
        self.sensor_epoch_us = int(sensor_epoch_us)
        self.priority = priority
        self.foreign_node_id = foreign_node_id
        self.mag_sensor_id = mag_sensor_id
        self.publish_imu = publish_imu
        self._imu_id = build_message_id(RAW_IMU_ID, node_id, priority)
        self._mag_id = build_message_id(MAG2_ID, node_id, priority)
        self._imu_seed = transfer_crc_seed(RAW_IMU_ID)
        self._next_imu = 0  # index k of the next RawIMU, published at t = k / rate_hz
        self._next_mag = 0
        self._next_status = 0
        self._tid = {RAW_IMU_ID: 0, MAG2_ID: 0, NODE_STATUS_ID: 0}
        self._queued: dict[str, int] = {}  # fault kind -> RawIMU transfers still to damage
        self.sent_transfers = 0
        self.sent_frames = 0
        self.send_errors = 0
        self.injected = {k: 0 for k in FAULTS}
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ---------------------------------------------------------------------- publishing

    def inject(self, kind: str, count: int = 1) -> None:
        """Applies fault ``kind`` to the next ``count`` RawIMU transfers."""
        if kind not in FAULTS:
            raise ValueError(f"unknown fault {kind!r}; kinds are {FAULTS}")
        self._queued[kind] = self._queued.get(kind, 0) + int(count)

    def step(self, t: float) -> int:
        """Publishes every message due at or before simulation time ``t`` (s); returns transfers sent.

        Calling it with t = k / rate_hz for k = 0, 1, 2, … sends exactly one RawIMU per call
        (plus magnetometer and status messages when due).
        """
        sent = 0
        while self._next_imu / self.rate_hz <= t + _EPS:
            ts = self._next_imu / self.rate_hz
            # magnetometer first: a reading taken at the same instant reaches the receiver
            # before the IMU sample it belongs to
            if self.mag_rate_hz > 0 and self._next_mag / self.mag_rate_hz <= ts + _EPS:
                sent += self._publish_mag(ts)
                self._next_mag = math.floor(ts * self.mag_rate_hz + _EPS) + 1
            if self.node_status and self._next_status <= ts + _EPS:
                sent += self._publish_status(ts)
                self._next_status = math.floor(ts + _EPS) + 1
            if self.publish_imu:
                sent += self._publish_imu(ts, self._next_imu)
            self._next_imu += 1
        return sent

    def _sensor_us(self, t: float) -> int:
        return self.sensor_epoch_us + int(round(t * 1e6))

    def _publish_imu(self, t: float, k: int) -> int:
        ph = self.imu.physics(t)
        # integration_interval -1: only the latest samples are filled
        payload = pack_raw_imu(self._sensor_us(t), ph["gyr"], ph["acc"])
        frames = transfer_frames(self._imu_id, payload, self._next_tid(RAW_IMU_ID), self._imu_seed)
        kinds = {kind for kind, left in self._queued.items() if left > 0}
        for kind in kinds:
            self._queued[kind] -= 1
        kinds |= {kind for kind, every in self.faults.items() if (k + 1) % int(every) == 0}
        foreign = None
        for kind in sorted(kinds):  # a fixed order: the same faults give the same frames
            self.injected[kind] += 1
            if kind == "foreign":
                foreign = transfer_frames(
                    build_message_id(RAW_IMU_ID, self.foreign_node_id, self.priority), payload, k, self._imu_seed
                )
            else:
                frames = _damage(frames, kind)
        n = self._send(frames)
        if foreign is not None:
            n += self._send(foreign)
        return n

    def _publish_mag(self, t: float) -> int:
        mag = self.imu.physics(t)["mag"]
        payload = pack_mag2(self.mag_sensor_id, [float(v) / GAUSS_TO_UT for v in mag])
        return self._send(transfer_frames(self._mag_id, payload, self._next_tid(MAG2_ID)))

    def _publish_status(self, t: float) -> int:
        m = dronecan.uavcan.protocol.NodeStatus()
        m.uptime_sec = int(self._sensor_us(t) // 1_000_000)
        m.health = 0
        m.mode = 0
        return self._send(encode_message(m, self.node_id, self._next_tid(NODE_STATUS_ID), self.priority))

    def _next_tid(self, dtid: int) -> int:
        tid = self._tid[dtid]
        self._tid[dtid] = (tid + 1) & 0x1F
        return tid

    def _send(self, frames: list[can.Message]) -> int:
        """Sends one transfer's frames; a failed send is counted and the transfer abandoned."""
        for msg in frames:
            try:
                self.bus.send(msg)
            except (can.CanError, OSError):
                self.send_errors += 1
                return 0
            self.sent_frames += 1
        self.sent_transfers += 1
        return 1

    # -------------------------------------------------------------------- background

    def start(self, duration_s: float | None = None) -> None:
        """Publishes in real time from a daemon thread, by ``simulated_imu.clock.now()``.

        Stops by itself after ``duration_s`` seconds of simulation time when given.
        """
        if self._thread is not None:
            raise RuntimeError("node already running")
        self._stop.clear()
        clock = self.imu.clock
        t_end = None if duration_s is None else clock.now() + duration_s

        def run() -> None:
            period = 1.0 / self.rate_hz
            while not self._stop.is_set():
                t = clock.now()
                if t_end is not None and t >= t_end:
                    break
                self.step(t)
                # sleep about one period; the sleep is interruptible by stop()
                self._stop.wait(period)

        self._thread = threading.Thread(target=run, name=f"dronecan-sim-node-{self.node_id}", daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        """Whether the background thread is publishing."""
        return self._thread is not None and self._thread.is_alive()

    def stop(self, timeout_s: float = 2.0) -> bool:
        """Stops the background thread; True when it ended within ``timeout_s``."""
        th = self._thread
        if th is None:
            return True
        self._stop.set()
        th.join(timeout_s)
        self._thread = None
        return not th.is_alive()

    def __enter__(self) -> "SimulatedDroneCanImuNode":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _damage(frames: list[can.Message], kind: str) -> list[can.Message]:
    """A copy of a transfer's frames with one fault applied (multi-frame transfers only)."""
    if len(frames) < 3 and kind in ("drop_middle", "swap_middle"):
        raise ValueError(f"fault {kind!r} needs a transfer of at least 3 frames")
    out = [can.Message(arbitration_id=f.arbitration_id, is_extended_id=True, data=bytes(f.data)) for f in frames]
    mid = len(out) // 2
    if kind == "corrupt":
        data = bytearray(out[mid].data)
        data[0] ^= 0x10  # a payload byte, never the tail byte: the frame stays well formed
        out[mid].data = data
    elif kind == "drop_middle":
        del out[mid]
    elif kind == "swap_middle":
        out[mid - 1], out[mid] = out[mid], out[mid - 1]
    return out


__all__ = ["FAULTS", "SimulatedDroneCanImuNode"]
