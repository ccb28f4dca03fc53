"""``ahrs-service evaluate``: runs estimators (and peer libraries) over BROAD and reports as the papers did.

For every trial: BROAD's total/heading/inclination RMSE (``metrics``), the second paper's L2
index, the mean error ("mean value", third paper) and the cost of an update, measured with the
batch run; and the recording's own timing, how late its IMU samples are against the
reference (``metrics.imu_delay``). Per group: the mean of its trials' RMSEs. Across trials:
Friedman + Nemenyi (``stats``). Written as ``results.json``, ``results.md`` and PNG plots,
each carrying the BROAD citation.

With ``--offline`` every selected column X gets a twin column "X+offline": the same estimator
(or peer) run forward and backward over the recording and fused
(``ahrs_service.estimators.offline``), scored alike, beside the causal X.

With ``--drop-pattern`` every estimator column (causal or offline; not the peers, which take a
constant rate) is also run on the rows each pattern keeps, and the gapped and gap-free runs are
scored on the same rows (``ahrs_service.evaluation.gaps``, docs/gaps.md): ``results["gaps"]``.
"""

from __future__ import annotations

import datetime as _dt
import functools
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ahrs_service import estimators
from ahrs_service.estimators import offline as offline_mode
from ahrs_service.estimators.base import stack_rows, time_steps
from ahrs_service.estimators.settings import check_estimator_params
from ahrs_service.evaluation import broad, dido, gaps, metrics, peers, stats
from ahrs_service.execution import Runner, open_runner, worker_cache

#: ``--dataset`` name → the module that reads it (same functions: default_dir, check_dir,
#: list_trials, list_groups, load_trial, CITATION).
DATASETS = {"broad": broad, "dido": dido}

#: Title of each data set in the report.
TITLES = {"broad": "BROAD", "dido": "DIDO (quadrotor flights)"}


def has_mag(trial: Any) -> bool:
    """False for recordings without a magnetometer (DIDO): scored on inclination only."""
    return not bool(np.isnan(trial.mag).all())


def stamps_of(trial: Any) -> np.ndarray | None:
    """The recording's own sample times (s) when it has them (DIDO), else None (BROAD: rate)."""
    return getattr(trial, "timestamps", None)
from ahrs_service.core.quaternion import ned_to_enu_array
from ahrs_service.estimators import SAMPLE_ROW

_R = SAMPLE_ROW.slices


@dataclass
class Column:
    """One column of the results: an estimator of ours or a peer library, causal or offline.

    An offline column is named "<base>+offline" and runs ``base`` forward and backward
    (``estimators.offline``) with fusion time constant ``blend_time_s``.
    """

    name: str
    kind: str  # "estimator" | "peer"
    observes_heading: bool
    uses_mag: bool
    params: dict[str, Any] = field(default_factory=dict)
    offline: bool = False
    base: str = ""  # the estimator or peer run; "" means ``name``
    blend_time_s: float = offline_mode.DEFAULT_BLEND_TIME_S

    def __post_init__(self) -> None:
        if not self.base:
            self.base = self.name

    @property
    def scores_heading(self) -> bool:
        # heading is only observable with a magnetometer in the loop
        return self.observes_heading and self.uses_mag


# ------------------------------------------------------------------------------ selection


def select_estimators(spec: str | None) -> tuple[list[str], list[str]]:
    """Estimator names for ``--estimators`` ("all" or "a,b"); returns (chosen, skipped-with-reason).

    "all" skips estimators whose module is not there yet; a name given explicitly must load.
    """
    spec = "all" if spec is None else spec.strip()
    if spec == "all":
        chosen, skipped = [], []
        for name in estimators.names():
            try:
                estimators.get(name)
            except ImportError as exc:
                skipped.append(f"{name} ({exc})")
                continue
            chosen.append(name)
        return chosen, skipped
    chosen = []
    for name in (s.strip() for s in spec.split(",")):
        if name and name not in chosen:
            estimators.get(name)  # ValueError for unknown names, ImportError when not built
            chosen.append(name)
    if not chosen:  # "" or ",": a typo, not a request for every estimator (a long run)
        raise ValueError(f"--estimators {spec!r}: no estimator named (comma-separated names, or all)")
    return chosen, []


def parse_params(items: list[str] | None, columns: list[str]) -> dict[str, dict[str, Any]]:
    """``name.key=value`` items → {name: {key: value}}; names must be among ``columns``.

    Values become floats when they parse as numbers (estimator parameters always do).
    """
    out: dict[str, dict[str, Any]] = {}
    for item in items or []:
        lhs, sep, value = item.partition("=")
        name, dot, key = lhs.strip().rpartition(".")
        if not sep or not dot or not name or not key:
            raise ValueError(f"--param {item!r}: expected name.key=value, e.g. madgwick.beta=0.05")
        if name not in columns:
            raise ValueError(f"--param {item!r}: {name!r} is not among the selected columns ({', '.join(columns)})")
        try:
            parsed: Any = float(value)
        except ValueError:
            parsed = value.strip()
        out.setdefault(name, {})[key] = parsed
    return out


