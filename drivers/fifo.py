"""FIFO acquisition shared by today's IMUs: decoded bursts, the sensor clock, simulated FIFOs.

* :class:`SensorClock` — each sample's time from its index on the part's own output clock,
  with the part's real rate tracked against the host's monotonic clock: timestamps neither
  jitter with the host's read times nor drift from the host clock.
* :class:`FifoTimeline` — one FIFO part's sample indices, times and losses: every FIFO
  board stamps its bursts and counts its overflows and outages through it (one place).
* :class:`SimulatedFifo` and :class:`SimulatedFifoDevice` — the twins' side: a byte FIFO of
  the part's depth (stop-on-full or stream), filled with every sample due on a clock that
  runs ``clock_error`` off nominal (real parts are 0.5–2 % off).

Bursts are handed out as :class:`~ahrs_service.drivers.base.SampleBlock` (the sample-block
interface in ``drivers/base.py``).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ahrs_service.drivers.base import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    LossCounts,
    SourceDiagnostics,
)
from ahrs_service.drivers.i2c.device import SimulatedRegisterDevice


class SensorClock:
    """Sample times from sample indices on the part's clock, mapped onto the host clock.

    A part's samples are evenly spaced on its own oscillator, ``1 / rate`` apart, where the
    real rate is off the nominal one by the oscillator's error. Sample ``i`` is at
    ``offset + i · period``. ``period`` is the host time between the first anchor (the least
    late of the first 16 reads) and the least late read of the last ``window`` bursts, divided
    by the samples between them (read latency is a few 100 µs against seconds of span, and a
    read delayed by a host stall is never the one chosen); ``offset`` is the lower envelope
    of ``host_read − i_newest · period`` over the last ``window`` bursts — a read never
    happens before the newest sample it returns, so the smallest latency is the best
    estimate of none.
    """

    def __init__(self, nominal_rate_hz: float, window: int = 128, min_span_s: float = 0.2) -> None:
        self.nominal_period_ns = 1e9 / nominal_rate_hz
        self.period_ns = self.nominal_period_ns
        self._min_span = min_span_s * 1e9
        self._first: tuple[int, int] | None = None  # (index, host_ns)
        self._early: list[tuple[int, int]] = []  # the first 16 anchors (index, host_ns)
        self._idx = deque(maxlen=window)
        self._host = deque(maxlen=window)
        self._last_t: int | None = None
        self._anchors = 0

    @property
    def rate_hz(self) -> float:
        """The part's tracked real output rate, Hz."""
        return 1e9 / self.period_ns

    def stamp(self, host_ns: int, first_index: int, n: int, anchor: bool = True) -> np.ndarray:
        """Times (int64 ns, oldest first) of samples ``first_index … first_index + n − 1``,
        the newest of which was read out at ``host_ns``.

        anchor: False when the newest sample is known to be older than the read (a FIFO that
        was full): the burst is stamped from the current fit without updating it.
        """
        last = first_index + n - 1
        if anchor:
            self._anchors += 1
            if self._anchors <= 16:
                # the first reads: the period's far end is the least late of them, judged
                # with the period tracked so far (re-judged as it improves): one slow first
                # read (a start-up stall) must not bias the period for good, and judged with
                # the nominal period a part 1 % off picks a read up to a period late
                self._early.append((last, host_ns))
            self._idx.append(last)
            self._host.append(host_ns)
            p = self.period_ns
            i0, h0 = min(self._early, key=lambda ih: ih[1] - ih[0] * p)
            self._first = (i0, h0)
            if host_ns - h0 >= self._min_span:
                # the slope to the least late recent read: a read delayed by a host stall
                # (late by ms) must not tilt the period
                i1, h1 = min(zip(self._idx, self._host), key=lambda ih: ih[1] - ih[0] * p)
                if h1 - h0 >= self._min_span and i1 > i0:
                    self.period_ns = (h1 - h0) / (i1 - i0)
        if not self._idx:  # no anchor yet (a first burst from a full FIFO): provisional offset
            self._idx.append(last)
            self._host.append(host_ns)
        p = self.period_ns
        offset = min(h - i * p for i, h in zip(self._idx, self._host))
        t = offset + p * np.arange(first_index, last + 1, dtype=np.float64)
        t = np.rint(t).astype(np.int64)
        # a new estimate may move the offset back a little: never hand out a time twice
        if self._last_t is not None and t[0] <= self._last_t:
            t += self._last_t + int(p / 2) - t[0]
        self._last_t = int(t[-1])
        return t

    @property
    def anchored(self) -> bool:
        """True once a read has tied the part's sample indices to the host clock."""
        return bool(self._idx)

    def forget_offset(self) -> None:
        """Drops the index ↔ host-time anchors, keeps the tracked period: after a FIFO
        reset the next reads anchor the offset afresh, so an index estimated across the
        reset one sample off shifts the count, never the times."""
        self._idx.clear()
        self._host.clear()

    def index_at(self, host_ns: int) -> int:
        """The index of the newest sample the part has produced by ``host_ns``."""
        if not self._idx:
            return -1
        p = self.period_ns
        offset = min(h - i * p for i, h in zip(self._idx, self._host))
        return int(math.floor((host_ns - offset) / p))


