"""Sample losses as the hardware makes them, for scoring estimators across gaps.

A *drop pattern* removes rows from a recording the way a companion computer loses them: a
FIFO that overflows while the host stalls loses a burst of consecutive samples, a dropped
link loses seconds. The estimator then runs on the kept rows with their own timestamps
(``estimators.run(..., timestamps=t[keep])``) and is scored on the kept rows only, against
the same truth, so the cost of the gaps is the ratio to the gap-free run's score on the same
rows (docs/gaps.md).

Patterns (``parse``):

* ``bursts:LO-HIms:PCT%`` — bursts whose lengths are uniform between LO and HI milliseconds,
  at random places that do not touch each other, until PCT % of the samples are gone
  (``bursts:20-100ms:10%``: what FIFO overflows do on a busy host);
* ``outage:Ss`` — one outage of S seconds in the middle of the scored part of the
  recording (``outage:2s``: a link or a bus that came back).

The places are drawn from a seeded generator (``seed``), so a pattern and a seed name one
set of lost rows on a given recording.

Scoring (``score_with_gaps``, ``compare``): for one recording and estimator, the gap-free run
and the gapped run are both scored on the recording's scored rows (``movement``) that the
pattern keeps, against the truth, with the metric of ``ahrs-service evaluate``
(``metrics.score``: total RMSE where the estimator observes heading and the recording has a
magnetometer, else inclination). After an outage, the recovery time is how long after the
outage the gapped estimate takes to come, and stay, within ``RECOVERY_TOLERANCE_DEG`` of the
gap-free one (the same angle: total or inclination). ``summarize`` and ``check_targets`` reduce
many scores to the issue's figures (mean ratio per estimator and pattern, worst RMSE, the
targets below); ``benchmarks/gaps.py`` prints them.
"""

from __future__ import annotations

import hashlib
import math
import re
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from ahrs_service import estimators
from ahrs_service.estimators.base import time_steps
from ahrs_service.evaluation import broad, dido, metrics
from ahrs_service.execution import worker_cache

#: the patterns of the gap benchmark and of ``ahrs-service evaluate --drop-pattern standard``
STANDARD_PATTERNS = (
    "bursts:20-100ms:1%",
    "bursts:20-100ms:10%",
    "bursts:20-100ms:40%",
    "bursts:20-400ms:1%",
    "bursts:20-400ms:10%",
    "bursts:20-400ms:40%",
    "outage:2s",
)

#: ``--drop-pattern`` word for all of STANDARD_PATTERNS
STANDARD = "standard"

#: the first samples are never dropped: every estimator starts from a sample, and the losses
#: are then all losses of a running filter (a start-up's own losses are a different matter)
KEEP_AT_START_S = 1.0

# ------------------------------------------------------------------------------ targets
#: the issue's targets: mean ratio (gapped / gap-free RMSE) over the recordings, per pattern
RATIO_TARGETS: Mapping[str, float] = {"bursts:20-100ms:10%": 1.25, "bursts:20-400ms:10%": 1.5}
#: no recording whose gap-free RMSE is at most BOUNDED_GAP_FREE_DEG may score above
#: BOUNDED_GAPPED_DEG with gaps (under any pattern)
BOUNDED_GAP_FREE_DEG = 5.0
BOUNDED_GAPPED_DEG = 10.0
#: after an outage: within RECOVERY_TOLERANCE_DEG of the gap-free estimate for good, at most
#: RECOVERY_TARGET_S after the outage ended
RECOVERY_TOLERANCE_DEG = 2.0
RECOVERY_TARGET_S = 5.0

_NUMBER = r"\d+(?:\.\d+)?"
_BURSTS = re.compile(rf"^bursts:(?P<lo>{_NUMBER})-(?P<hi>{_NUMBER})ms:(?P<pct>{_NUMBER})%$")
_OUTAGE = re.compile(rf"^outage:(?P<s>{_NUMBER})s$")

#: data set name -> loader module (the same functions: load_trial, list_trials, default_dir)
DATASETS = {"broad": broad, "dido": dido}