#: Suffix of the offline twin of a column (``--offline``).
OFFLINE_SUFFIX = "+offline"


def make_columns(
    names: list[str],
    peer_names: list[str],
    params: dict[str, dict[str, Any]],
    *,
    with_offline: bool = False,
    blend_time_s: float | None = None,
) -> list[Column]:
    """Columns for the chosen estimators and peers; estimator parameters are checked here.

    ``with_offline``: each column is followed by its offline twin "<name>+offline" (same
    parameters), fused with time constant ``blend_time_s`` (s; None: the default).
    """
    if with_offline:
        blend_time_s = offline_mode.blend_time(blend_time_s)
    cols = []
    for name in names:
        cls = estimators.get(name)
        p = params.get(name, {})
        estimators.create(name, **p)  # raises ValueError for unknown or bad parameters
        cols.append(Column(name, "estimator", bool(cls.observes_heading), bool(cls.uses_mag), p))
    for name in peer_names:
        peer = peers.PEERS[name]
        cols.append(Column(name, "peer", peer.observes_heading, True, params.get(name, {})))
    if not with_offline:
        return cols
    out = []
    for col in cols:
        out.append(col)
        if col.kind == "peer" and not peers.PEERS[col.name].causal:
            continue  # already an offline method (vqf.offline): no twin
        out.append(
            Column(
                col.name + OFFLINE_SUFFIX, col.kind, col.observes_heading, col.uses_mag, dict(col.params),
                offline=True, base=col.name, blend_time_s=blend_time_s,
            )
        )
    return out


# ------------------------------------------------------------------------------ running


def _run_offline(col: Column, trial: broad.Trial) -> np.ndarray:
    """(N, 4) NED offline estimate of an offline column (both passes and the fusion)."""
    mag = trial.mag if col.uses_mag else None
    if col.kind == "estimator":
        return offline_mode.smooth(
            col.base, trial.gyr, trial.acc, mag,
            rate_hz=trial.rate_hz if stamps_of(trial) is None else None, timestamps=stamps_of(trial),
            params=col.params, blend_time_s=col.blend_time_s,
        )
    # a peer takes whole arrays at a fixed rate: the reversed rows' dt column is not needed
    rows = stack_rows(trial.gyr, trial.acc, trial.mag, time_steps(len(trial), trial.rate_hz))

    def run_rows(r: np.ndarray) -> np.ndarray:
        return peers.run(col.base, r[:, _R.gyr], r[:, _R.acc], r[:, _R.mag], rate_hz=trial.rate_hz, **col.params)

    return offline_mode.smooth_rows(run_rows, rows, blend_time_s=col.blend_time_s, align=not col.observes_heading).q


def _run_column(col: Column, trial: broad.Trial) -> tuple[np.ndarray, float]:
    """(N, 4) NED estimate and the wall time of the batch run (both passes when offline) in seconds."""
    mag = trial.mag if col.uses_mag else None
    if col.offline:
        t0 = time.perf_counter()
        q = _run_offline(col, trial)
        return q, time.perf_counter() - t0
    if col.kind == "estimator":
        t0 = time.perf_counter()
        # recorded stamps when the recording has them (recovered onto the sensor's clock by
        # estimators.run, docs/timing.md); a peer library takes a constant rate: the fitted one
        # (the fitted rate is a whole-flight figure: not given to a causal run as its nominal)
        stamps = stamps_of(trial)
        rate = trial.rate_hz if stamps is None else None
        # the steps (clock recovery included) as estimators.run makes them, once per recording
        key = ("steps", trial.name, len(trial), trial.rate_hz if stamps is None else (float(stamps[0]), float(stamps[-1])))
        steps = worker_cache(key, lambda: time_steps(len(trial), rate, stamps))
        q = estimators.create(col.name, **col.params).run(trial.gyr, trial.acc, mag, dt=steps)
        return q, time.perf_counter() - t0
    t0 = time.perf_counter()
    q = peers.run(col.name, trial.gyr, trial.acc, trial.mag, rate_hz=trial.rate_hz, **col.params)
    return q, time.perf_counter() - t0


def _warm_up(col: Column, trial: broad.Trial) -> None:
    # the first call compiles (numba) or loads caches: keep that out of the measured cost
    if col.kind == "estimator":
        n = min(32, len(trial))
        mag = trial.mag[:n] if col.uses_mag else None
        estimators.run(col.base, trial.gyr[:n], trial.acc[:n], mag, rate_hz=trial.rate_hz, **col.params)


