"""Fixed-rate loop timing against absolute deadlines on the monotonic clock.

Tick k is due at ``start + k·period``; deadlines never move, so lateness never accumulates
into drift. A tick that starts more than one period late is an *overrun*: the missed ticks
are counted and skipped, and the loop resumes on the next deadline in the future.
Lateness (wake-up time − the deadline of the first tick not served, so an overrun's whole
delay counts), period jitter, the loop's busy time and its thread's CPU time are kept in ring
buffers for percentiles and shares.
"""

from __future__ import annotations

import ctypes
import sys
import time
from dataclasses import dataclass

import numpy as np

_WINDOW = 8192  # ticks kept for percentiles (8 s at 1 kHz)
_PR_SET_TIMERSLACK = 29


def _tighten_timer_slack() -> None:
    """Linux rounds sleeps up by the thread's timer slack (50 µs by default); ask for 1 µs."""
    if sys.platform != "linux":
        return
    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)
    except (OSError, AttributeError):
        pass  # not fatal: only jitter gets worse


def _percentile_of_sorted(values: np.ndarray, q: float) -> float:
    """``np.percentile(values, q)`` (linear interpolation) of sorted ``values``, without its
    ~100 µs of per-call overhead."""
    pos = q / 100.0 * (len(values) - 1)
    lo = int(pos)
    hi = min(lo + 1, len(values) - 1)
    return float(values[lo] + (values[hi] - values[lo]) * (pos - lo))


@dataclass
class LoopStats:
    """Timing of the last second of ticks (see ``FixedRateScheduler.stats``); times in µs."""

    rate_hz: float
    ticks: int
    overruns: int
    missed_ticks: int
    period_jitter_p50_us: float
    period_jitter_p99_us: float
    period_jitter_max_us: float
    lateness_p99_us: float
    load_percent: float
    #: the longest a tick of the window woke after its deadline, µs (what a FIFO must hold)
    lateness_max_us: float = 0.0
    #: the loop thread's CPU time over the window's wall time, % of one core
    cpu_percent: float = 0.0

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