class FifoTimeline:
    """One FIFO part's samples on its own clock: indices, times and the losses between them.

    Every sample the part produces has an index (0, 1, … from the FIFO's start); a burst of
    ``n`` samples read from the FIFO is the next ``n`` indices, stamped by the part's
    :class:`SensorClock`. Samples the part produced but the host never read (an overflowed
    FIFO that was reset, a part unreachable on the bus) advance the index without rows and
    are counted by cause: in ``diagnostics.lost`` when found, and in the ``lost`` of the next
    block (:meth:`take_loss`), so the gap shows as one long dt before that block's first row.

    The loss of an overflow is ``produced − read``: the index the sensor clock gives the
    host time of the FIFO reset, minus the samples read — it does not depend on when the
    overflow flag was noticed or how long since the last read (a flag seen one read late, or
    a stop between the status and the data reads, cost no accuracy).
    """

    def __init__(self, rate_hz: float, diagnostics: SourceDiagnostics,
                 events_key: str = "fifo_overflows", rows: bool = True) -> None:
        self.clock = SensorClock(rate_hz)
        self.diagnostics = diagnostics
        #: whether this part's samples are the rows: then its losses are lost rows
        #: (``diagnostics.lost``); a part held by the pairing rule only counts its events
        self.rows = rows
        self.events_key = events_key
        diagnostics.extra.setdefault(events_key, 0)
        self.next_index = 0
        #: whether a sample of this part has been read or counted lost (here or on the
        #: timeline this one continues, :meth:`carry_loss`): an overflow found before that
        #: holds stale samples nobody asked for yet, one found after it is a loss
        self.started = False
        self._pending = LossCounts()
        self._shortest_read = 1 << 62  # ns: the quickest level read so far

    def stamp(self, host_ns: int, n: int, full: bool = False, read_end_ns: int | None = None) -> np.ndarray:
        """Times (int64 ns, oldest first) of the next ``n`` samples, the newest of which was
        in the FIFO when its level was read in a transfer begun at ``host_ns`` (and ended at
        ``read_end_ns``). full: the FIFO had filled (its newest sample may be much older than
        the read): timed from the clock's fit.

        The anchor is the transfer's start: the part latches its level while the transfer
        runs, so the newest counted sample can be younger than the start by as much as the
        transfer took. A level read that took much longer than the shortest seen (the host
        was preempted inside it) is no anchor: a sample counted long after the start would
        look earlier than it was and pull the clock's lower envelope early."""
        anchor = not full
        if read_end_ns is not None:
            took = read_end_ns - host_ns
            self._shortest_read = min(self._shortest_read, took)
            if took > 2 * self._shortest_read + 200_000:
                anchor = False
        t = self.clock.stamp(host_ns, self.next_index, n, anchor=anchor)
        self.next_index += n
        self.started |= n > 0
        return t

    def overflowed(self, reset_host_ns: int, flagged: bool = True) -> int:
        """The FIFO was reset at ``reset_host_ns`` after an overflow: the samples produced
        since the last one read are lost (at least one when the part flagged the overflow).
        Returns the count; the offset is anchored afresh by the next reads."""
        self.diagnostics.extra[self.events_key] += 1
        produced = self.clock.index_at(reset_host_ns) + 1
        n = max(1 if flagged else 0, produced - self.next_index)
        self._lose(n, "fifo_overflow")
        self.clock.forget_offset()
        return n

    def overran(self, host_ns: int, n: int) -> int:
        """A stream FIFO found filled at ``host_ns`` holds the newest ``n`` samples, its
        oldest overwritten: the samples between the last one read and those are lost (the
        part flags only "filled": 0 when it had just filled). Call before stamping the ``n``;
        the offset is anchored afresh by them."""
        self.diagnostics.extra[self.events_key] += 1
        lost = max(0, self.clock.index_at(host_ns) + 1 - n - self.next_index)
        self._lose(lost, "fifo_overflow")
        self.clock.forget_offset()
        return lost

    def missed(self, host_ns: int) -> int:
        """The part was unreachable and has been configured again (its FIFO reset) at
        ``host_ns``: what it produced since the last sample read is lost to bus errors."""
        if not self.clock.anchored:
            return 0
        n = max(0, self.clock.index_at(host_ns) + 1 - self.next_index)
        self._lose(n, "bus_error")
        self.clock.forget_offset()
        return n

    def carry_loss(self, earlier: "FifoTimeline") -> None:
        """Takes over the losses ``earlier`` (the timeline before a re-configuration) has
        not handed out yet, so the first block of this one carries them."""
        self._pending.add(earlier.take_loss())
        self.started |= earlier.started

    def _lose(self, n: int, cause: str) -> None:
        self.next_index += n
        self.started = True
        if not self.rows:
            return
        setattr(self._pending, cause, getattr(self._pending, cause) + n)
        lost = self.diagnostics.lost
        setattr(lost, cause, getattr(lost, cause) + n)

    def take_loss(self) -> LossCounts:
        """The losses since the last call: the ``lost`` of the next block handed out."""
        lost, self._pending = self._pending, LossCounts()
        return lost

    @property
    def loss_pending(self) -> bool:
        return self._pending.total > 0


