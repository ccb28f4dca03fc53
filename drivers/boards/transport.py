"""Boards of today's IMUs as :class:`~ahrs_service.core.samples.ImuSource`: FIFO bursts.

A :class:`FifoBoard` reads its part's FIFO in bursts (status + count in one transfer, the
packets in transfers of at most what the transport carries), timestamps each row on the
sensor's clock (:class:`~ahrs_service.core.sample_clock.SensorClock`), and hands the rows out
as a :class:`~ahrs_service.core.samples.SampleBlock` (``read_block``) or one
:class:`~ahrs_service.core.samples.ImuSample` per row (``read``, ``may_have_backlog``).

Loss accounting: ``diagnostics.lost`` (:class:`~ahrs_service.core.samples.LossCounts`):
``fifo_overflow`` — samples the full FIFO turned away, estimated from the sensor clock at
the FIFO reset; ``bus_error`` — samples produced while the part was unreachable;
``diagnostics.extra["fifo_overflows"]`` counts the events. The block after a loss carries it
in ``lost``; its first row's time shows the gap (a long dt, never fake samples).

Faults: a failed transfer is retried and counted; a part that keeps failing is marked lost
and configured again at most every ``reinit_period_s``.
"""

from __future__ import annotations

from collections import deque
from typing import Any, Callable

import numpy as np

from ahrs_service.core.sample_clock import SensorClock
from ahrs_service.core.samples import (
    ImuSample,
    ImuSource,
    LossCounts,
    SampleBlock,
    bus_simulation_cpu_s,
)
from ahrs_service.drivers.device import DeviceIdentityError, watermark_frames
from ahrs_service.drivers.fifo import FifoTimeline, LevelRead, burst_flags, hold_pairing, latch_bounds
from ahrs_service.drivers.parts import icm42688p
from ahrs_service.drivers.sim.bus import twin_behind
from ahrs_service.drivers.transport import RegisterTransport, check_bus_rate