@dataclass(frozen=True)
class TrialJob:
    """One task of ``evaluate``: a column over a trial, the trial named (loaded on the worker)."""

    data_dir: str
    trial: str
    column: Column
    with_errors: bool  # also return the per-sample errors (the plots want them)
    dataset: str = "broad"  # a key of DATASETS
    drop_patterns: tuple[str, ...] = ()  # also scored with these drop patterns (gaps.parse)
    drop_seed: int = 0


@dataclass
class TrialResult:
    """What a :class:`TrialJob` sends back: its score row and, if asked, per-sample errors (deg)."""

    trial: str
    column: str
    row: dict
    imu_delay: dict[str, float]  # {"samples", "ms"}: how late the trial's IMU samples are
    errors: dict[str, np.ndarray] | None = None
    gap_scores: dict[str, gaps.GapScore] | None = None  # drop pattern -> score (estimator columns)


def recording_of(job: TrialJob) -> tuple[str, str, str]:
    """The input a job reads, (data set, folder, recording name): jobs are placed by it."""
    return (job.dataset, job.data_dir, job.trial)


def prepare_recording(recording: tuple[str, str, str]) -> bool:
    """Loads a recording and its IMU delay into this process's cache (a worker's data);
    ``Runner.map`` runs it once per recording and places the recording's jobs beside it."""
    _load_with_delay(*recording)
    return True


#: The cost model's first guess of a job's duration (``Runner.map``'s ``cost``; the runner
#: scales it by what finished jobs took): µs per sample of each estimator's batch run and of
#: the peers' (docs/accuracy.md, BROAD on the development VM), others at the default, plus
#: scoring the estimate (RMSE, L2, mean error: measured the same way).
_RUN_US_PER_SAMPLE = {
    "complementary_reduced": 0.30, "complementary_full": 0.30, "triad": 0.12, "quest": 0.28,
    "kalman_roll_pitch": 0.26, "quaternion_kf": 0.18, "mahony_direct": 0.23, "mahony_passive": 0.17,
    "immersion_invariance": 0.19, "ekf": 0.46, "madgwick": 0.11, "valenti": 0.18, "robust": 0.29,
    "vqf": 0.46, "imufusion": 1.49,
}
_DEFAULT_RUN_US_PER_SAMPLE = 0.5
_SCORING_US_PER_SAMPLE = 0.45
_OFFLINE_COST_FACTOR = 3.0  # two passes and the fusion (docs/evaluation.md)
_NOMINAL_SAMPLES = 50_000  # a BROAD recording's size, for a file whose size cannot be read
_GYRO_DATASET = {"broad": "imu_gyr", "dido": "gyr"}


def expected_job_seconds(job: TrialJob) -> float:
    """A cheap first guess of how long ``run_trial_job(job)`` takes, seconds: the recording's
    samples (from its file's metadata, not its data) × the column's µs/sample, scoring
    included, once more per drop pattern."""
    col = job.column
    run_us = _RUN_US_PER_SAMPLE.get(col.base, _DEFAULT_RUN_US_PER_SAMPLE)
    if col.offline:
        run_us *= _OFFLINE_COST_FACTOR
    passes = 1 + (len(job.drop_patterns) if col.kind == "estimator" else 0)
    return _samples_in(*recording_of(job)) * passes * (run_us + _SCORING_US_PER_SAMPLE) * 1e-6


@functools.lru_cache(maxsize=4096)
def _samples_in(dataset: str, data_dir: str, name: str) -> int:
    """The recording's sample count from its HDF5 metadata; a nominal count when it cannot be
    read (the job itself then reports why)."""
    try:
        with DATASETS[dataset].FOLDER.open(data_dir, name, (_GYRO_DATASET[dataset],)) as f:
            return int(f[_GYRO_DATASET[dataset]].shape[0])
    except (OSError, ValueError, KeyError, IndexError):
        return _NOMINAL_SAMPLES


def _load_with_delay(dataset: str, data_dir: str, name: str) -> tuple[Any, float]:
    """(trial, its IMU delay in samples), each computed once per process."""
    trial = worker_cache((dataset, data_dir, name), lambda: DATASETS[dataset].load_trial(data_dir, name))
    delay = worker_cache(
        ("delay", dataset, data_dir, name),
        lambda: metrics.imu_delay(trial.gyr, trial.ref, trial.rate_hz, trial.movement),
    )
    return trial, delay


