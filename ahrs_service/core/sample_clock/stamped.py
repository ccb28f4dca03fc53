"""Sample times from host stamps that jitter, come in bursts and skip (no FIFO level to bound them).

A sensor samples on its own oscillator: sample k is taken at ``t0 + k·T`` (T drifts slowly
with temperature). The host only sees when a sample (or a FIFO block of them) *arrived*:
``stamp_k = t0 + k·T + latency_k``, where the latency jitters (bus, scheduler, USB frames),
comes in bursts (several samples read at once get one stamp), and now and then samples are
lost (an overrun FIFO, a dropped frame) so ``k`` skips whole periods.

Model and method (see ``docs/timing.md``):

* a least-squares line ``time = a + b·k`` over a sliding window of the last ``window_s``
  seconds of samples; ``b`` is the tracked period (``rate_hz = 1/b``), so slow drift is
  followed with a lag of about half a window;
* each stamp enters the fit clipped to ``clip`` times the running mean absolute residual
  (never below one period) around the prediction, so a late outlier moves the line little
  (a Huber-like robust fit that stays O(1) per sample with running sums);
* a sample's recovered time is the fitted line at its index, evaluated with the stamps up to
  and including its own: the recovery is causal;
* without a sample counter, a lost sample shows as residuals that stay a whole period (or
  more) late; after ``gap_confirm_s`` of such residuals the index is moved on by the rounded
  number of periods (counted in ``lost_samples``); with a counter (``stamp_indexed``) gaps are
  exact at once;
* a stamp that lies on the fitted line to within ``snap`` periods is returned unchanged, so
  exactly uniform stamps pass bit for bit.

Times enter in nanoseconds of the monotonic clock (``SampleClock``; ``unit="s"`` for float
seconds) or as a batch in seconds (``recover_times``, identical to feeding a
``SampleClock(unit="s")`` one stamp at a time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ahrs_service.core.sample_clock.model import whole_periods


@dataclass(frozen=True)
class ClockTuning:
    """Tuning of the recovery. Defaults suit 100 Hz – 8 kHz sensors read by a busy host.

    window_s: length of the sliding fit window, s of samples (longer: smoother, slower drift
        tracking). clip: residuals beyond clip × mean |residual| enter the fit clipped (never
        below one period). gap_confirm_s: how long stamps must stay a whole period off the
        line before the index is moved (longer than the host's longest stall). snap: a stamp
        within snap periods of the fit is returned as it is.
    """

    window_s: float = 2.0
    clip: float = 4.0
    gap_confirm_s: float = 0.25
    snap: float = 1e-6

    def __post_init__(self) -> None:
        for name in ("window_s", "clip", "gap_confirm_s", "snap"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"sample clock: {name} must be a positive number, got {value!r}")


class _LineFit:
    """Running least squares of y on x over the last ``size`` points (ring buffer).

    Sums are kept relative to a base point and rebuilt from the buffer every ``size`` points
    so rounding does not accumulate over hours of samples.
    """

    def __init__(self, size: int) -> None:
        self.size = size
        self.xs = [0.0] * size
        self.ys = [0.0] * size
        self.head = 0
        self.n = 0
        self.since_rebuild = 0
        self.x0 = 0.0
        self.y0 = 0.0
        self.sx = self.sy = self.sxx = self.sxy = 0.0

    def add(self, x: float, y: float) -> None:
        if self.n == self.size:
            ox = self.xs[self.head] - self.x0
            oy = self.ys[self.head] - self.y0
            self.sx -= ox
            self.sy -= oy
            self.sxx -= ox * ox
            self.sxy -= ox * oy
        else:
            self.n += 1
        self.xs[self.head] = x
        self.ys[self.head] = y
        self.head = (self.head + 1) % self.size
        dx = x - self.x0
        dy = y - self.y0
        self.sx += dx
        self.sy += dy
        self.sxx += dx * dx
        self.sxy += dx * dy
        self.since_rebuild += 1
        if self.since_rebuild >= self.size:
            self.rebuild()

    def shift_newest(self, count: int, dx: float) -> None:
        """Moves the x of the newest ``count`` points by dx (a confirmed gap) and rebuilds."""
        for j in range(1, min(count, self.n) + 1):
            i = (self.head - j) % self.size
            self.xs[i] += dx
        self.rebuild()

    def rebuild(self) -> None:
        self.since_rebuild = 0
        if self.n == 0:
            return
        idx = [(self.head - j) % self.size for j in range(self.n, 0, -1)]
        self.x0 = self.xs[idx[-1]]
        self.y0 = self.ys[idx[-1]]
        self.sx = self.sy = self.sxx = self.sxy = 0.0
        for i in idx:
            dx = self.xs[i] - self.x0
            dy = self.ys[i] - self.y0
            self.sx += dx
            self.sy += dy
            self.sxx += dx * dx
            self.sxy += dx * dy

    def slope(self, prior: float = 0.0, weight: float = 0.0) -> float | None:
        """Fitted dy/dx, pulled toward ``prior`` with ``weight`` (in units of Σ(x − x̄)²);
        None with fewer than two distinct x."""
        if self.n < 2:
            return None
        cxx = self.sxx - self.sx * self.sx / self.n
        if cxx <= 0.0:
            return None
        return (self.sxy - self.sx * self.sy / self.n + weight * prior) / (cxx + weight)

    def at(self, x: float, slope: float) -> float:
        """The fitted line (with the given slope) at x."""
        return self.y0 + self.sy / self.n + slope * (x - self.x0 - self.sx / self.n)


class _Recovery:
    """The recovery in float time units (ns or s) relative to the first stamp."""

    def __init__(self, period: float, units_per_s: float, tuning: ClockTuning) -> None:
        self.tuning = tuning
        period_s = period / units_per_s
        self.fit = _LineFit(max(8, int(round(tuning.window_s / period_s))))
        self.confirm = max(4, int(round(tuning.gap_confirm_s / period_s)))
        self.period_nominal = period
        # the nominal period weighs on the slope like this many evenly spread samples while
        # the window fills, fading to nothing at PRIOR_SAMPLES points
        self.pull = min(1.0, 8.0 / self.fit.size)
        self.k = 0.0  # index of the newest sample (float: exact for integers below 2**53)
        self.started = False
        self.period = period
        self.scale = 0.0  # running mean |residual|
        self.scale_n = 0
        self.last = 0.0  # newest recovered time
        self.last_stamp = 0.0  # newest stamp as given
        self.lost = 0
        self.pending: list[tuple[float, float, float]] = []  # held stamps: index, time, offset
        self.pending_sign = 0

    PRIOR_SAMPLES = 64

    def _prior_weight(self) -> float:
        n = self.fit.n
        if n >= self.PRIOR_SAMPLES:
            return 0.0
        half = self.PRIOR_SAMPLES / 2.0
        return half**3 / 12.0 * (1.0 - n / self.PRIOR_SAMPLES)

    def step(self, y: float, dk: int, detect_gaps: bool, resolution: float) -> float:
        """Feeds a stamp ``y`` of the sample ``dk`` indices after the previous one; returns
        its recovered time (same unit). ``resolution``: the stamp's own rounding step."""
        if not self.started:
            self.started = True
            self.k = 0.0
            self.fit.add(0.0, y)
            self.last = y
            self.last_stamp = y
            return y
        silence = y - self.last_stamp
        self.last_stamp = y
        self.k += dk
        advance = float(dk)
        if detect_gaps and self.fit.n >= 8:
            advance += self._watch_gaps(y, silence)
        else:
            self._flush()
            self._absorb(self.k, y)
        slope = self._slope()
        if slope is not None and slope > 0.0:
            self.period = slope
            # advance by the fitted period, then pull toward the fitted line: the step from
            # sample to sample carries the period's small noise, not the line's end-point jitter
            ahead = self.last + slope * advance
            gain = min(1.0, max(self.pull, 2.0 / self.fit.n))
            r = ahead + gain * (self.fit.at(self.k, slope) - ahead)
        else:
            r = y
        # monotonic: never less than a quarter period per index after the previous sample
        floor = self.last + 0.25 * self.period * advance
        if r < floor:
            r = floor
        if abs(y - r) <= max(self.tuning.snap * self.period, 2.0 * resolution):
            r = y
        self.last = r
        return r

    def _slope(self) -> float | None:
        return self.fit.slope(prior=self.period_nominal, weight=self._prior_weight())

    def _absorb(self, x: float, y: float) -> None:
        """Adds one stamp to the fit, clipped around the line's prediction (Huber-like)."""
        slope = self._slope()
        period = self.period if slope is None else slope
        # with one point in the fit the line through it at the current period is still the
        # prediction: the next stamp may be a whole block (many indices) later
        pred = self.fit.at(x, period) if self.fit.n else self.last + period
        e = y - pred
        bound = max(self.tuning.clip * self.scale, period) if self.scale_n >= 8 else 4.0 * period
        ec = min(max(e, -bound), bound)
        self.scale_n += 1
        self.scale += (abs(ec) - self.scale) / min(self.scale_n, 64)
        self.fit.add(x, pred + ec)

    def _flush(self) -> None:
        """Stamps held back as a possible gap turned out to be a stall: fit them as they are."""
        for x, y, _ in self.pending:
            self._absorb(x, y)
        self.pending.clear()
        self.pending_sign = 0

    #: a stamp that comes after a silence of more than this many periods and lies as many
    #: periods late is a gap at once (lost samples), not a late run to confirm
    GAP_AT_ONCE = 4.0

    def _watch_gaps(self, y: float, silence: float) -> float:
        """Stamps more than half a period off the line are held out of the fit; when
        ``confirm`` of them follow one another on the same side, the index moves by their
        median offset in whole periods (a gap) and they join the fit. A stamp that ends a
        silence of more than GAP_AT_ONCE periods (and GAP_AT_ONCE times the stamps' usual
        scatter) and lies as late moves the index at once: its
        samples were lost, and the step across the gap must carry the gap's time now, where
        the estimators integrate it (a stall that a catch-up burst follows is undone as a
        run of early stamps). Returns the index shift."""
        slope = self._slope()
        period = self.period if slope is None else slope
        e = y - self.fit.at(self.k, period)
        # stamps that arrive in bursts (a FIFO block stamped with its read time) scatter by
        # half a block around the line: a gap at once must stand out of that scatter too
        at_once = self.GAP_AT_ONCE * max(period, self.scale)
        if self.scale_n >= self.fit.size // 2 and e > at_once and silence > at_once:
            self._flush()
            m = whole_periods(e, period)
            self.k += m
            self.lost += m
            self._absorb(self.k, y)
            return float(m)
        side = 1 if e > 0.5 * period else (-1 if e < -0.5 * period else 0)
        if side == 0 or (self.pending and side != self.pending_sign):
            self._flush()
            if side == 0:
                self._absorb(self.k, y)
                return 0.0
        self.pending_sign = side
        self.pending.append((self.k, y, e))
        if len(self.pending) < self.confirm:
            return 0.0
        m = whole_periods(float(np.median([p[2] for p in self.pending])), period)
        if m != 0:
            # the held stamps came after the gap: their indices move on by m
            self.pending = [(x + m, yy, ee) for x, yy, ee in self.pending]
            self.k += m
            self.lost += m
        self._flush()
        return float(m)


class SampleClock:
    """Causal recovery of sample times on the sensor's steady clock.

    ``nominal_rate_hz`` is the sensor's configured output rate (Hz); the tracked rate starts
    there and follows the stamps. Times are monotonic-clock nanoseconds (int64) with the
    default ``unit="ns"``, float seconds with ``unit="s"``. Other keywords: ``ClockTuning``.
    """

    def __init__(self, nominal_rate_hz: float, *, unit: str = "ns", **tuning: float) -> None:
        try:
            rate = float(nominal_rate_hz)
        except (TypeError, ValueError):
            raise ValueError(f"sample clock: nominal_rate_hz must be a number, got {nominal_rate_hz!r}") from None
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f"sample clock: nominal_rate_hz must be positive, got {nominal_rate_hz!r}")
        if unit not in ("ns", "s"):
            raise ValueError(f"sample clock: unit must be 'ns' or 's', got {unit!r}")
        unknown = sorted(set(tuning) - set(ClockTuning.__dataclass_fields__))
        if unknown:
            raise ValueError(
                f"sample clock: unknown tuning {', '.join(unknown)}; "
                f"accepted: {', '.join(ClockTuning.__dataclass_fields__)}"
            )
        self.tuning = ClockTuning(**tuning)
        self.nominal_rate_hz = rate
        self.unit = unit
        self._per_s = 1e9 if unit == "ns" else 1.0
        self._core = _Recovery(self._per_s / rate, self._per_s, self.tuning)
        self._origin: int | float | None = None
        self._last_index: int | None = None
        self._mode: str | None = None

    # ------------------------------------------------------------------ state
    @property
    def rate_hz(self) -> float:
        """Tracked sample rate, Hz (the nominal rate until two stamps have been seen)."""
        return self._per_s / self._core.period

    @property
    def lost_samples(self) -> int:
        """Whole missing periods detected so far (from counter gaps or confirmed late runs)."""
        return self._core.lost

    # ------------------------------------------------------------------ feeding
    def _rel(self, t: int | float) -> float:
        if self._origin is None:
            self._origin = t
        return float(t - self._origin)

    def _out(self, r: float, raw: int | float, y: float):
        if r == y:
            return raw  # snapped: the stamp itself, bit for bit
        if self.unit == "ns":
            return int(self._origin) + int(round(r))
        return self._origin + r

    def _resolution(self, raw: int | float) -> float:
        return 1.0 if self.unit == "ns" else float(np.spacing(float(raw)))

    def _check_mode(self, mode: str) -> None:
        if self._mode is None:
            self._mode = mode
        elif self._mode != mode:
            raise ValueError("sample clock: do not mix stamp() and stamp_indexed() on one clock")

    def _check_time(self, t: int | float, what: str) -> None:
        if self.unit == "ns":
            if not isinstance(t, (int, np.integer)):
                raise ValueError(f"sample clock: {what} must be integer nanoseconds, got {t!r}")
        elif not math.isfinite(float(t)):
            raise ValueError(f"sample clock: {what} must be finite seconds, got {t!r}")

    def stamp(self, host_t_ns: int | float, n: int = 1) -> np.ndarray:
        """n consecutive samples whose newest was read/arrived at ``host_t_ns``; returns their
        recovered times, oldest first (int64 ns, or float64 s with ``unit="s"``)."""
        self._check_mode("stamp")
        self._check_time(host_t_ns, "host_t_ns")
        n = int(n)
        if n < 1:
            raise ValueError(f"sample clock: n must be at least 1, got {n}")
        raw = host_t_ns
        first = self._origin is None
        y = self._rel(raw)
        core = self._core
        previous = core.last
        r = core.step(y, n, detect_gaps=True, resolution=self._resolution(raw))
        if first and n > 1:
            # the first block: its older samples lie a nominal period apart before the newest
            core.k = float(n - 1)
            core.fit.shift_newest(1, float(n - 1))
        newest = self._out(r, raw, y)
        dtype = np.int64 if self.unit == "ns" else np.float64
        out = np.empty(n, dtype=dtype)
        out[-1] = newest
        # the block's older samples a tracked period apart before the newest; should the
        # block's start fall at or before the previous block's newest sample (a block read
        # early, or a period still settling), they are spread evenly after it instead, so
        # times always increase
        step = core.period
        if not first and r - (n - 1) * step <= previous:
            step = (r - previous) / n
        for j in range(1, n):
            out[n - 1 - j] = self._out(r - j * step, raw, float("nan"))
        return out

    def stamp_indexed(self, host_t_ns: int | float, index: int) -> int | float:
        """One sample with a known, increasing sample counter ``index`` (unwrapped): a jump of
        the counter by m counts m − 1 lost samples. Returns its recovered time."""
        self._check_mode("indexed")
        self._check_time(host_t_ns, "host_t_ns")
        index = int(index)
        if self._last_index is None:
            dk = 1
        else:
            dk = index - self._last_index
            if dk < 1:
                raise ValueError(
                    f"sample clock: sample index must increase, got {index} after {self._last_index}"
                )
        first = self._last_index is None
        self._last_index = index
        y = self._rel(host_t_ns)
        r = self._core.step(y, dk, detect_gaps=False, resolution=self._resolution(host_t_ns))
        if not first and dk > 1:
            self._core.lost += dk - 1
        return self._out(r, host_t_ns, y)