def burst_flags(gyr_counts: np.ndarray, acc_counts: np.ndarray, gyro_full_scale: int,
                acc_full_scale: int, diagnostics: SourceDiagnostics) -> np.ndarray:
    """(n,) int64 validity bits of a burst's rows: an axis at or beyond its full scale marks
    the reading saturated instead of valid (counted in ``diagnostics.saturated``)."""
    gsat = (np.abs(gyr_counts) >= gyro_full_scale).any(axis=1)
    asat = (np.abs(acc_counts) >= acc_full_scale).any(axis=1)
    diagnostics.saturated += int(gsat.sum() + asat.sum())
    return (np.where(gsat, GYR_SATURATED, GYR_VALID) | np.where(asat, ACC_SATURATED, ACC_VALID)).astype(np.int64)


def hold_pairing(row_t_ns: np.ndarray, other_t_ns: np.ndarray) -> np.ndarray:
    """**The pairing rule for parts on separate clocks** (GY-80: ADXL345 beside L3G4200D;
    MinIMU-9 v2: LSM303DLHC beside L3GD20; BMI088: its accelerometer die beside its gyroscope
    die): the gyroscope's samples are the rows, on the gyroscope's clock; each row takes the
    other part's newest sample whose own sensor-clock time is at or before the row's time
    (zero-order hold: never a value from the row's future, never an interpolation between
    two readings). Returns, per row, the index into ``other_t_ns`` (ascending), or −1 where
    the other part has no sample yet (such rows are not handed out)."""
    return np.searchsorted(other_t_ns, row_t_ns, side="right") - 1


class SimulatedFrameFifo:
    """The twins' FIFO of whole samples (frames of the data registers), with each sample's
    truth beside it (simulation only): the 32-level FIFOs of the ST parts and the ADXL345.

    ``push`` follows the part's mode: a full FIFO turns the new sample away (FIFO mode,
    ``keep_oldest``) or overwrites its oldest (stream mode). Counters for tests: ``overflowed``
    (samples overwritten or turned away), ``discarded`` (samples emptied unread by a reset).
    """

    def __init__(self, depth: int) -> None:
        self.depth = int(depth)
        self.frames: deque[bytes] = deque()
        self.truth: deque = deque()
        self.popped_truth: list = []  # the truth of the samples read since take_popped_truth()
        self.overflowed = 0
        self.discarded = 0

    def __len__(self) -> int:
        return len(self.frames)

    def push(self, frame: bytes, truth, keep_oldest: bool) -> None:
        if len(self.frames) >= self.depth:
            self.overflowed += 1
            if keep_oldest:
                return
            self.frames.popleft()
            self.truth.popleft()
        self.frames.append(frame)
        self.truth.append(truth)

    def head(self) -> bytes | None:
        """The oldest stored sample (what the data registers show), None when empty."""
        return self.frames[0] if self.frames else None

    def pop(self) -> None:
        """The oldest sample has been read out."""
        self.frames.popleft()
        self.popped_truth.append(self.truth.popleft())

    def reset(self) -> None:
        """Emptied unread (bypass mode)."""
        self.discarded += len(self.frames)
        self.frames.clear()
        self.truth.clear()

    def take_popped_truth(self) -> list:
        out, self.popped_truth = self.popped_truth, []
        return out