class FifoBoard(ImuSource):
    """Base of the FIFO boards: one main part, polled in bursts."""

    NAME = ""
    has_mag = False
    may_have_backlog = True
    times_on_sensor_clock = True  # each row timed by its position in the burst
    #: the FIFO watermark line, when wired (``source.drdy_gpio``); the service then waits on it
    data_ready_line = None
    #: bursts per second the watermark is set for (the data-ready line's edge rate), Hz
    wakeup_rate_hz = 1000.0
    #: whether the part raises a FIFO watermark interrupt a data-ready line can wait for
    HAS_WATERMARK_LINE = True
    #: samples the part's FIFO holds (a burst reads at most this many)
    FIFO_FRAMES = 128

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
        self._drained: deque[SampleBlock] = deque()  # rows drained, not handed out yet
        #: the part's samples on its own clock: indices, times, losses (drivers/fifo.py)
        self.timeline: FifoTimeline | None = None
        self._overflow_pending = False
        self.diagnostics.extra["fifo_overflows"] = 0
        self._drain_started_ns: int | None = None  # the last drain's start (_note_drain_window)

    @property
    def simulation_cpu_s(self) -> float | None:
        return bus_simulation_cpu_s(self.bus)

    @property
    def clock(self) -> SensorClock | None:
        """The row part's sensor clock (its tracked rate: ``clock.rate_hz``)."""
        return None if self.timeline is None else self.timeline.clock

    def _kw(self) -> dict[str, Any]:
        return {"diagnostics": self.diagnostics, "retries": self.retries}

    def _latch(self, transport: RegisterTransport | None = None) -> dict[str, int]:
        """Where in a level read the part latches it: after its command phase (SPI: the
        data phase after it is a µs or two, not counted)."""
        transport = self.transport if transport is None else transport
        return latch_bounds(transport.kind, transport.clock_hz)

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        self._configure()
        self._opened = True
        self._sim_base = self._sim_fifo_dropped() if self.transport.simulated else 0

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
        self.timeline.missed(self.transport.now_ns())
        self.lost = False
        self.diagnostics.device_lost = False
        self.diagnostics.reinitialisations += 1
        return True

    # ------------------------------------------------------------------ samples
    #: rows the host may hold drained but not handed out, in FIFO depths: beyond that (a
    #: consumer slower than the part) the FIFO is left to fill and its overflow is counted
    HOST_QUEUE_DEPTHS = 4

    def read_block(self, max_samples: int = 128) -> SampleBlock:
        """At most ``max_samples`` rows, oldest first (empty: nothing new, or the part is lost).

        Every call empties the part's FIFO (all whole packets, in as few transfers as the
        transport carries) and keeps the rows beyond ``max_samples`` on the host for the next
        calls: a consumer that takes a few rows a tick after a stall must not leave the FIFO
        near full while it catches up (at 1 kHz an 80 ms stop on a busy host left the 102-
        sample FIFO 2–3 samples short of full, and taking 16 rows a tick filled it). A block
        ends at a loss: the rows after a gap come in the next call."""
        if not self._opened:
            raise RuntimeError(f"{self.NAME} on {self.transport.where}: read before open()")
        if (not self.lost or self._recover()) and \
                self.pending < self.HOST_QUEUE_DEPTHS * self.FIFO_FRAMES:
            started = self.transport.now_ns()
            try:
                block = self._burst(self.FIFO_FRAMES)
            except OSError as exc:
                self._mark_lost(exc)
            else:
                if len(block) or block.lost.total:
                    self._drained.append(block)
            self._note_drain_window(started)
            if self.transport.simulated:
                # the twin's own count of the samples its FIFO turned away or had flushed
                # unread since the first read, beside the driver's estimate (the stall tests)
                self.diagnostics.extra["sim_fifo_dropped"] = self._sim_fifo_dropped() - self._sim_base
        # the queued rows, oldest first, up to max_samples and up to the next loss
        taken: list[SampleBlock] = []
        room = max_samples
        while self._drained and room > 0 and (not taken or not self._drained[0].lost.total):
            first = self._drained[0]
            if len(first) <= room:
                taken.append(self._drained.popleft())
            else:
                head, self._drained[0] = first.split(room)
                taken.append(head)
            room -= len(taken[-1])
        return SampleBlock.concat(taken) if taken else SampleBlock.empty()

    @property
    def late_tolerance_s(self) -> float:  # type: ignore[override]
        """The FIFO's depth at the part's rate less one wake-up's worth, s: how late a drain
        may come before the FIFO overflows."""
        return max(0.0, self.FIFO_FRAMES / self.odr_hz - 1.0 / self.wakeup_rate_hz)

    def _note_drain_window(self, started_ns: int) -> None:
        """``diagnostics.extra["fifo_longest_window_ms"]``: the longest time from one drain's
        start (its level read, which decides what it pops) to the end of the next, ms, since
        the first read — an upper bound of the time the FIFO had to hold its samples. An
        overflow with this under the FIFO's depth is the driver's fault, not the host's."""
        if self._drain_started_ns is not None:
            window_ms = (self.transport.now_ns() - self._drain_started_ns) / 1e6
            if window_ms > self.diagnostics.extra.get("fifo_longest_window_ms", 0.0):
                self.diagnostics.extra["fifo_longest_window_ms"] = window_ms
        self._drain_started_ns = started_ns

    @property
    def pending(self) -> int:
        """Rows drained from the FIFO that have not been handed out yet."""
        return sum(len(b) for b in self._drained) + len(self._rows)

    def read(self) -> ImuSample | None:
        """The oldest row not yet handed out (a burst is read when none is left)."""
        if not self._rows:
            block = self.read_block()
            if not len(block):
                return None
            self._rows.extend(block.samples())
        return self._rows.popleft()

    def _burst(self, max_samples: int) -> SampleBlock:
        raise NotImplementedError

    @staticmethod
    def _flush_counting_loss(flush: Callable[[], None], timeline: FifoTimeline,
                             transport: RegisterTransport) -> None:
        """Empties an overflowed FIFO (``flush``) and counts the samples it turned away: the
        flush's transfer, from its start to its end on ``transport``'s clock, bounds the first
        sample after it (:meth:`FifoTimeline.overflowed`)."""
        started = transport.now_ns()
        flush()
        timeline.overflowed(started, transport.now_ns())

    def _stale_start(self, part: Any) -> bool:
        """An overflow found before the first read was timed (the FIFO filled between
        ``open`` and the consumer's first read: the service sets up its log and links in
        between): those samples predate the consumer, not a loss — the FIFO is flushed and
        nothing counted (as on the I2C boards). True when that was the case."""
        if self.timeline.started:
            return False
        part.flush()
        self._overflow_pending = False
        if self.transport.simulated:
            twin_behind(self.transport).take_popped_truth()
            self._sim_base = self._sim_fifo_dropped()
        return True

    def _sim_fifo_dropped(self) -> int:
        fifo = twin_behind(self.transport).fifo
        return fifo.dropped + fifo.discarded

    def _take_loss(self) -> LossCounts:
        return self.timeline.take_loss()

    def _empty(self) -> SampleBlock:
        """No rows: an empty block, carrying a loss found meanwhile."""
        return SampleBlock.empty(self._take_loss()) if self.timeline.loss_pending else SampleBlock.empty()

    def _flags(self, gyr_counts: np.ndarray, acc_counts: np.ndarray, gfs: int, afs: int) -> np.ndarray:
        return burst_flags(gyr_counts, acc_counts, gfs, afs, self.diagnostics)