@dataclass(frozen=True)
class DropPattern:
    """One way of losing samples: bursts until a share is gone, or one outage.

    ``kind`` "bursts": lengths uniform in [``burst_min_s``, ``burst_max_s``] s until
    ``fraction`` (0–1) of the samples are gone. ``kind`` "outage": one gap of
    ``outage_s`` s in the middle of the scored samples.
    """

    kind: str
    burst_min_s: float = 0.0
    burst_max_s: float = 0.0
    fraction: float = 0.0
    outage_s: float = 0.0

    @property
    def label(self) -> str:
        """The pattern as ``parse`` reads it."""
        if self.kind == "outage":
            return f"outage:{self.outage_s:g}s"
        return f"bursts:{self.burst_min_s * 1e3:g}-{self.burst_max_s * 1e3:g}ms:{self.fraction * 100:g}%"

    def __str__(self) -> str:
        return self.label


def parse(text: str | DropPattern) -> DropPattern:
    """A pattern from its text (module docstring); ValueError naming what is wrong.

    A :class:`DropPattern` is returned as it is.
    """
    if isinstance(text, DropPattern):
        return text
    if not isinstance(text, str):
        raise ValueError(f"drop pattern {text!r}: expected text such as bursts:20-100ms:10% or outage:2s")
    text = text.strip()
    m = _BURSTS.match(text)
    if m:
        lo, hi, pct = float(m["lo"]) / 1e3, float(m["hi"]) / 1e3, float(m["pct"]) / 100.0
        if not 0.0 < lo <= hi:
            raise ValueError(f"drop pattern {text!r}: burst lengths need 0 < LO <= HI milliseconds")
        if not 0.0 < pct < 0.9:
            raise ValueError(f"drop pattern {text!r}: the share dropped must be above 0 % and below 90 %")
        return DropPattern("bursts", burst_min_s=lo, burst_max_s=hi, fraction=pct)
    m = _OUTAGE.match(text)
    if m:
        s = float(m["s"])
        if not s > 0.0:
            raise ValueError(f"drop pattern {text!r}: the outage must last more than 0 s")
        return DropPattern("outage", outage_s=s)
    raise ValueError(
        f"drop pattern {text!r} not understood; expected bursts:LO-HIms:PCT% (e.g. bursts:20-100ms:10%), "
        f"outage:Ss (e.g. outage:2s) or {STANDARD}"
    )


def parse_list(items: str | Iterable[str]) -> list[DropPattern]:
    """Patterns from comma-separated text or a list of such texts (``--drop-pattern``, repeatable);
    ``standard`` stands for STANDARD_PATTERNS. Duplicates are dropped, order kept; ValueError
    for a bad pattern or for none at all."""
    texts = [items] if isinstance(items, str) else list(items)
    out: list[DropPattern] = []
    for part in (p.strip() for text in texts for p in str(text).split(",")):
        if not part:
            continue
        for pattern in (STANDARD_PATTERNS if part == STANDARD else (part,)):
            parsed = parse(pattern)
            if parsed not in out:
                out.append(parsed)
    if not out:
        raise ValueError(f"no drop pattern given in {texts!r}")
    return out


# ------------------------------------------------------------------------------ dropping rows


def _period(t: np.ndarray) -> float:
    """The mean sample period (s): host stamps jitter (DIDO's median step is 2–4 % short)."""
    return float((t[-1] - t[0]) / (t.size - 1)) if t.size > 1 else math.nan


