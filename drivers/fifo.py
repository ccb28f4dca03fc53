"""FIFO acquisition shared by every FIFO board: decoded bursts, the sensor clock, wire times.

* :class:`FifoTimeline` — one FIFO part's sample indices, times and losses: every FIFO
  board stamps its bursts and counts its overflows and outages through it (one place).
* The twins' FIFOs (a byte FIFO of the part's depth, filled on a clock that runs
  ``clock_error`` off nominal) are in :mod:`ahrs_service.drivers.sim.fifo`.

Each sample's time comes from its index on the part's own output clock, with the part's real
rate tracked against the host's monotonic clock (:class:`ahrs_service.core.sample_clock.SensorClock`,
the sample-clock package's bounded fit): timestamps neither jitter with the host's read times
nor drift from the host clock. Bursts are handed out as :class:`~ahrs_service.core.samples.SampleBlock`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ahrs_service import _moved
from ahrs_service.core.sample_clock import SensorClock, whole_periods
from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    LossCounts,
    SourceDiagnostics,
)


@dataclass(frozen=True)
class _PendingGap:
    """An overflow reset whose loss waits for the first sample after it to be timed."""

    last_ns: int  # the time of the last sample read before the reset
    at_least: int  # 1 when the part flagged the overflow
    counted: int  # what was counted from the reset's host time


@dataclass(frozen=True)
class LevelRead:
    """A transfer that latched the FIFO's level again after the burst's level read (the
    ICM-42688-P's data transfer starts with status and count): from ``start_ns`` to
    ``end_ns`` on the host's monotonic clock the FIFO held ``level`` samples; ``full``: it
    had filled by then (samples after its newest were turned away)."""

    start_ns: int
    end_ns: int
    level: int
    full: bool = False


class FifoTimeline:
    """One FIFO part's samples on its own clock: indices, times and the losses between them.

    Every sample the part produces has an index (0, 1, … from the FIFO's start); a burst of
    ``n`` samples read from the FIFO is the next ``n`` indices, stamped by the part's
    :class:`SensorClock`. Samples the part produced but the host never read (an overflowed
    FIFO that was reset, a part unreachable on the bus) advance the index without rows and
    are counted by cause: in ``diagnostics.lost`` when found, and in the ``lost`` of the next
    block (:meth:`take_loss`), so the gap shows as one long dt before that block's first row.

    The loss of an overflow is counted from the sensor clock on both sides of the FIFO
    reset: counted when found from the reset's host time, then corrected from the periods
    between the last sample read before it and the first one after, less one — which does
    not depend on when the overflow flag was noticed, how long since the last read, or when
    the host sent the reset (a host preempted around any of them costs no accuracy). Drivers
    take a block's loss (:meth:`take_loss`) after stamping it, so the block after the gap
    carries the corrected count.
    """

    def __init__(self, rate_hz: float, diagnostics: SourceDiagnostics,
                 events_key: str = "fifo_overflows", rows: bool = True,
                 latch_after_ns: int = 0, latch_before_end_ns: int = 0) -> None:
        self.clock = SensorClock(rate_hz)
        #: the least time from a level read's start to the part latching its level (the
        #: read's command phase on the wire) and from the latch to the read's end (its data
        #: phase): :func:`wire_time_ns`
        self.latch_after_ns = int(latch_after_ns)
        self.latch_before_end_ns = int(latch_before_end_ns)
        self.diagnostics = diagnostics
        #: whether this part's samples are the rows: then its losses are lost rows
        #: (``diagnostics.lost``); a part held by the pairing rule only counts its events
        self.rows = rows
        self.events_key = events_key
        diagnostics.extra.setdefault(events_key, 0)
        self._gap: _PendingGap | None = None  # an overflow reset whose loss is not counted yet
        #: where the part's tracked output rate (Hz) is reported: ``sensor_rate_hz`` for the
        #: row part, ``acc_sensor_rate_hz`` beside ``acc_fifo_overflows``
        self.rate_key = events_key.replace("fifo_overflows", "sensor_rate_hz")
        self.next_index = 0
        #: whether a sample of this part has been read or counted lost (here or on the
        #: timeline this one continues, :meth:`carry_loss`): an overflow found before that
        #: holds stale samples nobody asked for yet, one found after it is a loss
        self.started = False
        self._pending = LossCounts()

    def stamp(self, host_ns: int, n: int, full: bool = False, read_end_ns: int | None = None,
              level: int | None = None, then: LevelRead | None = None) -> np.ndarray:
        """Times (int64 ns, oldest first) of the next ``n`` samples, read from a FIFO whose
        level was latched by a transfer from ``host_ns`` to ``read_end_ns``: the part
        latches its level while the transfer runs, so the newest sample counted existed by
        its end and the next one did not yet at its start (:class:`SensorClock`'s bounds).

        level: the samples the FIFO held at that latch (default ``n``; more when the read
        took fewer). full: the FIFO had filled (what came after its newest was turned away):
        only the "it existed" bound holds. then: a later transfer of the same burst that
        latched the level again (its bound is added before the times are computed: a level
        read held up around its latch, a busy host's first read, leaves the line to it)."""
        end = host_ns if read_end_ns is None else read_end_ns
        self._observe(host_ns, end, n if level is None else int(level), full, self.latch_before_end_ns)
        if then is not None:
            # its data phase (the packets after the count) is not counted: a looser, valid bound
            self._observe(then.start_ns, then.end_ns, then.level, then.full, 0)
        t = self.clock.times(self.next_index, n)
        if self._gap is not None and n:
            self._correct_gap(int(t[0]))
        self.next_index += n
        self.started |= n > 0
        self.diagnostics.extra[self.rate_key] = round(self.clock.rate_hz, 3)
        return t

    def wants_second_look(self, start_ns: int, end_ns: int) -> bool:
        """Whether a level read that took from ``start_ns`` to ``end_ns`` should be followed
        by another before the burst is stamped (passed as ``then``): it took longer than a
        period while the run's first reads are still placing the clock (a host held up
        around the latch of the first read otherwise puts the first rows that many periods
        off, and the next tight read jumps them back). Never in steady state."""
        return end_ns - start_ns > self.clock.period_ns and self.clock.placing_first_reads

    def _observe(self, start_ns: int, end_ns: int, level: int, full: bool, latch_before_end_ns: int) -> None:
        """One level read's bounds on the sensor clock: the latch lies between the read's
        command phase and its data phase (a transfer timed shorter than its wire time, as on
        a simulated bus, bounds nothing more)."""
        latch_earliest = min(start_ns + self.latch_after_ns, end_ns)
        latch_latest = max(end_ns - latch_before_end_ns, latch_earliest)
        self.clock.observe(latch_earliest, self.next_index + level - 1, anchor=not full,
                           read_end_ns=latch_latest)

    def overflowed(self, reset_started_ns: int, reset_host_ns: int, flagged: bool = True) -> int:
        """The FIFO was reset at ``reset_host_ns`` after an overflow: the samples produced
        between the last one read and the first one after the reset are lost (at least one
        when the part flagged the overflow). Counted now from the reset's host time, and
        corrected at the next read from the first new sample's time against the last old
        one's (:meth:`_correct_gap`): a host preempted around the reset command moves the
        first count by the preemption, never the second. Returns the first count.

        reset_started_ns: when the reset's transfer began (``reset_host_ns`` its end): the
        reset bounds the first new sample's time (:meth:`SensorClock.anchor_reset`), so that
        sample's time counts the loss even when its read finds the FIFO full again."""
        self.diagnostics.extra[self.events_key] += 1
        at_least = 1 if flagged else 0
        n = max(at_least, self.clock.index_at(reset_host_ns) + 1 - self.next_index)
        last = self.clock.last_time_ns
        if last is not None and self.clock.anchored:
            # the middle of what the reads allow, as the first sample after the gap is taken
            # (the times handed out are the latest allowed: a young segment's, a reset and
            # one full read, are up to a period late, which counted half a sample short a gap)
            last_mid = int(round(last - 0.5 * self.clock.offset_range_ns()))
            self._gap = _PendingGap(last_mid, at_least, n)
        self._lose(n, "fifo_overflow")
        self.clock.anchor_reset(self.next_index, reset_started_ns, reset_host_ns)
        return n

    def _correct_gap(self, first_new_ns: int) -> None:
        """The pending overflow gap, once the first sample after the reset has a time: the
        periods between it (placed in the middle of what the reset and its read allow) and
        the last sample before, less one. A correction is never more than the loss not yet
        handed out."""
        gap, self._gap = self._gap, None
        p = self.clock.period_ns
        first = first_new_ns - 0.5 * self.clock.offset_range_ns()
        # the middle of a range one period wide is off by [−½, ½) of a period: floor(x + ½)
        n = max(gap.at_least, whole_periods(first - gap.last_ns, p) - 1)
        delta = max(n - gap.counted, -self._pending.fifo_overflow) if self.rows else n - gap.counted
        if delta:
            self.clock.shift_indices(delta)
            self._lose(delta, "fifo_overflow")

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
        self._gap = None
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


#: bus clocks a register read spends before the part can latch the register's value (I2C:
#: START, the address, the register, a repeated START and the address again, 3 bytes of 9
#: clocks; SPI: the command byte), and per data byte clocked out after it
COMMAND_CLOCKS = {"i2c": 27, "spi": 8}
DATA_BYTE_CLOCKS = {"i2c": 9, "spi": 8}


def wire_time_ns(kind: str, clock_hz: float, data_bytes: int | None = None) -> int:
    """The wire time of a register read on a ``kind`` ("i2c"/"spi") bus clocked at
    ``clock_hz`` (0 when either is unknown): its command phase, or with ``data_bytes`` its
    data phase. Bounds of when a part latches a level read inside the read's host times:
    host delays only widen them, a bus slower than ``clock_hz`` too."""
    if not clock_hz or kind not in COMMAND_CLOCKS:
        return 0
    clocks = COMMAND_CLOCKS[kind] if data_bytes is None else DATA_BYTE_CLOCKS[kind] * data_bytes
    return int(clocks * 1e9 / clock_hz)


def latch_bounds(kind: str, clock_hz: float, level_bytes: int = 0) -> dict[str, int]:
    """:class:`FifoTimeline`'s ``latch_after_ns`` / ``latch_before_end_ns`` for a level read
    of ``level_bytes`` data bytes on a ``kind`` bus at ``clock_hz``: the part latches after
    the read's command phase and before its data bytes."""
    return {"latch_after_ns": wire_time_ns(kind, clock_hz),
            "latch_before_end_ns": wire_time_ns(kind, clock_hz, level_bytes) if level_bytes else 0}


def burst_flags(gyr_counts: np.ndarray, acc_counts: np.ndarray, gyro_full_scale: int,
                acc_full_scale: int, diagnostics: SourceDiagnostics) -> np.ndarray:
    """(n,) int64 validity bits of a burst's rows: an axis at or beyond its full scale marks
    the reading saturated instead of valid (counted in ``diagnostics.saturated``)."""
    # the usual burst, every reading inside its full scale: nothing to count, every row valid
    # (told by the largest magnitude of each: four NumPy calls, not a mask per row)
    if int(np.abs(gyr_counts).max(initial=0)) < gyro_full_scale and \
            int(np.abs(acc_counts).max(initial=0)) < acc_full_scale:
        return np.full(len(gyr_counts), GYR_VALID | ACC_VALID, np.int64)
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


def __getattr__(name: str):  # names that moved out of this module keep working for one release
    return _moved.moved_name(__name__, name)