def run_trial_job(job: TrialJob) -> TrialResult:
    """Runs and scores one column over one trial; the same code serial or as a Dask task."""
    trial, delay = _load_with_delay(*recording_of(job))
    col = job.column
    # once per process and estimator: compile outside the measured run
    worker_cache(("warm", col.kind, col.base), lambda: _warm_up(col, trial) or True)
    q, seconds = _run_column(col, trial)
    score = metrics.score(
        q, trial.ref, trial.movement, rate_hz=trial.rate_hz, with_heading=col.scores_heading and has_mag(trial)
    )
    row = score.as_dict()
    row["us_per_sample"] = seconds / len(trial) * 1e6
    errors = None
    if job.with_errors:
        tot, head, inc = (np.degrees(a) for a in metrics.error_angles(ned_to_enu_array(q), trial.ref))
        errors = {"total": tot, "heading": head, "inclination": inc}
    imu_delay = {"samples": float(delay), "ms": float(delay) / trial.rate_hz * 1e3}
    gap_scores = None
    if job.drop_patterns and col.kind == "estimator":
        with_heading = col.scores_heading and has_mag(trial)
        t = gaps.sample_times(trial)
        gap_scores = {}
        for label in job.drop_patterns:
            keep = gaps.kept_rows(t, label, seed=job.drop_seed, scored=trial.movement)
            gap_scores[label] = gaps.compare(
                trial, q, _run_gapped(col, trial, keep), keep, pattern=label, with_heading=with_heading,
                estimator=col.name, seed=job.drop_seed,
            )
    return TrialResult(job.trial, col.name, row, imu_delay, errors, gap_scores)


def _run_gapped(col: Column, trial: broad.Trial, keep: np.ndarray) -> np.ndarray:
    """(K, 4) NED estimate of an estimator column over the K rows ``keep`` marks, each with its
    own time (``gaps.gapped_steps``: what ``estimators.run(..., timestamps=t[keep])`` integrates)."""
    steps = gaps.gapped_steps(trial, keep)
    mag = trial.mag[keep] if col.uses_mag else None
    if col.offline:
        return offline_mode.smooth(
            col.base, trial.gyr[keep], trial.acc[keep], mag, dt=steps, params=col.params, blend_time_s=col.blend_time_s
        )
    return estimators.create(col.name, **col.params).run(trial.gyr[keep], trial.acc[keep], mag, dt=steps)


def evaluate(
    data_dir: str | os.PathLike,
    columns: list[Column],
    trial_names: list[str],
    *,
    progress: bool = False,
    on_trial: Callable[[broad.Trial, dict[str, dict[str, np.ndarray]]], None] | None = None,
    dataset: str = "broad",
    runner: Runner | None = None,
    drop_patterns: Sequence[str | gaps.DropPattern] = (),
    drop_seed: int = 0,
) -> dict:
    """Runs every column over every trial and returns the results dict.

    Each (trial, column) pair is one job of ``runner`` (default: serial, in this process; on a
    cluster the jobs are grouped into tasks by :func:`expected_job_seconds`); a
    job loads its trial on the worker that runs it (once per worker), and the results are
    gathered in trial-then-column order, so they equal the serial run's whatever the runner
    (except the measured ``us_per_sample``).

    ``dataset``: "broad" (handheld, optical truth) or "dido" (quadrotor flights: recorded
    stamps, no magnetometer, inclination only, first 10 % of each flight not scored).

    ``on_trial(trial, errors)`` is called after each trial with per-column per-sample errors in
    degrees ({"total", "heading", "inclination"} → (N,) arrays) — the plots use it.

    ``drop_patterns`` (``gaps.parse``): every estimator column is also run on the rows each
    pattern keeps (places drawn with ``drop_seed``) and scored against its gap-free run on the
    same rows; the results get a ``gaps`` entry (:func:`gap_results`).
    """
    source = DATASETS[dataset]
    if not trial_names:
        raise ValueError("no trial selected")
    if not columns:
        raise ValueError("nothing to evaluate: no estimator and no peer selected")
    data_dir = str(Path(data_dir).resolve())
    labels = tuple(p.label for p in gaps.parse_list(list(map(str, drop_patterns)))) if drop_patterns else ()
    jobs = [
        TrialJob(data_dir, t, c, on_trial is not None, dataset, labels, int(drop_seed))
        for t in trial_names
        for c in columns
    ]
    runner = runner or Runner()
    results = runner.map(
        run_trial_job, jobs, progress=progress, desc="evaluate", place_by=recording_of, prepare=prepare_recording,
        cost=expected_job_seconds,
    )
    per_trial: dict[str, dict[str, dict]] = {c.name: {} for c in columns}
    imu_delays: dict[str, dict[str, float]] = {}
    for res in results:
        per_trial[res.column][res.trial] = res.row
        imu_delays[res.trial] = res.imu_delay
    if on_trial is not None:
        for i, tname in enumerate(trial_names):
            trial, _ = _load_with_delay(dataset, data_dir, tname)  # the plots draw the recording's own signals too
            on_trial(trial, {r.column: r.errors for r in results[i * len(columns):(i + 1) * len(columns)]})

    groups = source.list_groups(data_dir, trial_names)
    per_group: dict[str, dict[str, dict]] = {}
    for col in columns:
        per_group[col.name] = {}
        for gname, members in groups.items():
            per_group[col.name][gname] = {
                kind: metrics.group_mean({t: per_trial[col.name][t][f"{kind}_rmse"] for t in members}, members)
                for kind in metrics.KINDS
            } | {"l2": metrics.group_mean({t: per_trial[col.name][t]["l2"] for t in members}, members)}

    tests = {
        "inclination": stats.rank_test(
            {c.name: [per_trial[c.name][t]["inclination_rmse"] for t in trial_names] for c in columns}, trial_names
        ).as_dict(),
        "total": stats.rank_test(
            {
                c.name: [per_trial[c.name][t]["total_rmse"] for t in trial_names]
                for c in columns
                if c.scores_heading and all(per_trial[c.name][t]["total_rmse"] is not None for t in trial_names)
            },
            trial_names,
        ).as_dict(),
    }
    return {
        "dataset": dataset,
        "citation": source.CITATION,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "data_dir": str(Path(data_dir).resolve()),
        "trials": trial_names,
        "groups": groups,
        "columns": [
            {"name": c.name, "kind": c.kind, "observes_heading": c.observes_heading, "uses_mag": c.uses_mag,
             "scores_heading": c.scores_heading, "params": c.params, "offline": c.offline, "base": c.base}
            | ({"blend_time_s": c.blend_time_s} if c.offline else {})
            for c in columns
        ],
        "per_trial": per_trial,
        "per_group": per_group,
        "imu_delay": imu_delays,
        "cost_us_per_sample": {
            c.name: float(np.mean([per_trial[c.name][t]["us_per_sample"] for t in trial_names])) for c in columns
        },
        "stats": tests,
    } | ({"gaps": gap_results(results, columns, trial_names, labels, int(drop_seed))} if labels else {})