class SimulatedFifo:
    """A byte FIFO of ``capacity`` bytes holding whole samples of ``frame`` bytes.

    stop_on_full: a frame that does not fit is dropped (ICM-42688-P "stop-on-full",
    BMI088 "FIFO mode"); otherwise the oldest frames make room (stream mode).
    ``overflowed`` is set on the first lost frame; ``dropped`` counts them.
    """

    def __init__(self, capacity: int, stop_on_full: bool = True, frame: int = 1) -> None:
        self.capacity = int(capacity)
        self.frame = int(frame)  # bytes of one sample (packet)
        self.discarded = 0  # samples emptied unread by clear() (a flush), for tests
        self.stop_on_full = stop_on_full
        self.data = bytearray()
        self.overflowed = False
        self.dropped = 0

    @property
    def level(self) -> int:
        return len(self.data)

    def push(self, frame: bytes) -> bool:
        if len(self.data) + len(frame) > self.capacity:
            self.overflowed = True
            self.dropped += 1
            if self.stop_on_full:
                return False
            del self.data[:len(frame)]
        self.data += frame
        return True

    def pop(self, n: int) -> bytes:
        out = bytes(self.data[:n])
        del self.data[:n]
        return out

    def clear(self) -> None:
        """Emptied (a FIFO flush/reset): the whole samples in it are ``discarded`` unread."""
        self.discarded += len(self.data) // self.frame
        self.data.clear()
        self.overflowed = False


class SimulatedFifoDevice(SimulatedRegisterDevice):
    """Twin base of the SPI parts whose every due sample is latched (and pushed to its FIFO),
    in order, by the base's FIFO latching (``fifo_room`` from the FIFO's free bytes).

    clock_error: the part's oscillator error (+0.004 = 0.4 % fast; the name the I2C twins use): ``rate_hz()`` returns the
    nominal rate from the registers, the samples come at ``nominal · (1 + clock_error)``.
    Subclasses implement :meth:`nominal_rate_hz`, :meth:`latch` (data registers + FIFO) and
    :meth:`backlog_limit` (how many samples can matter at once: the FIFO's depth + 1).
    """

    CLOCK_ERROR = 0.0

    def __init__(self, source=None, address: int | None = None, clock_error: float | None = None) -> None:
        super().__init__(source, address)
        self.clock_error = self.CLOCK_ERROR if clock_error is None else float(clock_error)
        #: samples produced while the FIFO was full that were never computed (``samples_latched``
        #: counts the rest: produced = samples_latched + samples_unseen)
        self.samples_unseen = 0

    def nominal_rate_hz(self) -> float | None:
        return None

    def rate_hz(self) -> float | None:
        r = self.nominal_rate_hz()
        return None if not r else r * (1.0 + self.clock_error)

    def sampling_rate_hz(self) -> float | None:
        return self.rate_hz()  # rate_hz() is already the real rate here

    def backlog_limit(self) -> int:
        return 1

    # the base's FIFO latching (SimulatedRegisterDevice._update_fifo) through these hooks
    def fifo_room(self) -> int | None:
        if self.backlog_limit() <= 1:  # FIFO off: the newest sample only, as in polling
            return None
        fifo = self.fifo  # type: ignore[attr-defined]
        return max(0, (fifo.capacity - fifo.level) // fifo.frame)

    def fifo_keeps_oldest(self) -> bool:
        return self.fifo.stop_on_full  # type: ignore[attr-defined]

    def fifo_dropped(self, n: int) -> None:
        # samples that could only have overflowed the FIFO: counted, never computed
        self.samples_unseen += n
        self.skipped_unseen(n)

    def skipped_unseen(self, n: int) -> None:
        """``n`` samples produced while the FIFO was already full (hook: mark overflow)."""