class FixedRateScheduler:
    """Paces a loop at ``rate_hz``.

    Call :meth:`wait` at the top of each iteration (it returns the tick's wake-up time in ns)
    and :meth:`done` at the end (for the load figure). ``spin_ns`` is how long before a
    deadline the loop stops sleeping and polls the clock: spinning costs CPU (at 1 kHz every
    10 µs of spin is 1 % of a core), sleeping costs the kernel's wake-up latency. The
    thread's timer slack is set to 1 µs (Linux) so that sleeps end close to when asked.
    """

    #: the default ``spin_ns``
    SPIN_NS = 20_000

    def __init__(self, rate_hz: float, *, spin_ns: int = SPIN_NS) -> None:
        self.spin_ns = spin_ns
        _tighten_timer_slack()
        self.set_rate(rate_hz)
        self.ticks = 0
        self.overruns = 0
        self.missed_ticks = 0
        self._lateness = np.zeros(_WINDOW)
        self._period = np.zeros(_WINDOW)
        self._busy = np.zeros(_WINDOW)
        self._cpu = np.zeros(_WINDOW)  # the loop thread's CPU clock at each tick's end, ns
        self._wake = 0  # the last wake-up, ns
        #: when the loop wakes next (monotonic ns), None before the first tick: other threads
        #: read it to leave the interpreter free then (the log writer, ``logs/writer.py``)
        self.next_wake_ns: int | None = None

    def set_rate(self, rate_hz: float) -> None:
        """Changes the rate; the new schedule starts at the next tick."""
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.rate_hz = float(rate_hz)
        self.period_ns = int(round(1e9 / rate_hz))
        self._start = None  # re-anchored on the next wait()
        self._k = 0

    def wait(self) -> int:
        """Sleeps until the next deadline; returns the wake-up time (ns, monotonic)."""
        now = time.monotonic_ns()
        if self._start is None:
            self._start = now
            self._k = 0
        deadline = first_due = self._start + self._k * self.period_ns
        if now - deadline > self.period_ns:
            # overrun: skip the ticks whose deadlines have passed, keep the grid
            missed = (now - deadline) // self.period_ns
            self.overruns += 1
            self.missed_ticks += int(missed)
            self._k += int(missed)
            deadline += int(missed) * self.period_ns
        remaining = deadline - now
        if remaining > self.spin_ns:
            time.sleep((remaining - self.spin_ns) * 1e-9)
        while True:
            now = time.monotonic_ns()
            if now >= deadline:
                break
        i = self.ticks % _WINDOW
        self._lateness[i] = now - first_due
        self._period[i] = (now - self._wake) if self.ticks else self.period_ns
        self._wake = now
        self.ticks += 1
        self._k += 1
        self.next_wake_ns = self._start + self._k * self.period_ns
        return now

    def done(self) -> None:
        """Marks the end of this tick's work (for the busy and CPU shares)."""
        i = (self.ticks - 1) % _WINDOW
        self._busy[i] = time.monotonic_ns() - self._wake
        self._cpu[i] = time.thread_time_ns()

    def stats(self) -> LoopStats:
        """Timing of the last second of ticks (at least 100 ticks, at most the ring's 8192).

        One second, because the service asks once a second: the figures then describe that
        second, and percentiles over 1 000 rather than 8 192 ticks cost a tenth as much — in a
        1 kHz loop this call must fit in one tick.
        """
        n = min(self.ticks, _WINDOW, max(100, int(round(self.rate_hz))))
        if n < 2:
            return LoopStats(self.rate_hz, self.ticks, self.overruns, self.missed_ticks, 0, 0, 0, 0, 0)
        last = np.arange(self.ticks - n, self.ticks) % _WINDOW
        jitter = np.sort(np.abs(self._period[last] - self.period_ns) / 1e3)
        p50, p99 = _percentile_of_sorted(jitter, 50), _percentile_of_sorted(jitter, 99)
        lateness = np.sort(self._lateness[last])
        # CPU between the window's first and last tick ends, over the wall time between them
        # (a tick not ended yet, the current one, has no CPU mark: left out)
        ended = last[:-1] if self._cpu[last[-1]] < self._cpu[last[-2]] else last
        wall = float(self._period[ended[1:]].sum())
        cpu = float(self._cpu[ended[-1]] - self._cpu[ended[0]])
        return LoopStats(
            rate_hz=self.rate_hz,
            ticks=self.ticks,
            overruns=self.overruns,
            missed_ticks=self.missed_ticks,
            period_jitter_p50_us=float(p50),
            period_jitter_p99_us=float(p99),
            period_jitter_max_us=float(jitter[-1]),
            lateness_p99_us=_percentile_of_sorted(lateness, 99) / 1e3,
            load_percent=float(100.0 * self._busy[last].mean() / self.period_ns),
            lateness_max_us=float(lateness[-1]) / 1e3,
            cpu_percent=100.0 * cpu / wall if wall > 0 and cpu >= 0 else 0.0,
        )


class DataReadyScheduler(FixedRateScheduler):
    """Paces the loop by a data-ready (FIFO watermark) line instead of a timer.

    :meth:`wait` blocks on ``line`` (a :class:`~ahrs_service.drivers.buses.drdy.DataReadyLine`)
    for at most ``timeout_periods`` periods of ``rate_hz`` (the watermark rate), then returns
    like a timer tick: an unwired or silent line degrades to polling at that timeout, never
    to a stall. ``rate_hz`` is the expected wake-up rate (for jitter and load figures);
    ``edges`` / ``timeouts`` are on the line.
    """

    def __init__(self, line, rate_hz: float, *, timeout_periods: float = 2.0) -> None:
        super().__init__(rate_hz)
        self.line = line
        self.timeout_periods = float(timeout_periods)
        # next_wake_ns stays None: the line's edge, not a timetable, wakes this loop

    def wait(self) -> int:
        self.line.wait(self.timeout_periods / self.rate_hz)
        now = time.monotonic_ns()
        i = self.ticks % _WINDOW
        self._lateness[i] = 0
        self._period[i] = (now - self._wake) if self.ticks else self.period_ns
        self._wake = now
        self.ticks += 1
        return now