def recover_times(t_s, nominal_rate_hz: float | None = None, **tuning: float) -> np.ndarray:
    """Recovered sample times (s) of a recording's stamps ``t_s`` (s, one per sample).

    Identical to feeding ``SampleClock(nominal_rate_hz, unit="s", **tuning)`` one stamp at a
    time: causal, and exactly uniform stamps come back bit for bit. Without
    ``nominal_rate_hz`` the median step of the stamps stands in for the sensor's configured
    rate (only the starting period; every time is still recovered from earlier stamps only).
    """
    t = np.asarray(t_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"timestamps must be one-dimensional (s), got shape {t.shape}")
    if t.size == 0:
        return t.copy()
    if nominal_rate_hz is None:
        step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
        if step <= 0 and t.size > 1 and t[-1] > t[0]:
            # bursts (several samples per stamp: most steps are 0): the mean step over the
            # recording, not the 1 Hz fallback that sent the recovered times backwards by ~1 s
            step = float(t[-1] - t[0]) / (t.size - 1)
        nominal_rate_hz = 1.0 / step if step > 0 else 1.0
    clock = SampleClock(nominal_rate_hz, unit="s", **tuning)
    out = np.empty_like(t)
    core = clock._core
    origin = float(t[0])
    clock._origin = origin
    clock._mode = "stamp"
    # the loop of SampleClock.stamp(t, 1) without its per-call checks
    for i in range(t.size):
        raw = float(t[i])
        y = raw - origin
        r = core.step(y, 1, detect_gaps=True, resolution=float(np.spacing(raw)))
        out[i] = raw if r == y else origin + r
    return out


__all__ = ["ClockTuning", "SampleClock", "recover_times"]
