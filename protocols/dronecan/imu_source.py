"""IMU input from a DroneCAN node: RawIMU (1003) plus MagneticFieldStrength2 (1002) or (1001).

Frames come from any python-can bus (socketcan, slcan, virtual, udp_multicast, …) and are
reassembled by :class:`ahrs_service.protocols.dronecan.messages.TransferReassembler`.

Units and axes: RawIMU ``rate_gyro_latest`` is rad/s and ``accelerometer_latest`` m/s², both
in the node's body frame with x forward, y right, z down (the DSDL comments). The DSDL calls
the accelerometer value "linear acceleration", but what nodes publish is the accelerometer
reading, i.e. specific force: ArduPilot's AP_Periph copies its INS accelerometer, which reads
(0, 0, −9.81) level at rest — the project's convention. ``negate_acc`` exists for a node that
publishes the opposite sign. Magnetometer messages are in Gauss and are converted to µT.

Identity: the IMU node is the configured ``node_id``, else the first node whose RawIMU
transfer arrives complete — a node sending only a magnetometer or anything else never takes
that place. Transfers of that node id that do not continue its stream (a second sender with
the same id, duplicates, a reboot) are sorted out by
:class:`ahrs_service.protocols.dronecan.node_stream.NodeStreamGuard`.

Time: each sample is stamped with the node's own acquisition time (``RawIMU.timestamp``, µs),
mapped onto the host monotonic clock by an offset estimate (see :class:`SensorClockMap`), so
bus and scheduling latency do not jitter the time steps the estimator sees.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import can
import numpy as np

from ahrs_service.core.sample_clock import SensorClockMap
from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
    ImuSample,
    ImuSource,
    beyond_range,
)
from ahrs_service.protocols.dronecan.messages import (
    GAUSS_TO_UT,
    MAG2_ID,
    MAG_ID,
    RAW_IMU_ID,
    Transfer,
    TransferReassembler,
    unpack_mag,
    unpack_mag2,
    unpack_raw_imu,
)
from ahrs_service.protocols.dronecan.node_stream import NodeStreamGuard, Verdict

_IMU_TYPES = (RAW_IMU_ID, MAG2_ID, MAG_ID)

_log = logging.getLogger(__name__)


@dataclass
class DroneCanConfig:
    """Where and how to listen; the ``[imu.can]`` section of the service configuration.

    interface, channel, bitrate: passed to ``can.Bus`` (e.g. "socketcan"/"can0", "slcan"/
        "/dev/ttyACM0" with bitrate 1_000_000, "virtual"/"sim").
    node_id: the IMU node (1…127). None: the first node whose RawIMU transfer arrives
        complete is taken, and the others count as foreign; magnetometer messages never
        choose it.
    mag_node_id: node sending the magnetometer messages when it is not the IMU node (e.g. a
        compass on a GPS node). None: the IMU node.
    mag_sensor_id: accept only this ``sensor_id`` of MagneticFieldStrength2 (None: any).
    transfer_timeout_s: a multi-frame transfer not finished this long after its first frame
        is dropped as incomplete.
    max_frames_per_read: bound on the frames drained in one ``read`` call.
    max_pending_samples: bound on the received samples waiting for ``read``; when more
        arrive the oldest are dropped (counted as ``superseded_samples``).
    reopen_backoff_s, reopen_backoff_max_s: first and longest wait before reopening a bus
        that raised an error (doubles on each failure).
    negate_acc: flips the accelerometer sign for nodes that publish −specific force.
    stream_silence_s: after this long (s) without a RawIMU transfer continuing the IMU node's
        stream, the next one starts it again whatever its transfer id and timestamp (a
        reboot; the second sender of a conflict once the first has fallen silent).
    bus_kwargs: further keyword arguments for ``can.Bus``.
    """

    interface: str = "socketcan"
    channel: str | int | None = "can0"
    bitrate: int | None = 1_000_000
    node_id: int | None = None
    mag_node_id: int | None = None
    mag_sensor_id: int | None = None
    transfer_timeout_s: float = 0.5
    max_frames_per_read: int = 512
    max_pending_samples: int = 64
    reopen_backoff_s: float = 0.05
    reopen_backoff_max_s: float = 2.0
    negate_acc: bool = False
    stream_silence_s: float = 1.0
    bus_kwargs: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_mapping(cls, cfg: Mapping[str, Any]) -> "DroneCanConfig":
        """From a configuration table; unknown keys raise ``ValueError`` naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ValueError(f"unknown DroneCAN option(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(cfg))

    def open_bus(self) -> can.BusABC:
        """A python-can bus for this configuration, filtered to the IMU message types."""
        # Kernel/hardware filters on the data type only: frames of other nodes with these
        # types must still reach us so that they are counted as foreign.
        filters = [
            {"can_id": dtid << 8, "can_mask": 0xFFFF80, "extended": True} for dtid in _IMU_TYPES
        ]
        kwargs: dict[str, Any] = {"interface": self.interface, "can_filters": filters}
        if self.channel is not None:
            kwargs["channel"] = self.channel
        if self.bitrate is not None and self.interface not in ("virtual", "udp_multicast"):
            kwargs["bitrate"] = self.bitrate
        kwargs.update(self.bus_kwargs)
        return can.Bus(**kwargs)


class DroneCanImuSource(ImuSource):
    """IMU samples from a DroneCAN node on a CAN bus.

    ``bus``: an open python-can bus (the caller owns and shuts it; errors are retried on the
    same object), or a zero-argument callable returning a new bus (called by ``open`` and on
    every reopen), or None to open one from ``config``. ``clock_ns`` is the host monotonic
    clock in ns (injectable for tests).

    ``read`` drains the pending frames and returns the oldest sample not yet delivered (the
    service calls it until None, see ``may_have_backlog``); magnetometer values are the
    latest received before that sample (µT), with ``MAG_NEW`` set when one arrived since the
    previous sample.
    """

    has_mag = True
    may_have_backlog = True

    def __init__(
        self,
        config: DroneCanConfig | Mapping[str, Any] | None = None,
        *,
        bus: can.BusABC | Callable[[], can.BusABC] | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        super().__init__()
        if config is None:
            config = DroneCanConfig()
        elif not isinstance(config, DroneCanConfig):
            config = DroneCanConfig.from_mapping(config)
        self.config = config
        self._clock_ns = clock_ns
        if bus is None:
            self._factory: Callable[[], can.BusABC] | None = config.open_bus
            self._given_bus = None
        elif isinstance(bus, can.BusABC):
            self._factory = None
            self._given_bus = bus
        elif callable(bus):
            self._factory = bus
            self._given_bus = None
        else:
            raise TypeError(f"bus must be a can.BusABC, a callable returning one, or None, not {type(bus)!r}")
        self._bus: can.BusABC | None = None
        self._opened = False
        self._next_open_ns = 0
        self._backoff_s = config.reopen_backoff_s
        self.reassembler = TransferReassembler(config.transfer_timeout_s)
        self.clock_map = SensorClockMap()
        self._imu_node = config.node_id
        self._mag_node = config.mag_node_id
        self._stream: NodeStreamGuard | None = None if config.node_id is None else self._new_stream_guard()
        self._conflicts_reported = 0
        self._last_t_ns = -1
        self._mag: tuple[float, float, float] | None = None
        self._mag_fresh = False
        # before the IMU node is known: each node's latest field (Gauss), for when it turns
        # out to be the IMU node and no other magnetometer node is configured
        self._early_mag: dict[int, tuple[float, float, float]] = {}
        # received, not yet delivered: [t_ns, usec, gyr, acc, mag_new, mag, node], oldest first
        self._pending: deque[list] = deque(maxlen=config.max_pending_samples)
        self._reasm_dropped = 0
        self.diagnostics.extra.update(
            foreign_frames=0,
            malformed_frames=0,
            out_of_order_transfers=0,
            crc_errors=0,
            malformed_transfers=0,
            error_frames=0,
            stale_samples=0,
            out_of_sequence_samples=0,
            conflict_samples=0,
            conflict_samples_delivered=0,
            node_id_conflicts=0,
            node_restarts=0,
            superseded_samples=0,
            sensor_clock_resets=0,
        )

    def _new_stream_guard(self) -> NodeStreamGuard:
        return NodeStreamGuard(silence_s=self.config.stream_silence_s,
                               time_slack_s=self.clock_map.reset_ns / 1e9)

    # ----------------------------------------------------------------------------- bus

    def open(self) -> None:
        """Opens the bus; raises ``OSError`` naming interface and channel when that fails."""
        self._opened = True
        self._next_open_ns = 0
        self._backoff_s = self.config.reopen_backoff_s
        if self._given_bus is not None:
            self._bus = self._given_bus
        else:
            try:
                self._bus = self._factory()  # type: ignore[misc]
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise OSError(
                    f"cannot open CAN bus interface={self.config.interface!r} channel={self.config.channel!r}: {exc}"
                ) from exc
        self.diagnostics.device_lost = False

    def close(self) -> None:
        """Shuts the bus down when this source opened it; undelivered samples are discarded."""
        self._opened = False
        self._pending.clear()
        bus, self._bus = self._bus, None
        if bus is not None and bus is not self._given_bus:
            try:
                bus.shutdown()
            except (can.CanError, OSError):
                pass

    def _bus_failed(self, exc: BaseException, now_ns: int) -> None:
        self.diagnostics.bus_errors += 1
        self._schedule_reopen(exc, now_ns)

    def _schedule_reopen(self, exc: BaseException, now_ns: int) -> None:
        d = self.diagnostics
        d.device_lost = True
        d.last_error = f"CAN bus {self.config.interface}/{self.config.channel}: {type(exc).__name__}: {exc}"
        if self._given_bus is None and self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:  # noqa: BLE001 — a broken bus may fail to shut down in any way
                pass
        self._bus = None
        self._next_open_ns = now_ns + int(self._backoff_s * 1e9)
        self._backoff_s = min(self._backoff_s * 2.0, self.config.reopen_backoff_max_s)
        # transfers in flight cannot complete across the gap
        self.reassembler.reset()

    def _reopen(self, now_ns: int) -> bool:
        if now_ns < self._next_open_ns:
            return False
        if self._given_bus is not None:
            self._bus = self._given_bus
        else:
            try:
                self._bus = self._factory()  # type: ignore[misc]
            except (can.CanError, OSError, ValueError) as exc:
                self.diagnostics.retries += 1  # a failed reopen is a retry, not a new bus fault
                self._schedule_reopen(exc, now_ns)
                return False
        self.diagnostics.reinitialisations += 1
        self.diagnostics.device_lost = False
        if self._stream is not None:  # transfers were missed: the transfer ids jump
            self._stream.resync()
        return True

    # ---------------------------------------------------------------------------- read

    def read(self) -> ImuSample | None:
        """The oldest sample not yet delivered, or None. Never raises on bus faults."""
        self._drain()
        return self._sample(self._pending.popleft()) if self._pending else None

    def _sample(self, p: list) -> ImuSample:
        t_ns, usec, gyr, acc, mag_new, mag, src = p
        flags = 0
        for values, part, valid, saturated in ((gyr, "gyr", GYR_VALID, GYR_SATURATED), (acc, "acc", ACC_VALID, ACC_SATURATED)):
            if not _finite(values):
                self.diagnostics.non_finite += 1
            elif beyond_range(values, part):  # 65504 rad/s in a float16: no motion (drivers.base.MAX_READING)
                flags |= saturated
                self.diagnostics.saturated += 1
            else:
                flags |= valid
        mag_a = None
        if mag is not None:
            # float16 values: finite ones stay finite when scaled to µT
            mag_a = np.array(mag, dtype=np.float64) * GAUSS_TO_UT
            if not _finite(mag):
                self.diagnostics.non_finite += 1
            elif beyond_range(mag_a, "mag"):
                flags |= MAG_SATURATED
                self.diagnostics.saturated += 1
            else:
                flags |= MAG_VALID
                if mag_new:
                    flags |= MAG_NEW
        self.diagnostics.samples += 1
        return ImuSample(
            t_ns=t_ns, gyr=np.array(gyr, dtype=np.float64), acc=np.array(acc, dtype=np.float64),
            mag=mag_a, flags=flags, raw={"sensor_time_us": usec, "node_id": src},
        )

    def _drain(self) -> None:
        """Receives all pending frames (bounded) and turns completed transfers into pending samples."""
        now = self._clock_ns()
        if not self._opened:
            return
        if self._bus is None and not self._reopen(now):
            return
        bus = self._bus
        push = self.reassembler.push
        batch: list[list] = []
        extra = self.diagnostics.extra
        for _ in range(self.config.max_frames_per_read):
            try:
                msg = bus.recv(timeout=0.0)
            except Exception as exc:  # noqa: BLE001 — whatever the interface raises is a bus fault
                self._bus_failed(exc, now)
                break
            if msg is None:
                break
            self._backoff_s = self.config.reopen_backoff_s  # the bus works again
            if msg.is_error_frame:
                self.diagnostics.bus_errors += 1
                extra["error_frames"] += 1
                continue
            cid = msg.arbitration_id
            if not msg.is_extended_id or msg.is_remote_frame:
                extra["malformed_frames"] += 1
                self.diagnostics.dropped_frames += 1
                continue
            dtid = (cid >> 8) & 0xFFFF
            if cid & 0x80 or dtid not in _IMU_TYPES:
                continue  # services and other messages on a shared bus are not faults
            src = cid & 0x7F
            if not self._accept_node(dtid, src):
                extra["foreign_frames"] += 1
                self.diagnostics.dropped_frames += 1
                continue
            tr = push(cid, msg.data, now)
            if tr is not None:
                p = self._on_transfer(tr)
                if p is not None:
                    batch.append(p)
        if batch:
            self._stamp(batch)
            overflow = len(self._pending) + len(batch) - self.config.max_pending_samples
            if overflow > 0:  # the reader fell behind: the deque drops the oldest
                extra["superseded_samples"] += overflow
            self._pending.extend(batch)
        self.reassembler.expire(now)
        self._sync_counters()

    def _accept_node(self, dtid: int, src: int) -> bool:
        if src == 0:
            return False  # anonymous nodes cannot be told apart
        if dtid != RAW_IMU_ID and self._mag_node is not None:
            return src == self._mag_node
        # until a RawIMU transfer names the IMU node, every node's frames are reassembled
        return self._imu_node is None or src == self._imu_node

    def _pin_imu_node(self, src: int) -> None:
        """Takes ``src``, the first node whose RawIMU arrived, as the IMU node."""
        self._imu_node = src
        self._stream = self._new_stream_guard()
        if self._mag_node is None and src in self._early_mag:
            self._mag, self._mag_fresh = self._early_mag[src], True
        self._early_mag.clear()
        # the other nodes' transfers under way are foreign from now on
        types = _IMU_TYPES if self._mag_node is None else (RAW_IMU_ID,)
        frames = self.reassembler.discard(types, (src,) if self._mag_node is None else (src, self._mag_node))
        self.diagnostics.extra["foreign_frames"] += frames
        _log.info("DroneCAN IMU node %d: the first node sending RawIMU", src)

    def _report_conflicts(self, stream: NodeStreamGuard) -> None:
        """A second sender with the IMU node's id: said once per sender recognised."""
        if stream.conflicts == self._conflicts_reported:
            return
        self._conflicts_reported = stream.conflicts
        text = (f"DroneCAN node {self._imu_node}: a second sender uses this node id (RawIMU transfer ids "
                "and timestamps of two sequences interleave); keeping the first sender's stream, "
                "dropping the other's (conflict_samples)")
        self.diagnostics.last_error = text
        _log.warning(text)

    def _on_transfer(self, tr: Transfer) -> list | None:
        """Handles one transfer; a RawIMU one gives a new sample ``[t_ns, usec, gyr, acc, mag_new, mag, node]``."""
        extra = self.diagnostics.extra
        try:
            if tr.data_type_id == RAW_IMU_ID:
                usec, gyr, acc = unpack_raw_imu(tr.payload)
            else:
                if tr.data_type_id == MAG2_ID:
                    sid, mag = unpack_mag2(tr.payload)
                    if self.config.mag_sensor_id is not None and sid != self.config.mag_sensor_id:
                        return None
                else:
                    mag = unpack_mag(tr.payload)
                if self._imu_node is None and self._mag_node is None:
                    self._early_mag[tr.source_node_id] = mag  # whose field it is is not known yet
                else:
                    self._mag, self._mag_fresh = mag, True
                return None
        except ValueError as exc:
            extra["malformed_frames"] += 1
            self.diagnostics.last_error = str(exc)
            return None
        if self._imu_node is None:
            self._pin_imu_node(tr.source_node_id)
        stream = self._stream
        assert stream is not None  # set with the IMU node
        # the same reading is never delivered twice, nor a second sender's merged in
        verdict = stream.admit(tr.transfer_id, usec, tr.payload, tr.t_ns)
        self._report_conflicts(stream)
        if verdict is not Verdict.DELIVER:
            return None
        if self.config.negate_acc:
            acc = (-acc[0], -acc[1], -acc[2])
        # t_ns is filled in by _stamp once the whole batch is known; until then the host time
        # of the transfer's first frame
        p = [tr.t_ns, usec, gyr, acc, self._mag_fresh, self._mag, tr.source_node_id]
        self._mag_fresh = False
        return p

    def _stamp(self, batch: list[list]) -> None:
        """Host-clock times of the samples received in one drain, ``batch``.

        Frames read in one batch share one receive time, and the newest sample of a batch
        has waited least, so only the batch's smallest (receive − sensor) difference feeds
        the offset estimate; every sample of the batch is then mapped with that offset.
        Stamping each sample on its own would squash a backlog onto the receive time.
        """
        timed = [p for p in batch if p[1] != 0]
        cm = self.clock_map
        if timed:
            best = min(timed, key=lambda p: p[0] - p[1] * 1000)
            cm.update(best[1], best[0])
        last = self._last_t_ns
        for p in batch:
            # a node without time (usec 0): its first frame's receive time is all we have
            t_ns = cm.to_host(p[1]) if p[1] != 0 else p[0]
            if t_ns <= last:  # an offset update must not reorder delivered samples
                t_ns = last + 1
            p[0] = last = t_ns
        self._last_t_ns = last

    def _sync_counters(self) -> None:
        st = self.reassembler.stats
        d = self.diagnostics
        e = d.extra
        # the reassembler drops whole transfers; fold its counts into the shared fields
        d.dropped_frames += st.dropped_frames - self._reasm_dropped
        self._reasm_dropped = st.dropped_frames
        d.incomplete_transfers = st.incomplete
        e["out_of_order_transfers"] = st.out_of_order
        e["crc_errors"] = st.crc_errors
        e["malformed_transfers"] = st.malformed
        e["sensor_clock_resets"] = self.clock_map.resets
        stream = self._stream
        if stream is not None:
            e["stale_samples"] = stream.duplicates + stream.stale
            e["out_of_sequence_samples"] = stream.out_of_sequence
            e["conflict_samples"] = stream.conflict_samples
            e["conflict_samples_delivered"] = stream.conflict_delivered
            e["node_id_conflicts"] = stream.conflicts
            e["node_restarts"] = stream.restarts

    @property
    def node_id(self) -> int | None:
        """The IMU node in use (configured, or the first one heard sending RawIMU), None before any."""
        return self._imu_node


def _finite(v: tuple[float, float, float]) -> bool:
    return math.isfinite(v[0]) and math.isfinite(v[1]) and math.isfinite(v[2])


__all__ = ["DroneCanConfig", "DroneCanImuSource"]