def kept_rows(t: np.ndarray, pattern: DropPattern | str, *, seed: int = 0, scored: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask of the rows a recording keeps under ``pattern``.

    ``t`` the sample times, s (N,); ``scored`` the rows that are scored (an outage goes in
    their middle; default all). The first KEEP_AT_START_S and the last row are always kept.

    Bursts: lengths drawn uniform in [LO, HI] s (whole samples, at least one) until their sum is
    nearest to the share of the N samples; then placed at random with at least one kept row
    between two bursts (the kept rows spread over the gaps between bursts uniformly at random).
    A recording too short for them all keeps fewer bursts (the share falls short). Outage: the
    rows within ±S/2 s of the middle scored row's time, cut to the droppable rows.
    """
    pattern = parse(pattern)
    t = np.asarray(t, dtype=float)
    n = t.size
    keep = np.ones(n, bool)
    if n < 3:
        return keep
    first = max(1, int(np.searchsorted(t, t[0] + KEEP_AT_START_S)))
    if first >= n - 1:
        return keep
    if pattern.kind == "outage":
        rows = np.flatnonzero(scored) if scored is not None and np.any(scored) else np.arange(n)
        middle = t[rows[len(rows) // 2]]
        lo = max(first, int(np.searchsorted(t, middle - pattern.outage_s / 2)))
        hi = min(n - 1, int(np.searchsorted(t, middle + pattern.outage_s / 2)))
        keep[lo:hi] = False
        return keep
    rng = np.random.default_rng(seed)
    target = int(round(pattern.fraction * n))
    period = _period(t)
    droppable = n - 1 - first  # rows first … n-2
    lengths: list[int] = []
    total = 0
    while total < target:  # each burst is at least one row: at most `target` draws
        draws = rng.uniform(pattern.burst_min_s, pattern.burst_max_s, size=64)
        for length in np.maximum(1, np.rint(draws / period)).astype(int):
            lengths.append(int(length))
            total += int(length)
            if total >= target:
                break
    # the last burst overshoots the share: keep it only if that lands nearer to the share
    if lengths and total - target > target - (total - lengths[-1]):
        total -= lengths.pop()
    # bursts need a kept row between each other: fewer bursts where the recording is too short
    while lengths and total + len(lengths) - 1 > droppable:
        total -= lengths.pop()
    if not lengths:
        return keep
    m = len(lengths)
    spare = droppable - total - (m - 1)  # kept rows free to place (beyond one between bursts)
    # a random split of the spare rows into the m + 1 stretches before, between and after
    cuts = np.sort(rng.integers(0, spare + 1, size=m))
    before = np.diff(np.concatenate(([0], cuts)))  # spare rows before each burst
    start = first
    for length, spare_before, k in zip(lengths, before, range(m)):
        start += int(spare_before) + (1 if k else 0)
        keep[start : start + length] = False
        start += length
    return keep


def dropped_runs(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(first, end) row indices of each run of dropped rows (``end`` exclusive)."""
    lost = ~np.asarray(keep, dtype=bool)
    edges = np.diff(np.concatenate(([0], lost.astype(np.int8), [0])))
    return np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)