def gap_results(
    results: list[TrialResult], columns: list[Column], trial_names: list[str], labels: tuple[str, ...], seed: int
) -> dict:
    """``results["gaps"]``: the patterns and seed, the columns run with gaps, and per pattern
    ``per_trial[pattern][column][trial]`` (``GapScore.as_dict``) and ``summary[pattern][column]``
    (``gaps.summarize`` over the trials: mean gap-free and gapped RMSE, mean and worst ratio,
    worst gapped RMSE and its trial, the trials above 10° gapped at most 5° gap-free, the worst
    recovery after an outage in seconds, null when not back by the end of a recording)."""
    scores = [s for r in results if r.gap_scores for s in r.gap_scores.values()]
    gapped_columns = [c.name for c in columns if c.kind == "estimator"]
    per_trial = {
        label: {c: {t: None for t in trial_names} for c in gapped_columns} for label in labels
    }
    for s in scores:
        per_trial[s.pattern][s.estimator][s.trial] = s.as_dict()
    summaries = gaps.summarize(scores)
    dropped = {
        label: float(np.mean([s.dropped_fraction for s in scores if s.pattern == label])) if scores else math.nan
        for label in labels
    }
    summary = {
        label: {
            c: {
                "recordings": m.recordings,
                "mean_gap_free": m.mean_gap_free,
                "mean_gapped": m.mean_gapped,
                "mean_ratio": m.mean_ratio,
                "worst_ratio": m.worst_ratio,
                "worst_gapped": m.worst_gapped,
                "worst_trial": m.worst_recording,
                "bounded_misses": m.bounded_misses,
                "worst_recovery_s": m.worst_recovery_s,
            }
            for c in gapped_columns
            if (m := summaries.get((c, label))) is not None
        }
        for label in labels
    }
    return {
        "patterns": list(labels),
        "seed": seed,
        "columns": gapped_columns,
        "not_run": [c.name for c in columns if c.kind != "estimator"],
        "dropped_fraction": dropped,
        "per_trial": per_trial,
        "summary": summary,
    }


# ------------------------------------------------------------------------------ writing