class ICM42688PBoard(FifoBoard):
    """ICM-42688-P on SPI (``/dev/spidevB.C``) or I2C (0x68/0x69).

    odr_hz: 100 … 8000; watermark: samples per burst (default ``odr_hz / fifo_read_hz``);
    fifo_read_hz: the burst (wake-up) rate the watermark is set for, default 500 Hz: 16
    samples a burst at 8 kHz, 2 ms of the FIFO's 12.7 ms. Each wake-up costs this Python loop
    about as much as a burst's samples do, so halving the wake-ups takes a clear share of a
    core off the service at 8 kHz (figures: benchmarks/README.md, "8 kHz ICM-42688-P"); PX4's
    C driver reads every 1.25 ms.
    """

    NAME = "icm42688p"
    PART = icm42688p.ICM42688P
    FIFO_FRAMES = icm42688p.FIFO_BYTES // icm42688p.PACKET
    #: the default ``fifo_read_hz``
    FIFO_READ_HZ = 500.0

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1000,
                 fifo_read_hz: float = FIFO_READ_HZ, watermark: int | None = None, **kw: Any) -> None:
        super().__init__(transport, **kw)
        if not 1 <= fifo_read_hz <= 8000:
            raise ValueError(f"icm42688p fifo_read_hz must be 1…8000 Hz, got {fifo_read_hz}")
        if watermark is None:
            # one sample of room short of the I2C twins' rule: the driver takes ≤ depth − 2
            watermark = watermark_frames(odr_hz, fifo_read_hz, icm42688p.ICM42688P.FIFO_SAMPLES - 1)
        self.part = icm42688p.ICM42688P(transport, odr_hz=odr_hz, watermark=watermark, **self._kw())
        self.odr_hz = float(odr_hz)
        self.wakeup_rate_hz = self.odr_hz / watermark
        # per burst besides the packets: the level read, and the status again ahead of the data
        check_bus_rate(transport, "source.board_options.odr_hz", self.odr_hz, icm42688p.PACKET,
                       min(self.odr_hz, self.odr_hz / watermark), 2 * icm42688p.STATUS_BYTES, "ICM-42688-P")

    def _configure(self) -> None:
        self.part.configure()
        if self.timeline is None:
            self.timeline = FifoTimeline(self.odr_hz, self.diagnostics, **self._latch())

    def _burst(self, max_samples: int) -> SampleBlock:
        part = self.part
        # the anchor: the part latches its level during this transfer, the newest sample
        # counted is at most its command phase younger than the transfer's start
        host = self.transport.now_ns()
        status, count = part.read_status()
        host_done = self.transport.now_ns()
        if count > icm42688p.FIFO_BYTES:
            # a count the part cannot hold: a garbled transfer or no part (SPI reads 0xFF)
            raise OSError(5, f"FIFO count {count} > {icm42688p.FIFO_BYTES}: bad transfer or part gone")
        # FIFO_FULL clears on reading INT_STATUS: remember it until the FIFO is drained
        self._overflow_pending |= bool(status & icm42688p.FIFO_FULL_INT)
        # the level read found the FIFO filled: its newest sample is older than the read
        full = self._overflow_pending
        packets = min(count // icm42688p.PACKET, max_samples)
        if packets == 0:
            return self._empty()
        # the packets come after INT_STATUS and the count again, in the same transfer (PX4):
        # a FIFO that filled after the level read is known with the packets it follows —
        # the oldest, contiguous with the last burst (stop-on-full) — not a drain later,
        # mixed with what came after the turned-away samples
        data_started = self.transport.now_ns()
        status, count_now, pk = part.read_status_and_packets(packets * icm42688p.PACKET)
        data_done = self.transport.now_ns()
        if count_now > icm42688p.FIFO_BYTES:
            raise OSError(5, f"FIFO count {count_now} > {icm42688p.FIFO_BYTES}: bad transfer or part gone")
        filled_since = bool(status & icm42688p.FIFO_FULL_INT)
        self._overflow_pending |= filled_since
        # reset after these packets: they emptied the FIFO, or it filled since the level
        # read (the rest of it is flushed and counted with the turned-away samples)
        drained = packets * icm42688p.PACKET > count_now - icm42688p.PACKET or filled_since
        overflow = self._overflow_pending
        if overflow and self._stale_start(part):
            return SampleBlock.empty()
        header = pk["header"]
        invalid = icm42688p.invalid_packets(pk)
        # every packet valid (the usual burst): the arrays as decoded, not copied through the mask
        every = invalid is None
        ok = None if every else ~invalid
        # a level read held up around its latch while the run's first reads place the clock:
        # the data transfer's count bounds it too (free: read with the packets)
        then = None
        if self.timeline.wants_second_look(host, host_done):
            then = LevelRead(data_started, data_done, count_now // icm42688p.PACKET, full or filled_since)
        # a full FIFO's newest sample is older than the read: timed from the clock's fit
        t = self.timeline.stamp(host, len(header), full=full, read_end_ns=host_done,
                                level=count // icm42688p.PACKET, then=then)
        if not every:
            t = t[ok]
        lost = self._take_loss()  # after stamping: a gap before these rows is counted by it
        if overflow and drained:  # stop-on-full: the rest after
            self._flush_counting_loss(part.flush, self.timeline, self.transport)
            self._overflow_pending = False
        n = len(header) if every else int(ok.sum())
        self.diagnostics.samples += n
        gyr_c, acc_c, temp_c = pk["gyr"], pk["acc"], pk["temp"]
        if not every:
            gyr_c, acc_c, temp_c = gyr_c[ok], acc_c[ok], temp_c[ok]
        truth = None
        if self.transport.simulated:  # the twin hands over the truth of the packets just read
            popped = twin_behind(self.transport).take_popped_truth()
            rows = popped[:len(header)] if every else [q for q, good in zip(popped, ok.tolist()) if good]
            if rows and all(q is not None for q in rows):
                truth = np.array(rows, dtype=float)
        return SampleBlock(
            t_ns=t, gyr=gyr_c * part.gyro_scale, acc=acc_c * part.acc_scale,
            mag=np.full((n, 3), np.nan),
            flags=self._flags(gyr_c, acc_c, part.gyro_full_scale, part.acc_full_scale),
            temperature_c=np.asarray(part.temperature_c(temp_c), dtype=float),  # float64 already: no copy
            raw={"gyr": gyr_c, "acc": acc_c}, truth_q=truth, lost=lost)


class BMI088Board(FifoBoard):
    """Bosch BMI088 on SPI: the gyroscope die (``transport``, drives the rows) and the
    accelerometer die (``acc_transport``, one dummy byte per read), each with its FIFO.

    **Pairing rule** (two dies, two oscillators; :func:`~ahrs_service.drivers.fifo.hold_pairing`,
    shared with the I2C boards): every gyroscope sample is one row; its accelerometer value
    is the newest accelerometer sample whose own sensor-clock time is at or before the row's
    time (zero-order hold, never a sample from the row's future). Rows before the first
    accelerometer sample after start are not emitted. The accelerometer's
    overflows are counted in ``diagnostics.extra["acc_fifo_overflows"]`` (they cost no rows:
    the held value bridges them) and do not count as lost samples.

    odr_hz: gyro 100/200/400/1000/2000; acc_odr_hz: 100…1600; watermark: gyro frames per
    burst (default ``odr_hz / fifo_read_hz``); ranges: gyro_range_dps, acc_range_g.
    """

    NAME = "bmi088"
    FIFO_FRAMES = 100  # the gyroscope die's FIFO (bmi088.GYRO_FIFO_FRAMES)
    #: accelerometer samples held for pairing at most: the rows the host may queue
    #: (``HOST_QUEUE_DEPTHS`` gyroscope FIFOs) span this many at 1 600 Hz beside 2 000 Hz
    ACC_HELD_MAX = 1024

    def __init__(self, transport: RegisterTransport, *, acc_transport: RegisterTransport,
                 odr_hz: float = 2000, acc_odr_hz: float = 1600, gyro_range_dps: int = 2000,
                 acc_range_g: int = 24, fifo_read_hz: float = 1000, watermark: int | None = None,
                 **kw: Any) -> None:
        from ahrs_service.drivers.parts import bmi088

        super().__init__(transport, **kw)
        self.acc_transport = acc_transport
        if not 1 <= fifo_read_hz <= 2000:
            raise ValueError(f"bmi088 fifo_read_hz must be 1…2000 Hz, got {fifo_read_hz}")
        if odr_hz not in bmi088.GYRO_ODR_CODES:
            raise ValueError(f"BMI088 odr_hz must be one of {sorted(bmi088.GYRO_ODR_CODES)}, got {odr_hz}")
        if watermark is None:
            watermark = watermark_frames(odr_hz, fifo_read_hz, bmi088.GYRO_FIFO_FRAMES - 1)
        self.gyro = bmi088.BMI088Gyro(transport, odr_hz=odr_hz, range_dps=gyro_range_dps,
                                      watermark=watermark, **self._kw())
        acc_wm = max(1, int(round(acc_odr_hz / (odr_hz / watermark))))
        self.acc = bmi088.BMI088Accel(acc_transport, odr_hz=acc_odr_hz, range_g=acc_range_g,
                                      watermark=acc_wm, **self._kw())
        self.part = self.gyro
        self.odr_hz = float(odr_hz)
        self.wakeup_rate_hz = self.odr_hz / watermark
        self._bmi = bmi088
        self.diagnostics.extra["acc_fifo_overflows"] = 0
        check_bus_rate(transport, "source.board_options.odr_hz", self.odr_hz, bmi088.GYRO_FRAME,
                       min(self.odr_hz, self.wakeup_rate_hz), 1, "BMI088 gyroscope")
        check_bus_rate(acc_transport, "source.board_options.acc_odr_hz", float(acc_odr_hz),
                       bmi088.ACC_FRAME, min(float(acc_odr_hz), self.wakeup_rate_hz), 2,
                       "BMI088 accelerometer")

    def _configure(self) -> None:
        self.acc.configure()
        self.gyro.configure()
        if self.timeline is None:
            self.timeline = FifoTimeline(self.odr_hz, self.diagnostics, **self._latch())
            # the accelerometer's samples are held by the pairing rule: its overflows cost
            # no rows, they are counted as events
            self.acc_timeline = FifoTimeline(self.acc.odr_hz, self.diagnostics,
                                             **self._latch(self.acc_transport),
                                             events_key="acc_fifo_overflows", rows=False)
            self._acc_t = np.empty(0, np.int64)
            self._acc_c = np.empty((0, 3), np.int64)

    def _read_acc(self) -> None:
        bmi = self._bmi
        host = self.acc_transport.now_ns()  # the level read's start: the anchor
        level = self.acc.read_level()
        host_done = self.acc_transport.now_ns()
        counts, full = self.acc.read_frames(level // bmi.ACC_FRAME * bmi.ACC_FRAME)
        if len(counts):
            t = self.acc_timeline.stamp(host, len(counts), full=full, read_end_ns=host_done)
            # every accelerometer sample a gyroscope row not read yet can still take: a
            # burst that took fewer rows than its FIFO held (a host held after the level
            # read, max_samples) leaves rows older than this read's samples, which keeping
            # only the newest old one dropped unpaired and uncounted; trimmed after pairing
            self._acc_t = np.concatenate([self._acc_t, t])[-self.ACC_HELD_MAX:]
            self._acc_c = np.concatenate([self._acc_c, counts])[-self.ACC_HELD_MAX:]
        if full:
            self._flush_counting_loss(self.acc.flush, self.acc_timeline, self.acc_transport)

    def _burst(self, max_samples: int) -> SampleBlock:
        gyro = self.gyro
        # the anchor: the part latches its level during this transfer, the newest sample
        # counted is at most its command phase younger than the transfer's start
        host = self.transport.now_ns()
        frames, overrun = gyro.read_status()
        host_done = self.transport.now_ns()
        self._overflow_pending |= overrun
        then = None
        if self.timeline.wants_second_look(host, host_done):
            look = self.transport.now_ns()
            frames_then, overrun_then = gyro.read_status()
            self._overflow_pending |= overrun_then
            then = LevelRead(look, self.transport.now_ns(), frames_then, self._overflow_pending)
        take = min(frames, max_samples)
        g = gyro.read_frames(take) if take else np.empty((0, 3), np.int64)
        self._read_acc()
        if take == 0:
            return self._empty()
        overflow = self._overflow_pending
        if overflow and self._stale_start(gyro):
            twin_behind(self.transport).take_popped_truth()
            return SampleBlock.empty()
        t = self.timeline.stamp(host, take, full=overflow, read_end_ns=host_done, level=frames, then=then)
        lost = self._take_loss()  # after stamping: a gap before these rows is counted by it
        if overflow and take == frames:
            self._flush_counting_loss(gyro.flush, self.timeline, self.transport)
            self._overflow_pending = False
        idx = hold_pairing(t, self._acc_t)  # the rule of drivers/fifo.py
        acc_c = self._acc_c
        if len(idx) and idx[-1] > 0:  # later rows pair with the newest row's sample or after it
            first_needed = int(idx[-1])
            self._acc_t, self._acc_c = self._acc_t[first_needed:], acc_c[first_needed:]
        ok = idx >= 0
        truth = None
        if self.transport.simulated:
            popped = twin_behind(self.transport).take_popped_truth()
            rows = [q for q, good in zip(popped, ok) if good]
            if rows and all(q is not None for q in rows):
                truth = np.array(rows, dtype=float)
        g, t, idx = g[ok], t[ok], idx[ok]
        a = acc_c[idx]
        n = len(t)
        self.diagnostics.samples += n
        return SampleBlock(
            t_ns=t, gyr=g * gyro.scale, acc=a * self.acc.scale, mag=np.full((n, 3), np.nan),
            flags=self._flags(g, a, gyro.full_scale, self.acc.full_scale).astype(np.int64),
            temperature_c=np.full(n, np.nan), raw={"gyr": g, "acc": a}, truth_q=truth, lost=lost)


class ICM20948Board(FifoBoard):
    """ICM-20948 with its AK09916 (through the part's auxiliary I2C master), SPI or I2C.

    Each FIFO packet carries accelerometer, gyro and the AK09916's ST1 … ST2 as slave 0 read
    them at that sample: a row has ``MAG_NEW`` exactly when ST1.DRDY is set in its packet
    (the master reads ST2 each sample, which clears DRDY until the next measurement). The
    field is in the accelerometer's axes (X, −Y, −Z of the die). No watermark line: timer
    polling at ``fifo_read_hz`` (the FIFO holds 21 ms at 1125 Hz).
    """

    NAME = "icm20948"
    FIFO_FRAMES = 512 // 21 + 4  # icm20948.FIFO_BYTES // PACKET, and the count's slack (FIFO_BYTES + 64)
    has_mag = True
    HAS_WATERMARK_LINE = False

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1125, gyro_range_dps: int = 2000,
                 acc_range_g: int = 16, mag_rate_hz: float = 100, fifo_read_hz: float = 250, **kw: Any) -> None:
        from ahrs_service.drivers.parts import icm20948

        super().__init__(transport, **kw)
        self._icm = icm20948
        self.part = icm20948.ICM20948(transport, odr_hz=odr_hz, gyro_range_dps=gyro_range_dps,
                                      acc_range_g=acc_range_g, mag_rate_hz=mag_rate_hz, **self._kw())
        self.odr_hz = self.part.odr_hz
        self.wakeup_rate_hz = float(fifo_read_hz)
        check_bus_rate(transport, "source.board_options.odr_hz", self.odr_hz, icm20948.PACKET,
                       min(self.odr_hz, fifo_read_hz), 3, "ICM-20948")

    def _configure(self) -> None:
        self.part.configure()
        if self.timeline is None:
            self.timeline = FifoTimeline(self.odr_hz, self.diagnostics, **self._latch())

    def _burst(self, max_samples: int) -> SampleBlock:
        from ahrs_service.core.samples import MAG_NEW, MAG_SATURATED, MAG_VALID

        icm, part = self._icm, self.part
        # the anchor: the part latches its level during this transfer, the newest sample
        # counted is at most its command phase younger than the transfer's start
        host = self.transport.now_ns()
        overflow, count = part.read_status()
        host_done = self.transport.now_ns()
        if count > icm.FIFO_BYTES + 64:
            raise OSError(5, f"FIFO count {count} > {icm.FIFO_BYTES}: bad transfer or part gone")
        self._overflow_pending |= overflow
        then = None
        if self.timeline.wants_second_look(host, host_done):
            look = self.transport.now_ns()
            overflow_then, count_then = part.read_status()
            self._overflow_pending |= overflow_then
            then = LevelRead(look, self.transport.now_ns(), count_then // icm.PACKET, self._overflow_pending)
        packets = min(count // icm.PACKET, max_samples)
        if packets == 0:
            return self._empty()
        p = part.read_packets(packets)
        drained = packets * icm.PACKET > count - icm.PACKET
        overflow = self._overflow_pending
        if overflow and self._stale_start(part):
            return SampleBlock.empty()
        t = self.timeline.stamp(host, packets, full=overflow, read_end_ns=host_done,
                                level=count // icm.PACKET, then=then)
        lost = self._take_loss()  # after stamping: a gap before these rows is counted by it
        if overflow and drained:
            self._flush_counting_loss(part.flush, self.timeline, self.transport)
            self._overflow_pending = False
        acc_c, gyr_c = p[:, 0:3], p[:, 3:6]
        st1, mag_c, st2 = p[:, 6], p[:, 7:10], p[:, 11]
        new = (st1 & 0x01) != 0
        hofl = (st2 & 0x08) != 0
        mag = np.where(new[:, None], part.mag_to_board(mag_c), np.nan)
        flags = self._flags(gyr_c, acc_c, part.gyro_full_scale, part.acc_full_scale)
        flags |= np.where(new, MAG_NEW | np.where(hofl, MAG_SATURATED, MAG_VALID), 0)
        self.diagnostics.samples += packets
        truth = None
        if self.transport.simulated:
            rows = twin_behind(self.transport).take_popped_truth()
            if rows and all(q is not None for q in rows):
                truth = np.array(rows, dtype=float)
        return SampleBlock(
            t_ns=t, gyr=gyr_c * part.gyro_scale, acc=acc_c * part.acc_scale, mag=mag,
            flags=flags.astype(np.int64), temperature_c=np.full(packets, np.nan),
            raw={"gyr": gyr_c, "acc": acc_c, "mag": mag_c}, truth_q=truth, lost=lost)
