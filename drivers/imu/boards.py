"""Boards of today's IMUs as :class:`~ahrs_service.drivers.base.ImuSource`: FIFO bursts.

A :class:`FifoBoard` reads its part's FIFO in bursts (status + count in one transfer, the
packets in transfers of at most what the transport carries), timestamps each row on the
sensor's clock (:class:`~ahrs_service.drivers.fifo.SensorClock`), and hands the rows out
as a :class:`~ahrs_service.drivers.fifo.FifoBlock` (``read_block``) or one
:class:`~ahrs_service.drivers.base.ImuSample` per row (``read``, ``may_have_backlog``).

Loss accounting (``diagnostics.extra``): ``fifo_overflows`` (events), ``lost_overflow``
(samples the full FIFO could not take, estimated from the sensor clock at the FIFO reset),
``lost_bus_error`` (samples produced while the part was unreachable). A burst after a loss
carries ``lost_before``; its first row's time shows the gap (a long dt, no fake samples).

Faults: a failed transfer is retried and counted; a part that keeps failing is marked lost
and configured again at most every ``reinit_period_s``.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ahrs_service.drivers.base import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    ImuSample,
    ImuSource,
)
from ahrs_service.drivers.fifo import FifoBlock, SensorClock
from ahrs_service.drivers.i2c.device import DeviceIdentityError
from ahrs_service.drivers.imu import icm42688p
from ahrs_service.drivers.transport import RegisterTransport, check_bus_rate

_NAN3 = np.full(3, np.nan)


class FifoBoard(ImuSource):
    """Base of the FIFO boards: one main part, polled in bursts."""

    NAME = ""
    has_mag = False
    may_have_backlog = True
    #: the FIFO watermark line, when wired (``source.drdy_gpio``); the service then waits on it
    data_ready_line = None
    #: bursts per second the watermark is set for (the data-ready line's edge rate), Hz
    wakeup_rate_hz = 1000.0

    def __init__(self, transport: RegisterTransport, *, retries: int = 2,
                 reinit_period_s: float = 0.05, own_bus: Any = None) -> None:
        super().__init__()
        self.transport = transport
        self.bus = getattr(transport, "bus", None)
        self.own_bus = own_bus
        self.retries = retries
        self.reinit_period_ns = int(reinit_period_s * 1e9)
        self.lost = False
        self._last_attempt_ns = 0
        self._opened = False
        self._rows: deque[ImuSample] = deque()
        self.clock: SensorClock | None = None
        self._next_index = 0
        self._lost_pending = 0
        self._truth_rows: list | None = None
        for key in ("fifo_overflows", "lost_overflow", "lost_bus_error"):
            self.diagnostics.extra[key] = 0

    def _kw(self) -> dict[str, Any]:
        return {"diagnostics": self.diagnostics, "retries": self.retries}

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        self._configure()
        self._opened = True

    def _configure(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        self._opened = False
        if self.data_ready_line is not None:
            self.data_ready_line.close()
        if self.own_bus is not None:
            self.own_bus.close()

    # ------------------------------------------------------------------ faults
    def _mark_lost(self, err: Exception) -> None:
        if not self.lost:
            self.lost = True
            self._last_attempt_ns = self.transport.now_ns()
        self.diagnostics.device_lost = True
        self.diagnostics.last_error = f"{self.NAME} lost: {err}"

    def _recover(self) -> bool:
        now = self.transport.now_ns()
        if now - self._last_attempt_ns < self.reinit_period_ns:
            return False
        self._last_attempt_ns = now
        try:
            self._configure()
        except (OSError, DeviceIdentityError) as exc:
            self.diagnostics.last_error = f"{self.NAME} still lost: {exc}"
            return False
        # the samples the part would have produced meanwhile are lost (bus error)
        if self.clock is not None and self.clock._idx:
            idx = self.clock.index_at(self.transport.now_ns())
            lost = max(0, idx + 1 - self._next_index)
            self.diagnostics.extra["lost_bus_error"] += lost
            self._next_index += lost
            self._lost_pending += lost
        self.lost = False
        self.diagnostics.device_lost = False
        self.diagnostics.reinitialisations += 1
        return True

    # ------------------------------------------------------------------ samples
    def read_block(self) -> FifoBlock | None:
        """The rows read from the FIFO now (None: nothing new, or the part is lost)."""
        if not self._opened:
            raise RuntimeError(f"{self.NAME} on {self.transport.where}: read before open()")
        if self.lost and not self._recover():
            return None
        try:
            return self._burst()
        except OSError as exc:
            self._mark_lost(exc)
            return None

    def read(self) -> ImuSample | None:
        """The oldest row not yet handed out (a burst is read when none is left)."""
        if not self._rows:
            block = self.read_block()
            if block is None or not len(block):
                return None
            self._rows.extend(self.rows(block))
        return self._rows.popleft()

    def rows(self, block: FifoBlock) -> list[ImuSample]:
        """One :class:`ImuSample` per row of ``block`` (the adapter for per-sample consumers)."""
        truth = self._truth(len(block))
        out = []
        for i in range(len(block)):
            t = block.temperature_c[i]
            out.append(ImuSample(int(block.t_ns[i]), block.gyr[i], block.acc[i], None,
                                 int(block.flags[i]),
                                 {"gyr": block.raw_gyr[i].tolist(), "acc": block.raw_acc[i].tolist()},
                                 truth[i] if truth is not None else None,
                                 None if t != t else float(t)))
        return out

    def _truth(self, n: int) -> list | None:
        return None

    def _burst(self) -> FifoBlock | None:
        raise NotImplementedError

    def _flags(self, gyr_counts: np.ndarray, acc_counts: np.ndarray, gfs: int, afs: int) -> np.ndarray:
        gsat = (np.abs(gyr_counts) >= gfs).any(axis=1)
        asat = (np.abs(acc_counts) >= afs).any(axis=1)
        flags = np.where(gsat, GYR_SATURATED, GYR_VALID) | np.where(asat, ACC_SATURATED, ACC_VALID)
        self.diagnostics.saturated += int(gsat.sum() + asat.sum())
        return flags


class ICM42688PBoard(FifoBoard):
    """ICM-42688-P on SPI (``/dev/spidevB.C``) or I2C (0x68/0x69).

    odr_hz: 100 … 8000; watermark: samples per burst (default ``odr_hz / fifo_read_hz``);
    fifo_read_hz: the burst (wake-up) rate the watermark is set for, default 1000 Hz.
    """

    NAME = "icm42688p"
    PART = icm42688p.ICM42688P

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1000,
                 fifo_read_hz: float = 1000, watermark: int | None = None, **kw: Any) -> None:
        super().__init__(transport, **kw)
        if not 1 <= fifo_read_hz <= 8000:
            raise ValueError(f"icm42688p fifo_read_hz must be 1…8000 Hz, got {fifo_read_hz}")
        if watermark is None:
            watermark = max(1, min(int(round(odr_hz / fifo_read_hz)), icm42688p.ICM42688P.FIFO_SAMPLES - 2))
        self.part = icm42688p.ICM42688P(transport, odr_hz=odr_hz, watermark=watermark, **self._kw())
        self.odr_hz = float(odr_hz)
        self.wakeup_rate_hz = self.odr_hz / watermark
        check_bus_rate(transport, "source.board_options.odr_hz", self.odr_hz, icm42688p.PACKET,
                       min(self.odr_hz, self.odr_hz / watermark), icm42688p.STATUS_BYTES, "ICM-42688-P")

    def _configure(self) -> None:
        self.part.configure()
        if self.clock is None:
            self.clock = SensorClock(self.odr_hz)

    def _burst(self) -> FifoBlock | None:
        part = self.part
        status, count = part.read_status()
        if count > icm42688p.FIFO_BYTES:
            # a count the part cannot hold: a garbled transfer or no part (SPI reads 0xFF)
            raise OSError(5, f"FIFO count {count} > {icm42688p.FIFO_BYTES}: bad transfer or part gone")
        if count < icm42688p.PACKET:
            return None
        pk = part.read_packets(count)
        host = self.transport.now_ns()
        if self.transport.simulated:  # the twin hands over the truth of the packets just read
            popped = _twin(self.transport).take_popped_truth()
        header = pk["header"]
        ok = ((header & 0xFC) == icm42688p.HIRES_HEADER) & \
            (pk["acc20"] != icm42688p.INVALID_20BIT).all(axis=1) & \
            (pk["gyr20"] != icm42688p.INVALID_20BIT).all(axis=1)
        n = int(ok.sum())
        if self.transport.simulated:
            self._truth_rows = [q for q, good in zip(popped, ok) if good]
        overflow = bool(status & icm42688p.FIFO_FULL_INT)
        first = self._next_index
        self._next_index += len(header)
        lost_before = self._lost_pending
        self._lost_pending = 0
        # a full FIFO's newest sample is older than the read: not a clock anchor
        t = self.clock.stamp(host, first, len(header), anchor=not overflow)[ok]
        if overflow:
            part.flush()
            d = self.diagnostics.extra
            d["fifo_overflows"] += 1
            produced = self.clock.index_at(self.transport.now_ns())
            lost = max(0, produced + 1 - self._next_index)
            d["lost_overflow"] += lost
            self._next_index += lost
            self._lost_pending = lost
        self.diagnostics.samples += n
        gyr_c, acc_c = pk["gyr"][ok], pk["acc"][ok]
        return FifoBlock(
            t_ns=t, gyr=gyr_c * part.gyro_scale, acc=acc_c * part.acc_scale,
            mag=np.full((n, 3), np.nan),
            flags=self._flags(gyr_c, acc_c, part.gyro_full_scale, part.acc_full_scale),
            temperature_c=part.temperature_c(pk["temp"][ok]), raw_gyr=gyr_c, raw_acc=acc_c,
            lost_before=lost_before)

    def _truth(self, n: int) -> list | None:
        return self._truth_rows


def _twin(transport: RegisterTransport) -> Any:
    bus = transport.bus
    return bus.device(transport.cs if transport.kind == "spi" else transport.address)