def _fmt(x: float | None, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "n/a"
    return f"{x:.{digits}f}"


def to_json(results: dict, path: Path) -> None:
    """Writes the results; NaN becomes null so the file is strict JSON."""

    def clean(v):
        if isinstance(v, float):
            return v if math.isfinite(v) else None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    path.write_text(json.dumps(clean(results), indent=2, ensure_ascii=False) + "\n", encoding="utf-8")


def to_markdown(results: dict, plots: list[str] | None = None) -> str:
    """The human-readable report (GitHub-flavoured Markdown)."""
    cols = [c["name"] for c in results["columns"]]
    meta = {c["name"]: c for c in results["columns"]}
    trials = results["trials"]
    pt, pg = results["per_trial"], results["per_group"]
    dataset = results.get("dataset", "broad")
    citation = results.get("citation", broad.CITATION)
    scope = (
        "Errors in degrees, RMSE over the `movement` samples (reference gaps skipped); a group's "
        if dataset == "broad"
        else "Flights have no magnetometer: inclination only (the angle between the estimated and "
        "the true gravity direction in the IMU frame), RMSE over each flight after its first 10 %. "
        "Our estimators take the recorded stamps (recovered onto the sensor's clock, "
        "docs/timing.md); peers take the flight's fitted rate (VQF: its 6D output). A group's "
    )
    out = [
        f"# Attitude estimator evaluation on {TITLES.get(dataset, dataset)}",
        "",
        f"Data: {citation}",
        "",
        f"Created {results['created']} from `{results['data_dir']}`, {len(trials)} trial(s). "
        + scope +
        "figure is the mean of its trials' RMSEs. Estimators without heading are scored on "
        "inclination only (total and heading n/a). L2: the second paper's index "
        "√(1/(t−t₀)∫|e|dt) of the scored error, √deg. µs/sample: wall time of the batch run "
        "divided by the samples (after a warm-up call).",
        "",
    ]
    params = {c: meta[c]["params"] for c in cols if meta[c]["params"] and not meta[c].get("offline")}
    if params:
        out += ["Parameters: " + "; ".join(f"{c}: {p}" for c, p in params.items()), ""]
    blends = sorted({meta[c]["blend_time_s"] for c in cols if meta[c].get("offline")})
    if blends:
        out += [
            "Columns named `<name>+offline` are the offline (non-causal) mode of `<name>`: a forward "
            "and a backward pass over the whole recording, fused per sample with weights "
            f"1 − exp(−t/τ), τ = {', '.join(f'{b:g}' for b in blends)} s "
            "(`ahrs_service.estimators.offline`); same parameters as `<name>`. Their µs/sample "
            "covers both passes and the fusion.",
            "",
        ]
    out += ["## Summary (mean over the trials)", "",
            "| column | kind | total RMSE | heading RMSE | inclination RMSE | L2 | mean error | µs/sample |",
            "|---|---|---:|---:|---:|---:|---:|---:|"]
    for c in cols:
        rows = [pt[c][t] for t in trials]

        def mean_of(key):
            vals = [r[key] for r in rows]
            return None if any(v is None for v in vals) else float(np.nanmean(vals))

        out.append(
            f"| {c} | {meta[c]['kind']} | {_fmt(mean_of('total_rmse'))} | {_fmt(mean_of('heading_rmse'))} | "
            f"{_fmt(mean_of('inclination_rmse'))} | {_fmt(mean_of('l2'))} | {_fmt(mean_of('mean'))} | "
            f"{_fmt(results['cost_us_per_sample'][c], 3)} |"
        )
    out.append("")

    for kind in metrics.KINDS:
        out += [f"## {kind.capitalize()} RMSE per group (°)", "",
                "| group | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
        for gname, members in results["groups"].items():
            out.append(f"| {gname} ({len(members)}) | " + " | ".join(_fmt(pg[c][gname][kind]) for c in cols) + " |")
        out.append("")

    for kind in metrics.KINDS:
        out += [f"## {kind.capitalize()} RMSE per trial (°)", "",
                "| trial | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
        for t in trials:
            out.append(f"| {t} | " + " | ".join(_fmt(pt[c][t][f'{kind}_rmse']) for c in cols) + " |")
        out.append("")

    out += ["## L2 performance index per trial (√deg)", "",
            "| trial | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
    for t in trials:
        out.append(f"| {t} | " + " | ".join(_fmt(pt[c][t]["l2"], 3) for c in cols) + " |")
    out.append("")

    delays = results.get("imu_delay") or {}
    if delays:
        out += ["## Timing of the recordings", "",
                "How late each recording's IMU samples are against its reference, in sample periods "
                "(`metrics.imu_delay`: the gyro against the reference's body rate, shifted until they "
                "agree best). A causal estimator that integrates each gyro sample over the period "
                "ending at it runs d − ½ sample behind the reference, which every column's error "
                "carries alike; it is a property of the recording, not of a filter.", "",
                "| trial | IMU delay (samples) | (ms) |", "|---|---:|---:|"]
        for t in trials:
            out.append(f"| {t} | {_fmt(delays[t]['samples'])} | {_fmt(delays[t]['ms'])} |")
        out.append("")

    out += ["## Friedman and Nemenyi tests", "",
            "Blocks are the trials, treatments the columns, values the per-trial RMSEs.", ""]
    for kind, title in (("inclination", "inclination RMSE, all columns"), ("total", "total RMSE, columns with heading")):
        d = results["stats"][kind]
        test = stats.RankTest(
            columns=d["columns"], trials=d["trials"],
            statistic=d["friedman_chi2"] if d["friedman_chi2"] is not None else math.nan,
            pvalue=d["friedman_p"] if d["friedman_p"] is not None else math.nan,
            mean_ranks=[d["mean_ranks"][c] for c in d["columns"]] if d["mean_ranks"] else [],
            nemenyi=[[d["nemenyi_p"][a][b] for b in d["columns"]] for a in d["columns"]] if d["nemenyi_p"] else [],
            cd=d["critical_difference"] if d["critical_difference"] is not None else math.nan,
            alpha=d["alpha"], note=d["note"],
        )
        out.append(stats.friedman_markdown(test, title))
        out.append(stats.nemenyi_markdown(test, title))

    if results.get("gaps"):
        out += gaps_markdown(results["gaps"], trials)

    if plots:
        out += ["## Plots", ""] + [f"- [{p}]({p})" for p in plots] + [""]
    out += ["---", "", f"Data: {citation}", ""]
    return "\n".join(out)


def _ratio(x: float | None) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.2f}×"


def _recovery(d: dict) -> str:
    """An outage's recovery of one trial: seconds, or "not back" within the recording."""
    if d.get("recovered") is None:
        return ""
    if d["recovered"]:
        return f", back in {d['recovery_s']:.1f} s"
    return f", not back in {_fmt(d.get('observed_after_s'), 0)} s"


def gaps_markdown(g: dict, trials: list[str]) -> list[str]:
    """The report's "Sample gaps" section (``--drop-pattern``): lines of Markdown."""
    cols = g["columns"]
    out = [
        f"## Sample gaps (`--drop-pattern`, seed {g['seed']})", "",
        "Each pattern drops rows as docs/gaps.md describes; every estimator column runs on the kept rows, "
        "each with its own time, and its gapped and gap-free runs are both scored on the same rows — the "
        "scored rows the pattern keeps — so the gap-free figures here differ a little from the tables above. "
        "RMSE of the scored error (total where heading is scored, else inclination), degrees; ratio: gapped "
        f"over gap-free. Recovery after an outage: until the gapped estimate stays within "
        f"{gaps.RECOVERY_TOLERANCE_DEG:g}° of the gap-free one."
        + (f" Not run with gaps (peers take a constant rate): {', '.join(g['not_run'])}." if g.get("not_run") else ""),
        "",
        "| column | pattern | dropped | gap-free RMSE | with gaps | ratio (mean) | worst ratio | worst with gaps | worst recovery |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label in g["patterns"]:
        outage = gaps.parse(label).kind == "outage"
        for c in cols:
            m = g["summary"].get(label, {}).get(c)
            if m is None:
                continue
            rec = m.get("worst_recovery_s")
            recovery = "" if not outage else ("not back" if rec is None or not math.isfinite(rec) else f"{rec:.1f} s")
            out.append(
                f"| {c} | {label} | {100 * g['dropped_fraction'][label]:.1f} % | {_fmt(m['mean_gap_free'])} | "
                f"{_fmt(m['mean_gapped'])} | {_ratio(m['mean_ratio'])} | {_ratio(m['worst_ratio'])} | "
                f"{_fmt(m['worst_gapped'])} ({m['worst_trial']}) | {recovery} |"
            )
    out.append("")
    for label in g["patterns"]:
        out += [f"### {label} per trial: gap-free → with gaps (ratio)", "",
                "| trial | " + " | ".join(cols) + " |", "|---|" + "---:|" * len(cols)]
        for t in trials:
            cells = []
            for c in cols:
                d = g["per_trial"][label][c].get(t)
                cells.append("n/a" if d is None else
                             f"{_fmt(d['rmse_gap_free'])} → {_fmt(d['rmse_gapped'])} ({_ratio(d['ratio'])}{_recovery(d)})")
            out.append(f"| {t} | " + " | ".join(cells) + " |")
        out.append("")
    return out


# ------------------------------------------------------------------------------ command


def with_presets(items: list[str], names: list[str], params: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """``--preset`` items under the ``--param`` values: ``paper`` gives every selected estimator
    that declares paper values (``presets.paper_params``; not robust, triad, quest) its source
    paper's values; a preset file gives its own estimator (which must be selected) its params."""
    from ahrs_service.core.paths import regular_file
    from ahrs_service.estimators.presets import PAPER, has_paper_preset, load_preset

    out = {k: dict(v) for k, v in params.items()}
    for item in items:
        if item == PAPER:
            targets = [n for n in names if has_paper_preset(estimators.get(n).Params)]
        else:
            try:
                # regular_file: a FIFO would block read_text() until some process wrote to it
                target = json.loads(regular_file(item).read_text(encoding="utf-8")).get("estimator")
            except (OSError, ValueError, AttributeError):
                target = None
            if target is None:
                raise ValueError(f"--preset {item!r}: not a preset file naming its estimator (or 'paper')")
            if target not in names:
                raise ValueError(f"--preset {item!r} is for {target!r}, which is not among the selected estimators")
            targets = [target]
        for name in targets:
            out[name] = {**load_preset(name, item), **out.get(name, {})}
    return out


def drop_options(args: Any) -> tuple[list[str], int]:
    """``--drop-pattern`` (comma-separated, repeatable, ``standard``) and ``--drop-seed``:
    the patterns' labels and the seed; ValueError naming the option."""
    items = getattr(args, "drop_pattern", None) or []
    seed = getattr(args, "drop_seed", None)
    if not items:
        if seed is not None:
            raise ValueError(f"--drop-seed {seed}: only with --drop-pattern")
        return [], 0
    try:
        labels = [p.label for p in gaps.parse_list(items)]
    except ValueError as exc:
        raise ValueError(f"--drop-pattern: {exc}") from None
    seed = 0 if seed is None else int(seed)
    if seed < 0:
        raise ValueError(f"--drop-seed {seed}: must be 0 or more")
    return labels, seed


def main(args: Any) -> int:
    """Entry of ``ahrs-service evaluate`` (arguments from ``command.add_subcommands``)."""
    dataset = getattr(args, "dataset", "broad") or "broad"
    try:
        drop_patterns, drop_seed = drop_options(args)  # before the data: a typo needs no recordings
        if dataset not in DATASETS:
            raise ValueError(f"--dataset {dataset!r}: choose from {', '.join(DATASETS)}")
        source = DATASETS[dataset]
        data_dir = source.check_dir(args.data if args.data else source.default_dir())
        trial_names = source.list_trials(data_dir, args.trials)
        if not trial_names:
            raise ValueError(f"no trial in {str(data_dir)!r} matches {args.trials!r}")
        est_names, skipped = select_estimators(args.estimators)
        peer_names = peers.select(args.peers)
        params = parse_params(args.param, est_names + peer_names)
        for name in est_names:  # the configuration file's checks and ranges (ConfigError: a ValueError)
            if name in params:
                check_estimator_params(name, params[name], label=f"--param {name}.{{}}")
        params = with_presets(getattr(args, "preset", []) or [], est_names, params)
        columns = make_columns(
            est_names,
            peer_names,
            params,
            with_offline=bool(getattr(args, "offline", False)),
            blend_time_s=getattr(args, "offline_blend", None),
        )
    except (FileNotFoundError, ValueError, ImportError) as exc:
        print(f"ahrs-service evaluate: error: {exc}", file=sys.stderr)
        return 2
    for s in skipped:
        print(f"ahrs-service evaluate: skipping estimator {s}", file=sys.stderr)
    not_gapped = [c.name for c in columns if c.kind != "estimator"]
    if drop_patterns and not_gapped:
        print(f"ahrs-service evaluate: --drop-pattern: peers take a constant rate and are scored without gaps only: "
              f"{', '.join(not_gapped)}", file=sys.stderr)

    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    from ahrs_service.evaluation import plots

    plot_files: list[str] = []

    def on_trial(trial, errors):
        plot_files.append(plots.error_over_time(trial, errors, columns, out_dir, source.CITATION))

    progress = not args.quiet and sys.stderr.isatty()
    # a RunnerError (scheduler out of reach, bad --workers) is cli.main's one line
    with open_runner(getattr(args, "workers", 1), getattr(args, "scheduler", None),
                     task_floor_s=getattr(args, "task_floor_s", None)) as runner:
        results = evaluate(
            data_dir, columns, trial_names, progress=progress, on_trial=on_trial, dataset=dataset, runner=runner,
            drop_patterns=drop_patterns, drop_seed=drop_seed,
        )
    plot_files += plots.group_bars(results, out_dir)
    results["plots"] = plot_files
    if skipped:
        results["skipped"] = skipped
    to_json(results, out_dir / "results.json")
    (out_dir / "results.md").write_text(to_markdown(results, plot_files), encoding="utf-8")
    if not args.quiet:
        print(f"wrote {out_dir / 'results.md'}, {out_dir / 'results.json'} and {len(plot_files)} plot(s)")
    return 0
