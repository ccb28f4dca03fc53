"""Sample times from known sample indices bounded by FIFO level reads (the FIFO boards).

A part with a FIFO counts its samples: a burst read from it is the next ``n`` indices, and
the samples the host lost (an overflowed FIFO, an outage) are counted by the driver. What is
left to recover is the line ``t_i = offset + i·period`` of the package's model
(:mod:`ahrs_service.core.sample_clock`), and each FIFO level read bounds it from both sides:
the newest sample counted existed when the level was latched, the next one did not yet.
:class:`SensorClock` keeps those bounds as convex hulls and places the line inside them.
Used through :class:`ahrs_service.drivers.fifo.FifoTimeline` by every FIFO board.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np


class _LowerHull:
    """The lower convex hull of integer points added in increasing x (Andrew's monotone
    chain, one point at a time): the only points that can be the minimum of ``y − x·p`` for
    any slope ``p``. Exact integer arithmetic, so hours of nanoseconds lose nothing."""

    __slots__ = ("x", "y", "_slope", "_lowest")

    def __init__(self) -> None:
        self.x: list[int] = []
        self.y: list[int] = []
        # lowest(slope)'s last answer, kept up to date as points come (the loop asks it at
        # every read with the same slope, between refits): one point's term, not the hull's
        self._slope: float | None = None
        self._lowest = math.inf

    def add(self, x: int, y: int) -> None:
        xs, ys = self.x, self.y
        if xs and x <= xs[-1]:
            if y >= ys[-1] or x < xs[-1]:
                return  # the same index again, no lower: nothing new
            xs.pop()
            ys.pop()
        while len(xs) >= 2 and (xs[-1] - xs[-2]) * (y - ys[-2]) - (ys[-1] - ys[-2]) * (x - xs[-2]) <= 0:
            xs.pop()
            ys.pop()
        xs.append(x)
        ys.append(y)
        if self._slope is not None:
            self._lowest = min(self._lowest, y - x * self._slope)

    def lowest(self, slope: float) -> float:
        """min(y − x·slope) over the points (math.inf with none): the lowest line of that slope
        through them. Over the hull's vertices, which is over every point added (a point the
        hull dropped lies above it at every slope), so a new point updates it alone."""
        if slope != self._slope:
            self._slope = slope
            self._lowest = min((y - x * slope for x, y in zip(self.x, self.y)), default=math.inf)
        return self._lowest


class _Segment:
    """Reads between two FIFO resets: within one, sample indices are counted, not estimated.

    Each read gives two bounds on the line ``t_i = offset + i·period`` (times and indices
    relative to the segment's first read, integers): the newest sample ``i`` in the FIFO
    when its level was latched was produced by the end of that transfer (``t_i ≤ done``,
    kept in ``before``: a lower hull of ``(i, done)``), and the next one was not yet produced
    at its start (``t_{i+1} > start``, kept in ``after``: the upper hull of ``(i + 1, start)``,
    stored negated as a lower hull). A FIFO that had filled gives only the first bound."""

    def __init__(self, index: int, host_ns: int, continues: "_Segment | None" = None,
                 first_of_run: bool = False) -> None:
        self.i0 = index
        self.h0 = host_ns
        #: the segment this one took over from without a reset (indices run on), while the
        #: new one has few reads of its own
        self.continues = continues
        #: the run's first segment: its first transfers carry one-time costs (see
        #: SensorClock._offset_rel)
        self.first_of_run = first_of_run
        self.before = _LowerHull()
        self.after = _LowerHull()  # of (i + 1, −start)
        self.reads = 0
        self.last_ns = host_ns

    def add(self, index: int, start_ns: int, done_ns: int, two_sided: bool) -> None:
        x = index - self.i0
        self.before.add(x, done_ns - self.h0)
        if two_sided:
            self.after.add(x + 1, self.h0 - start_ns)
        self.reads += 1
        self.last_ns = max(self.last_ns, done_ns)

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(x, y) of both hulls as float arrays, y relative to the segment's origin."""
        return (np.array(self.before.x, float), np.array(self.before.y, float),
                np.array(self.after.x, float), -np.array(self.after.y, float))


class SensorClock:
    """Sample times from sample indices on the part's clock, mapped onto the host clock.

    A part's samples are evenly spaced on its own oscillator: sample ``i`` is at
    ``offset + i · period``, where the real period is off the nominal one by the
    oscillator's error. Every FIFO level read bounds that line from both sides (the newest
    sample counted existed when the level was latched, the one after it did not yet; see
    :class:`_Segment`), however late the host was: a read delayed by a stall only gives a
    looser bound, never a wrong one. The period is the middle of the range of periods that
    satisfy every bound of the reads of the last ``horizon_s`` (at the period that satisfies
    them best when none does: a part whose rate drifts); ``offset`` is the latest the
    current segment's reads allow at that period (:meth:`_offset_rel`). This is the
    two-sided version of the convex-hull skew estimate of network clock synchronisation
    (Moon, Skelly and Towsley, "Estimation and removal of clock skew from network delay
    measurements", 1999; the method only, no code).

    A FIFO reset starts a new segment (:meth:`forget_offset`): the indices across it are an
    estimate (the samples lost are counted with this clock), so segments share the period
    but each has its own offset — a loss miscounted by one never tilts the period. A segment
    also ends after ``segment_s`` (10 s) without one, so the line follows a rate that drifts
    with temperature.
    """

    #: periods searched: the nominal one ±10 % (a part further off is broken)
    SEARCH = 0.10
    #: where a part's period is before its reads say more: the nominal one ±2 % (datasheets
    #: give ±0.5–2 % for these oscillators); a uniform prior, so the estimate is the middle
    #: of the periods both it and the reads allow, or of those the reads allow when a part
    #: turns out further off
    PRIOR = 0.02
    #: bisection steps of the period search (the range shrinks by 0.618 each)
    STEPS = 48

    def __init__(self, nominal_rate_hz: float, horizon_s: float = 20.0, refit_s: float = 1.0,
                 max_segments: int = 64, segment_s: float = 10.0, overlap_s: float = 5.0) -> None:
        self.nominal_period_ns = 1e9 / nominal_rate_hz
        self.period_ns = self.nominal_period_ns
        self._horizon_ns = horizon_s * 1e9
        # a part's rate drifts with its temperature: a segment ends after segment_s even
        # without a reset, so no straight line is fitted to more than that; the next one
        # carries the last one's offset bound for its first overlap_s
        self._segment_ns = segment_s * 1e9
        self._overlap_ns = overlap_s * 1e9
        self._refit_ns = refit_s * 1e9
        self._max_segments = max_segments
        self._segments: deque[_Segment] = deque()
        self._current: _Segment | None = None
        self._last_refit_ns: int | None = None
        self._reads = 0  # reads so far, all segments
        self._last_t: int | None = None
        # the continued segment's latest-offset bound, as last computed for (the current
        # segment, its first index, the period): its reads are over, it changes with those only
        self._continued: tuple[_Segment, int, float, float] | None = None

    @property
    def rate_hz(self) -> float:
        """The part's tracked real output rate, Hz."""
        return 1e9 / self.period_ns

    @property
    def anchored(self) -> bool:
        """True once a read has tied the part's sample indices to the host clock."""
        return self._current is not None and self._current.reads > 0

    @property
    def placing_first_reads(self) -> bool:
        """True while the run's first segment has no read that bounds its offset to within a
        period: its times would rest on reads whose transfers a busy host held up (a first
        read preempted around its latch places the whole line that much off, and the next
        tight read moves it by as much as the hold)."""
        seg = self._current
        if seg is None:
            return self._reads == 0
        return seg.first_of_run and (seg.reads == 0 or self.offset_range_ns() > self.period_ns)

    def stamp(self, host_ns: int, first_index: int, n: int, anchor: bool = True,
              read_end_ns: int | None = None, newest_index: int | None = None) -> np.ndarray:
        """Times (int64 ns, oldest first) of samples ``first_index … first_index + n − 1``,
        read from a FIFO whose level was latched by a transfer from ``host_ns`` to
        ``read_end_ns`` (``host_ns`` when not given).

        newest_index: the newest sample in the FIFO at that latch (default the newest one
        read; more when the read took fewer than the level). anchor: False when the FIFO was
        full (samples after its newest were turned away): only the "it existed" bound holds.
        """
        newest = first_index + n - 1 if newest_index is None else int(newest_index)
        self.observe(host_ns, newest, anchor=anchor, read_end_ns=read_end_ns)
        return self.times(first_index, n)

    def observe(self, host_ns: int, newest_index: int, anchor: bool = True,
                read_end_ns: int | None = None) -> None:
        """A FIFO level read that stamps nothing (:meth:`stamp` without the times): sample
        ``newest_index`` was the newest in the FIFO at a latch between ``host_ns`` and
        ``read_end_ns``. A driver whose data transfer reads the level again (the ICM-42688-P
        reads status and count with its packets) gives the clock that second bound too, so
        one read that a host preempted around its latch cannot place a young segment alone."""
        done = host_ns if read_end_ns is None else max(int(read_end_ns), host_ns)
        self._add(int(newest_index), host_ns, done, two_sided=anchor)

    def times(self, first_index: int, n: int) -> np.ndarray:
        """Times (int64 ns, oldest first) of samples ``first_index … first_index + n − 1`` on
        the line the reads so far give (at least one :meth:`observe` in this segment)."""
        p = self.period_ns
        seg = self._current
        t = (seg.h0 + self._offset_rel()) + p * np.arange(first_index - seg.i0, first_index - seg.i0 + n,
                                                          dtype=np.float64)
        t = np.rint(t).astype(np.int64)
        # a new estimate may move the offset back a little: never hand out a time twice
        if n and self._last_t is not None and t[0] <= self._last_t:
            t += self._last_t + int(p / 2) - t[0]
        if n:
            self._last_t = int(t[-1])
        return t

    def forget_offset(self) -> None:
        """After a FIFO reset: the next reads start a new segment (a fresh offset), the
        period keeps what every segment so far says."""
        self._current = None

    def anchor_reset(self, first_index: int, start_ns: int, done_ns: int) -> None:
        """A FIFO reset (flush) sent by a transfer from ``start_ns`` to ``done_ns``: a new
        segment, bounded as a level read of the emptied FIFO is — the part's first sample
        after the reset, ``first_index``, came after the reset began, and the one before it
        had been produced by the reset's end. Without this bound, a segment whose first read
        finds the FIFO full again (a host still stalled) has only the "it existed by the
        read" bound, the latest offset it allows puts that full FIFO's newest sample at the
        read, and the next reset counted from that line misses every sample the part turned
        away in between."""
        self.forget_offset()
        self._add(first_index - 1, int(start_ns), max(int(done_ns), int(start_ns)), two_sided=True)

    def index_at(self, host_ns: int) -> int:
        """The index of the newest sample the part has produced by ``host_ns``."""
        if not self.anchored:
            return -1
        seg = self._current
        p = self.period_ns
        return int(math.floor((host_ns - seg.h0 - self._offset_rel()) / p)) + seg.i0

    @property
    def last_time_ns(self) -> int | None:
        """The time handed out last (the newest sample stamped), None before any."""
        return self._last_t

    def offset_range_ns(self) -> float:
        """How wide the range of offsets the current segment's reads allow is, ns (a period
        and the read's transfer after one read; it narrows as reads fall at other phases)."""
        earliest = self._earliest_offset_rel()
        return 0.0 if earliest is None else max(0.0, self._offset_rel() - earliest)

    def shift_indices(self, n: int) -> None:
        """The current segment's indices are ``n`` further on than it was told (a loss
        counted after its first read): its times stay, its indices move."""
        self._current.i0 += n

    # the fit ---------------------------------------------------------------------------------

    def _add(self, index: int, start_ns: int, done_ns: int, two_sided: bool) -> None:
        seg = self._current
        if seg is None or done_ns - seg.h0 > self._segment_ns:
            seg = self._current = _Segment(index, start_ns, continues=seg, first_of_run=self._reads == 0)
            self._segments.append(seg)
            self._drop_old(done_ns)
        seg.add(index, start_ns, done_ns, two_sided)
        if seg.continues is not None and done_ns - seg.h0 > self._overlap_ns:
            seg.continues = None
        # the period while it is young at every doubling of the reads, then every refit_s
        # (a new segment needs none: the period is shared, and at 8 kHz with overflows
        # segments come many a second)
        self._reads += 1
        reads = self._reads
        if (reads <= 4096 and (reads & (reads - 1)) == 0) or self._last_refit_ns is None \
                or done_ns - self._last_refit_ns >= self._refit_ns:
            self._refit(done_ns)

    def _drop_old(self, now_ns: int) -> None:
        while len(self._segments) > 1 and (len(self._segments) > self._max_segments
                                           or now_ns - self._segments[0].last_ns > self._horizon_ns):
            self._segments.popleft()

    def _offset_rel(self) -> float:
        """The offset of the current segment, relative to its origin (ns).

        The latest its reads allow: each sample at the latest time it can have been taken,
        never before it was (with the period right). Not the middle of the allowed range: a
        host that reads on the part's data-ready line or watermark reads just after a sample
        every time, and the earliest allowed end is then a whole period early. But no later
        than a period after the earliest: while a young segment's only reads had long
        transfers (a first transfer that took 3 ms, a read preempted halfway), the latest
        bound is that much too late, and the next, tighter read would pull the times back
        by more than the period between two samples already handed out. Only in the run's
        first segment, whose first transfers carry one-time costs (first calls, page faults)
        before or after the latch, where no bound tells which: after a FIFO reset the first
        new sample's time counts the samples lost (``FifoTimeline``), and placing it at the
        start of a long transfer when the part latched late in it miscounts them. A range no
        wider than a period (every segment after a few reads) leaves the latest bound."""
        latest = self._latest_offset_rel()
        if not self._current.first_of_run:
            return latest
        earliest = self._earliest_offset_rel()
        return latest if earliest is None else min(latest, earliest + self.period_ns)

    def _earliest_offset_rel(self) -> float | None:
        """The earliest offset the current segment's reads allow (each newest sample's
        successor not yet produced when its read began), None before a two-sided read."""
        after = self._current.after  # of (i + 1, −start): the highest line is −(its lowest at −p)
        return -after.lowest(-self.period_ns) if after.x else None

    def _latest_offset_rel(self) -> float:
        """The latest offset the current segment's reads allow (and those of the segment it
        continues: each newest sample produced by the end of its read)."""
        p, seg = self.period_ns, self._current
        best = seg.before.lowest(p)
        old = seg.continues
        if old is not None:  # its bounds in this segment's coordinates (its reads are over)
            if self._continued is None or self._continued[:3] != (seg, seg.i0, p):
                dx, dy = old.i0 - seg.i0, old.h0 - seg.h0
                self._continued = (seg, seg.i0, p,
                                   min(y + dy - (x + dx) * p for x, y in zip(old.before.x, old.before.y)))
            best = min(best, self._continued[3])
        return best

    def _refit(self, now_ns: int) -> None:
        self._last_refit_ns = now_ns
        bx, by, ax, ay = [], [], [], []
        for seg in self._segments:
            sbx, sby, sax, say = seg.arrays()
            if len(sax) == 0:
                continue  # no two-sided bound: says nothing about the period
            bx.append(sbx), by.append(sby), ax.append(sax), ay.append(say)
        if bx:
            # where each segment's points start in the joined arrays (for reduceat)
            b_first = np.cumsum([0] + [len(v) for v in bx[:-1]])
            a_first = np.cumsum([0] + [len(v) for v in ax[:-1]])
            bx, by, ax, ay = (np.concatenate(v) for v in (bx, by, ax, ay))

            def room(p: float) -> float:
                """The least room any segment leaves its offset at period p (ns)."""
                latest = np.minimum.reduceat(by - bx * p, b_first)
                earliest = np.maximum.reduceat(ay - ax * p, a_first)
                return float(np.min(latest - earliest))

            self.period_ns = self._middle_of_feasible(room)

    def _middle_of_feasible(self, room) -> float:
        """The middle of the periods at which ``room`` (concave) is ≥ 0 (within the prior
        when it overlaps), else the period of its maximum (the bounds disagree)."""
        lo = self.nominal_period_ns * (1.0 - self.SEARCH)
        hi = self.nominal_period_ns * (1.0 + self.SEARCH)
        g = 0.5 * (math.sqrt(5.0) - 1.0)
        a, b = lo, hi
        c, d = b - g * (b - a), a + g * (b - a)
        fc, fd = room(c), room(d)
        for _ in range(self.STEPS):
            if fc < fd:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = room(d)
            else:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = room(c)
        best = 0.5 * (a + b)
        if room(best) < 0.0:
            return best

        def edge(inside: float, outside: float) -> float:
            if room(outside) >= 0.0:
                return outside
            for _ in range(self.STEPS):
                mid = 0.5 * (inside + outside)
                if room(mid) >= 0.0:
                    inside = mid
                else:
                    outside = mid
            return 0.5 * (inside + outside)

        low, high = edge(best, lo), edge(best, hi)
        prior_low = max(low, self.nominal_period_ns * (1.0 - self.PRIOR))
        prior_high = min(high, self.nominal_period_ns * (1.0 + self.PRIOR))
        if prior_low > prior_high:
            prior_low, prior_high = low, high
        return 0.5 * (prior_low + prior_high)


__all__ = ["SensorClock"]