def gap_lengths(t: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Durations (s) of the gaps the kept rows see: the step across each run of dropped rows,
    from the kept row before it to the kept row after it (one period more than the dropped
    rows span). A run at either end of the recording has no step across it and is left out."""
    t = np.asarray(t, dtype=float)
    keep = np.asarray(keep, dtype=bool)
    first, end = dropped_runs(keep)
    inner = (first > 0) & (end < t.size)
    return t[end[inner]] - t[first[inner] - 1]


# ------------------------------------------------------------------------------ running


def sample_times(trial: Any) -> np.ndarray:
    """The recording's sample times, s: its own stamps (DIDO), else ``arange(N) / rate_hz`` (BROAD)."""
    stamps = getattr(trial, "timestamps", None)
    if stamps is not None:
        return np.asarray(stamps, dtype=float)
    return np.arange(len(trial), dtype=float) / float(trial.rate_hz)


def has_mag(trial: Any) -> bool:
    """False for recordings without a magnetometer (DIDO)."""
    return not bool(np.isnan(trial.mag).all())


def heading_scored(estimator: str, trial: Any) -> bool:
    """Whether ``evaluate`` scores the estimator's heading on the recording (total RMSE):
    it observes heading, uses a magnetometer, and the recording has one."""
    cls = estimators.get(estimator)
    return bool(cls.observes_heading and cls.uses_mag) and has_mag(trial)


def _trial_key(trial: Any) -> tuple:
    t = sample_times(trial)
    return (trial.name, len(trial), float(t[0]), float(t[-1])) if len(trial) else (trial.name, 0)


def gap_free_steps(trial: Any, *, recover_clock: bool = True) -> np.ndarray:
    """The time steps of the gap-free run, as ``evaluate`` gives them: the recording's stamps
    (recovered onto the sensor's clock) when it has them, else its rate (cached per process)."""
    stamps = getattr(trial, "timestamps", None)
    rate = trial.rate_hz if stamps is None else None
    key = ("gap-free steps", *_trial_key(trial), recover_clock)
    return worker_cache(key, lambda: time_steps(len(trial), rate, stamps, recover_clock=recover_clock))


def gapped_steps(trial: Any, keep: np.ndarray, *, recover_clock: bool = True) -> np.ndarray:
    """The time steps of the kept rows, as ``estimators.run(..., timestamps=t[keep])`` makes them
    (BROAD's rate as the nominal rate; cached per process and set of kept rows)."""
    keep = np.asarray(keep, dtype=bool)
    stamps = getattr(trial, "timestamps", None)
    rate = trial.rate_hz if stamps is None else None
    t = sample_times(trial)[keep]
    digest = hashlib.blake2b(np.packbits(keep).tobytes(), digest_size=16).hexdigest()
    key = ("gapped steps", *_trial_key(trial), digest, recover_clock)
    return worker_cache(key, lambda: time_steps(t.size, rate, t, recover_clock=recover_clock))


def run_gap_free(
    trial: Any, estimator: str, params: Mapping[str, Any] | None = None, *, recover_clock: bool = True
) -> np.ndarray:
    """(N, 4) NED estimate of the whole recording, as ``evaluate`` runs it."""
    mag = trial.mag if estimators.get(estimator).uses_mag else None
    steps = gap_free_steps(trial, recover_clock=recover_clock)
    return estimators.create(estimator, **dict(params or {})).run(trial.gyr, trial.acc, mag, dt=steps)


def run_gapped(
    trial: Any,
    estimator: str,
    keep: np.ndarray,
    params: Mapping[str, Any] | None = None,
    *,
    recover_clock: bool = True,
) -> np.ndarray:
    """(K, 4) NED estimate over the K kept rows only, each with its own time."""
    keep = np.asarray(keep, dtype=bool)
    mag = trial.mag[keep] if estimators.get(estimator).uses_mag else None
    steps = gapped_steps(trial, keep, recover_clock=recover_clock)
    return estimators.create(estimator, **dict(params or {})).run(trial.gyr[keep], trial.acc[keep], mag, dt=steps)


# ------------------------------------------------------------------------------ scoring


@dataclass(frozen=True)
class GapScore:
    """One estimator on one recording under one drop pattern.

    ``gap_free`` and ``gapped`` are ``metrics.TrialScore``s of the two runs over the same rows:
    the recording's scored rows that the pattern keeps (rows the gapped run leaves without an
    attitude, NaN, are in neither: ``unscored_rows`` counts them). ``kind`` is the error the
    headline figures use: "total" where heading is scored (the estimator observes it with a
    magnetometer and the recording has one), else "inclination".

    ``recovery_s`` (outage patterns; None for bursts): seconds from the first row after the
    outage until the angle (of ``kind``) between the gapped and the gap-free estimates stays
    below RECOVERY_TOLERANCE_DEG to the end of the recording; 0 when it never left; ``inf``
    when it is not back by the end (``observed_after_s`` says how long the recording ran on).
    """

    trial: str
    estimator: str
    pattern: str
    seed: int
    kind: str
    dropped_fraction: float
    gaps: int
    longest_gap_s: float
    gap_free: metrics.TrialScore
    gapped: metrics.TrialScore
    unscored_rows: int = 0
    recovery_s: float | None = None
    observed_after_s: float | None = None
    max_divergence_deg: float | None = None

    @property
    def rmse_gap_free(self) -> float:
        return _rmse(self.gap_free, self.kind)

    @property
    def rmse_gapped(self) -> float:
        return _rmse(self.gapped, self.kind)

    @property
    def ratio(self) -> float:
        """Gapped over gap-free RMSE (NaN when either is missing, inf over a zero)."""
        a, b = self.rmse_gapped, self.rmse_gap_free
        if math.isnan(a) or math.isnan(b):
            return math.nan
        return a / b if b > 0.0 else (math.inf if a > 0.0 else 1.0)

    @property
    def recovered(self) -> bool | None:
        """After an outage: whether the gapped estimate came back within the tolerance for good."""
        return None if self.recovery_s is None else math.isfinite(self.recovery_s)

    def as_dict(self) -> dict:
        """Plain values for JSON: the fields, the two scores as dicts, and the headline figures."""
        d = asdict(self)
        d.update(rmse_gap_free=self.rmse_gap_free, rmse_gapped=self.rmse_gapped, ratio=self.ratio,
                 recovered=self.recovered)
        return d


def _rmse(score: metrics.TrialScore, kind: str) -> float:
    value = score.get(kind)
    return math.nan if value is None else float(value)


def recovery_time(t: np.ndarray, angle_deg: np.ndarray, start: int, tolerance_deg: float = RECOVERY_TOLERANCE_DEG) -> float:
    """Seconds from row ``start`` until ``angle_deg`` stays below ``tolerance_deg`` for good:
    0 when it never reaches it from ``start`` on, ``inf`` when it is at or above it (or NaN) at
    the last row. ``t`` and ``angle_deg`` are per row (the kept rows)."""
    tail = np.asarray(angle_deg[start:], dtype=float)
    if tail.size == 0:
        return math.inf
    bad = ~(tail < tolerance_deg)  # NaN counts as not within
    if not bad.any():
        return 0.0
    last = int(np.flatnonzero(bad)[-1])
    if last == tail.size - 1:
        return math.inf
    return float(t[start + last + 1] - t[start])


def compare(
    trial: Any,
    q_free: np.ndarray,
    q_gapped: np.ndarray,
    keep: np.ndarray,
    *,
    pattern: DropPattern | str,
    with_heading: bool,
    estimator: str = "",
    seed: int = 0,
) -> GapScore:
    """Scores a gapped run against the gap-free one on the same rows (the class docstring).

    ``q_free`` (N, 4) NED over the whole recording; ``q_gapped`` (K, 4) NED over the K rows
    ``keep`` marks; ``with_heading`` as ``metrics.score`` takes it.
    """
    pattern = parse(pattern)
    keep = np.asarray(keep, dtype=bool)
    q_free = np.asarray(q_free, dtype=float)
    q_gapped = np.asarray(q_gapped, dtype=float)
    n = len(trial)
    if keep.shape != (n,) or q_free.shape != (n, 4) or q_gapped.shape != (int(keep.sum()), 4):
        raise ValueError(
            f"compare: keep {keep.shape}, gap-free {q_free.shape} and gapped {q_gapped.shape} estimates "
            f"do not fit a recording of {n} rows with {int(keep.sum())} kept"
        )
    q_gap_full = np.full((n, 4), np.nan)
    q_gap_full[keep] = q_gapped
    free_ok = np.isfinite(q_free).all(axis=1)
    gap_ok = np.isfinite(q_gap_full).all(axis=1)
    rows = np.asarray(trial.movement, dtype=bool) & keep & free_ok
    common = rows & gap_ok
    kwargs = dict(rate_hz=trial.rate_hz, with_heading=with_heading)
    gap_free = metrics.score(q_free, trial.ref, common, **kwargs)
    gapped = metrics.score(np.where(common[:, None], q_gap_full, q_free), trial.ref, common, **kwargs)

    t = sample_times(trial)
    lengths = gap_lengths(t, keep)
    kind = "total" if with_heading else "inclination"
    recovery = observed = divergence = None
    if pattern.kind == "outage":
        first, end = dropped_runs(keep)
        if end.size and end[-1] < n:
            after = end[np.argmax(end - first)]  # the first row after the (longest) outage
            t_kept = t[keep]
            start = int(np.searchsorted(t_kept, t[after]))
            total, _, incl = metrics.error_angles(q_gapped, q_free[keep])
            angle = np.degrees(total if with_heading else incl)
            recovery = recovery_time(t_kept, angle, start)
            observed = float(t_kept[-1] - t_kept[start])
            tail = angle[start:]
            divergence = float(np.nanmax(tail)) if np.isfinite(tail).any() else math.nan
    return GapScore(
        trial=trial.name,
        estimator=estimator,
        pattern=pattern.label,
        seed=int(seed),
        kind=kind,
        dropped_fraction=float(1.0 - keep.mean()) if n else 0.0,
        gaps=int(dropped_runs(keep)[0].size),
        longest_gap_s=float(lengths.max()) if lengths.size else 0.0,
        gap_free=gap_free,
        gapped=gapped,
        unscored_rows=int((rows & ~gap_ok).sum()),
        recovery_s=recovery,
        observed_after_s=observed,
        max_divergence_deg=divergence,
    )


def score_with_gaps(
    trial: Any,
    estimator: str,
    pattern: DropPattern | str,
    seed: int = 0,
    *,
    params: Mapping[str, Any] | None = None,
    q_free: np.ndarray | None = None,
    recover_clock: bool = True,
) -> GapScore:
    """Drops rows of ``trial`` (a BROAD ``Trial`` or a DIDO ``Flight``) by ``pattern`` and
    ``seed``, runs ``estimator`` (with ``params``) on the kept rows and scores it against its
    gap-free run (``q_free`` when given, else run here) on the same rows; see :class:`GapScore`.

    >>> s = score_with_gaps(trial, "robust", "bursts:20-100ms:10%")   # doctest: +SKIP
    >>> s.ratio, s.rmse_gapped, s.rmse_gap_free                       # doctest: +SKIP
    """
    pattern = parse(pattern)
    keep = kept_rows(sample_times(trial), pattern, seed=seed, scored=trial.movement)
    if q_free is None:
        q_free = run_gap_free(trial, estimator, params, recover_clock=recover_clock)
    q_gapped = run_gapped(trial, estimator, keep, params, recover_clock=recover_clock)
    return compare(trial, q_free, q_gapped, keep, pattern=pattern, with_heading=heading_scored(estimator, trial),
                   estimator=estimator, seed=seed)


def score_patterns(
    trial: Any,
    estimator: str,
    patterns: Sequence[DropPattern | str] = STANDARD_PATTERNS,
    seed: int = 0,
    *,
    params: Mapping[str, Any] | None = None,
    recover_clock: bool = True,
) -> list[GapScore]:
    """:func:`score_with_gaps` for each pattern, with one gap-free run."""
    q_free = run_gap_free(trial, estimator, params, recover_clock=recover_clock)
    return [
        score_with_gaps(trial, estimator, p, seed, params=params, q_free=q_free, recover_clock=recover_clock)
        for p in patterns
    ]


# ------------------------------------------------------------------------------ jobs (benchmark)


@dataclass(frozen=True)
class GapJob:
    """One task of the gap benchmark: an estimator over one recording under every pattern
    (the recording named, loaded on the worker that runs the job)."""

    dataset: str  # a key of DATASETS
    data_dir: str
    recording: str
    estimator: str
    patterns: tuple[str, ...] = STANDARD_PATTERNS
    seed: int = 0
    params: tuple[tuple[str, Any], ...] = ()
    recover_clock: bool = True


def load_recording(dataset: str, data_dir: str, name: str) -> Any:
    """A recording, read once per process (the key ``evaluate`` uses too)."""
    return worker_cache((dataset, data_dir, name), lambda: DATASETS[dataset].load_trial(data_dir, name))


def recording_of(job: GapJob) -> tuple[str, str, str]:
    """What a job reads: jobs are placed beside it (``Runner.map``'s ``place_by``)."""
    return (job.dataset, job.data_dir, job.recording)


def prepare_recording(recording: tuple[str, str, str]) -> bool:
    """Loads a recording into this worker's cache (``Runner.map``'s ``prepare``)."""
    load_recording(*recording)
    return True


def run_gap_job(job: GapJob) -> list[GapScore]:
    """Runs one :class:`GapJob`: a score per pattern, in the job's pattern order."""
    trial = load_recording(*recording_of(job))
    return score_patterns(trial, job.estimator, job.patterns, job.seed, params=dict(job.params),
                          recover_clock=job.recover_clock)


def warm_up(estimator: str) -> str:
    """Compiles (or loads from numba's cache) an estimator's batch kernel in this process."""
    cls = estimators.get(estimator)
    rng = np.random.default_rng(0)
    acc = np.tile([0.0, 0.0, 9.81], (16, 1)) + rng.normal(0.0, 0.01, (16, 3))
    mag = np.tile([20.0, 0.0, 40.0], (16, 1)) if cls.uses_mag else None
    estimators.create(estimator).run(np.zeros((16, 3)), acc, mag, dt=np.full(16, 0.0035))
    return estimator


# ------------------------------------------------------------------------------ summaries


@dataclass
class GapSummary:
    """An estimator under one pattern over many recordings.

    ``mean_ratio`` the mean of the recordings' ratios; ``worst_*`` the recording with the
    largest gapped RMSE; ``bounded_misses`` the recordings whose gap-free RMSE is at most
    BOUNDED_GAP_FREE_DEG and whose gapped RMSE is above BOUNDED_GAPPED_DEG; ``recovery_s`` per
    recording after an outage (empty for bursts).
    """

    estimator: str
    pattern: str
    recordings: int
    mean_gap_free: float
    mean_gapped: float
    mean_ratio: float
    worst_ratio: float
    worst_gapped: float
    worst_recording: str
    bounded_misses: list[str] = field(default_factory=list)
    recovery_s: dict[str, float] = field(default_factory=dict)

    @property
    def worst_recovery_s(self) -> float | None:
        return max(self.recovery_s.values()) if self.recovery_s else None


def _nanmean(values: list[float]) -> float:
    v = np.asarray(values, dtype=float)
    v = v[~np.isnan(v)]
    return float(v.mean()) if v.size else math.nan


def summarize(scores: Iterable[GapScore]) -> dict[tuple[str, str], GapSummary]:
    """(estimator, pattern) → :class:`GapSummary`, in the order the pairs first appear."""
    groups: dict[tuple[str, str], list[GapScore]] = {}
    for s in scores:
        groups.setdefault((s.estimator, s.pattern), []).append(s)
    out = {}
    for (name, pattern), items in groups.items():
        gapped = [s.rmse_gapped for s in items]
        worst = max(items, key=lambda s: -math.inf if math.isnan(s.rmse_gapped) else s.rmse_gapped)
        ratios = [s.ratio for s in items]
        out[(name, pattern)] = GapSummary(
            estimator=name,
            pattern=pattern,
            recordings=len(items),
            mean_gap_free=_nanmean([s.rmse_gap_free for s in items]),
            mean_gapped=_nanmean(gapped),
            mean_ratio=_nanmean(ratios),
            worst_ratio=float(np.nanmax(ratios)) if not np.isnan(ratios).all() else math.nan,
            worst_gapped=worst.rmse_gapped,
            worst_recording=worst.trial,
            bounded_misses=[
                s.trial for s in items
                if s.rmse_gap_free <= BOUNDED_GAP_FREE_DEG and not s.rmse_gapped <= BOUNDED_GAPPED_DEG
            ],
            recovery_s={s.trial: s.recovery_s for s in items if s.recovery_s is not None},
        )
    return out


def _some(names: list[str], shown: int = 3) -> str:
    """Up to ``shown`` names, then how many more."""
    more = len(names) - shown
    return ", ".join(names[:shown]) + (f" and {more} more" if more > 0 else "")


@dataclass
class TargetCheck:
    """One of the issue's targets: whether it is met, and by whom it is missed (one line each)."""

    name: str
    met: bool
    misses: list[str] = field(default_factory=list)


def check_targets(summaries: Mapping[tuple[str, str], GapSummary]) -> list[TargetCheck]:
    """The issue's targets over the summaries given (a target whose pattern was not run is
    left out): mean ratio per RATIO_TARGETS pattern; bounded error under every pattern;
    recovery after every outage pattern."""
    checks = []
    by_pattern: dict[str, list[GapSummary]] = {}
    for s in summaries.values():
        by_pattern.setdefault(s.pattern, []).append(s)
    for pattern, limit in RATIO_TARGETS.items():
        if pattern in by_pattern:
            misses = [f"{s.estimator} {s.mean_ratio:.2f}x" for s in by_pattern[pattern] if not s.mean_ratio <= limit]
            checks.append(TargetCheck(f"mean ratio <= {limit:g}x at {pattern}", not misses, misses))
    if summaries:
        misses = [
            f"{s.estimator} at {s.pattern} on {_some(s.bounded_misses)}" for s in summaries.values() if s.bounded_misses
        ]
        checks.append(TargetCheck(
            f"no recording <= {BOUNDED_GAP_FREE_DEG:g} deg gap-free above {BOUNDED_GAPPED_DEG:g} deg with gaps",
            not misses, misses))
    for pattern, items in by_pattern.items():
        if parse(pattern).kind != "outage":
            continue
        misses = []
        for s in items:
            late = {r: v for r, v in s.recovery_s.items() if not v <= RECOVERY_TARGET_S}
            if late:
                misses.append(f"{s.estimator} on {len(late)} of {len(s.recovery_s)} (worst {max(late.values()):.1f} s)")
        checks.append(TargetCheck(
            f"back within {RECOVERY_TOLERANCE_DEG:g} deg of gap-free <= {RECOVERY_TARGET_S:g} s after {pattern}",
            not misses, misses))
    return checks
