"""``ahrs-service tune ESTIMATOR``: an Optuna search of an estimator's parameters on BROAD.

Search space: declared beside each ``Params`` field (``presets.tunable(default, paper=...,
search=SearchRange(low, high, log))``) in the estimator's module (see :func:`search_space`), or given
on the command line as ``--space NAME=LOW:HIGH[:log]``. A name the estimator does not have, or a
range whose end the ``Params`` class itself rejects (its ``__post_init__`` bounds), is a
ValueError naming it.

Recordings: ``--dataset broad`` (BROAD's handheld trials), ``dido`` (DIDO's quadrotor flights)
or ``both``. Each recording is scored as ``evaluate`` scores it: BROAD on the total RMSE, or on
the inclination RMSE for an estimator without heading; DIDO (no magnetometer) always on the
inclination RMSE. Objective (:func:`objective`): on one data set its mean score, degrees; on
both, the worse of the two data sets' means each divided by its accuracy target (BROAD 6°
total or 3° inclination, DIDO 5°), so 12 BROAD trials and 8 DIDO flights weigh the same and a
gain is judged by the data set it suits least.

Trials: Optuna's ask-and-tell interface; every (trial × recording) pair is one job of the
execution layer (``report.run_trial_job``, the same scoring as ``evaluate``), and the runner
groups a batch's jobs into tasks of at least its task floor (``--task-floor-s``), a
recording's jobs together. Serially a batch is one trial; on a cluster each batch asks for
enough trials that every worker gets two floors of work by the cost model's first guess
(:func:`trials_per_batch`), so a run is reproducible for its worker count and floor.
Cross-validation reuses the study's per-recording scores: for each recording left out, the trial best on the objective
over the others is scored on it (leave-one-recording-out); the per-data-set means of those
are the validation scores. Parameter importances: Optuna's fANOVA evaluator.

Result: a preset file (JSON: ``estimator``, ``params``, ``command``, scores) that
``estimators.create(name, preset=PATH)`` and ``estimators.run(..., preset=PATH)`` accept.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ahrs_service import estimators
from ahrs_service.estimators.presets import SearchRange
from ahrs_service.estimators.settings import check_estimator_params
from ahrs_service.evaluation import report
from ahrs_service.execution import Runner, progress_bar


def search_space(name: str) -> dict[str, SearchRange]:
    """The search ranges declared on estimator ``name``'s ``Params`` fields (field metadata)."""
    cls = estimators.get(name)
    return {f.name: f.metadata["search"] for f in dataclasses.fields(cls.Params) if "search" in f.metadata}


def parse_space(items: list[str], name: str) -> dict[str, SearchRange]:
    """``NAME=LOW:HIGH[:log]`` items; unknown names and malformed ranges are ValueErrors."""
    out: dict[str, SearchRange] = {}
    for item in items:
        key, sep, spec = item.partition("=")
        parts = spec.split(":")
        if not sep or len(parts) not in (2, 3) or (len(parts) == 3 and parts[2] != "log"):
            raise ValueError(f"--space {item!r}: expected NAME=LOW:HIGH or NAME=LOW:HIGH:log")
        try:
            low, high = float(parts[0]), float(parts[1])
        except ValueError:
            raise ValueError(f"--space {item!r}: LOW and HIGH must be numbers") from None
        out[key.strip()] = SearchRange(low, high, log=len(parts) == 3)
    return out


def check_space(name: str, space: dict[str, SearchRange]) -> None:
    """Every range names a parameter of ``name`` and both its ends are accepted by ``Params``."""
    cls = estimators.get(name)
    known = {f.name for f in dataclasses.fields(cls.Params)}
    if not space:
        raise ValueError(f"estimator {name!r} declares no search space; give --space NAME=LOW:HIGH")
    for key, rng in space.items():
        if key not in known:
            raise ValueError(f"unknown parameter {key!r} in the search space of {name!r}; accepted: {', '.join(sorted(known))}")
        if not (math.isfinite(rng.low) and math.isfinite(rng.high)) or rng.low >= rng.high:
            raise ValueError(f"search range of {name}.{key}: need finite LOW < HIGH, got {rng.low}:{rng.high}")
        if rng.log and rng.low <= 0:
            raise ValueError(f"search range of {name}.{key}: a log scale needs LOW > 0, got {rng.low}")
    # both corners of the box together (bounds that tie fields, such as low < high, hold there
    # for ranges declared so); a failing corner is pinned on the field that fails alone
    for corner in ("low", "high"):
        values = {k: getattr(r, corner) for k, r in space.items()}
        try:
            estimators.create(name, **values)
        except ValueError as exc:
            culprits = [k for k in space if not _accepts(name, k, values[k])] or sorted(space)
            key = culprits[0]
            raise ValueError(
                f"search range of {name}.{key} = {space[key].low}:{space[key].high} is outside its bounds: {exc}"
            ) from None
    for key, rng in space.items():  # then the configuration file's ranges (ConfigError: a ValueError)
        for end in (rng.low, rng.high):
            check_estimator_params(name, {key: end}, label=f"search range of {name}.{{}}")


def _accepts(name: str, key: str, value: float) -> bool:
    try:
        estimators.create(name, **{key: value})
    except ValueError:
        return False
    return True


OBJECTIVE_TEXT = ("one data set: its mean RMSE (deg); several: max over the data sets of mean RMSE / target "
                  "(BROAD 6 deg total or 3 deg inclination, DIDO 5 deg inclination)")

#: ``--dataset`` choices → the data sets tuned on.
DATASET_CHOICES = {"broad": ("broad",), "dido": ("dido",), "both": ("broad", "dido")}


@dataclass(frozen=True)
class Recording:
    """One recording a study scores: its data set (a key of ``report.DATASETS``), folder, name."""

    dataset: str
    data_dir: str
    name: str

    @property
    def label(self) -> str:
        """``dataset/name``: unique across data sets (the keys of the validation table)."""
        return f"{self.dataset}/{self.name}"


def metric_of(dataset: str, scores_heading: bool) -> str:
    """The score row key a recording is judged on: BROAD's total RMSE for an estimator with a
    heading, else (no heading, or DIDO, which has no magnetometer) the inclination RMSE."""
    return "total_rmse" if dataset == "broad" and scores_heading else "inclination_rmse"


#: Accuracy targets (deg) the objective divides each data set's mean score by: BROAD's mean
#: total RMSE (inclination for an estimator without heading), DIDO's mean inclination RMSE.
TARGETS_DEG = {("broad", True): 6.0, ("broad", False): 3.0, ("dido", True): 5.0, ("dido", False): 5.0}


def dataset_means(per: np.ndarray, datasets: list[str]) -> dict[str, float]:
    """Each data set's mean of the per-recording scores (deg)."""
    labels = np.array(datasets)
    return {k: float(np.mean(per[labels == k])) for k in sorted(set(datasets))}


def objective(per: np.ndarray, datasets: list[str], scores_heading: bool = True) -> float:
    """The study's objective from one trial's per-recording scores (deg).

    One data set: its mean score, deg. Several: the worst of them relative to its target,
    max_d(mean_d / target_d) (``TARGETS_DEG``), so a trial is as good as its weaker data set
    (1.0: both exactly on target) and neither data set's recording count weighs in: a gain
    that wins on the flights while losing the handheld trials (or the reverse) is not taken.
    """
    means = dataset_means(per, datasets)
    if len(means) == 1:
        return next(iter(means.values()))
    return max(v / TARGETS_DEG[(d, scores_heading)] for d, v in means.items())


@dataclass
class TuneResult:
    """The study's outcome: best parameters, their training score, cross-validation, importances.

    Scores in degrees; the two ``*_objective`` figures are :func:`objective` (degrees on one
    data set, target ratios on both). ``train`` and ``validation`` are keyed by :attr:`Recording.label`;
    ``metrics`` names the score each data set used; the ``*_by_dataset`` figures are means
    over each data set's recordings.
    """

    estimator: str
    params: dict[str, float]
    train_objective: float
    validation_objective: float
    train: dict[str, float]  # recording → its RMSE at the best trial
    validation: dict[str, float]  # held-out recording → its RMSE at the trial best on the others
    train_by_dataset: dict[str, float]
    validation_by_dataset: dict[str, float]
    importances: dict[str, float]
    trials: int
    recordings: list[str]
    metrics: dict[str, str]

    def preset(self, command: str, **extra: Any) -> dict[str, Any]:
        """The preset file's contents (``extra``: provenance such as date and budget)."""
        return {"estimator": self.estimator, "params": self.params, "command": command, **extra,
                "metrics": self.metrics, "objective": OBJECTIVE_TEXT,
                "train_objective": self.train_objective,
                "validation_objective": self.validation_objective,
                "train_by_dataset": self.train_by_dataset, "validation_by_dataset": self.validation_by_dataset,
                "train": self.train, "validation": self.validation,
                "importances": self.importances, "trials": self.trials, "recordings": self.recordings}


def tune(
    name: str,
    recordings: list[Recording],
    space: dict[str, SearchRange],
    *,
    budget: int,
    runner: Runner,
    seed: int = 0,
    progress: bool = False,
) -> TuneResult:
    """Runs ``budget`` Optuna trials (TPE, seeded) and cross-validates the best per fold."""
    import optuna

    check_space(name, space)
    if len(recordings) < 2:
        raise ValueError("tuning needs at least two recordings (one is held out in the cross-validation)")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed))
    dists = {k: optuna.distributions.FloatDistribution(r.low, r.high, log=r.log) for k, r in space.items()}
    base = report.make_columns([name], [], {})[0]
    datasets = [r.dataset for r in recordings]
    keys = [metric_of(r.dataset, base.scores_heading) for r in recordings]
    recordings = [dataclasses.replace(r, data_dir=str(Path(r.data_dir).resolve())) for r in recordings]
    scores: list[np.ndarray] = []  # per Optuna trial: (recordings,) RMSE, deg
    batch = trials_per_batch(runner, [report.TrialJob(r.data_dir, r.name, base, False, r.dataset) for r in recordings])
    n = len(recordings)
    bar = progress_bar(budget, f"tune {name}", unit="trial") if progress else None
    try:
        while len(scores) < budget:
            asked = [study.ask(dists) for _ in range(min(batch, budget - len(scores)))]
            jobs = [
                report.TrialJob(r.data_dir, r.name, dataclasses.replace(base, params=dict(tr.params)), False, r.dataset)
                for tr in asked for r in recordings
            ]
            results = runner.map(
                report.run_trial_job, jobs, place_by=report.recording_of, prepare=report.prepare_recording,
                cost=report.expected_job_seconds,
            )
            for i, tr in enumerate(asked):
                rows = results[i * n:(i + 1) * n]
                per = np.array([np.nan if row.row[k] is None else row.row[k] for row, k in zip(rows, keys)], float)
                scores.append(per)
                value = objective(per, datasets, base.scores_heading)
                study.tell(tr, value if math.isfinite(value) else float("inf"))
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    table = np.vstack(scores)  # (trials, recordings)

    def best_of(cols: list[int]) -> int:
        sub = [d for j, d in enumerate(datasets) if j in cols]
        values = np.array([objective(row[cols], sub, base.scores_heading) for row in table])
        return int(np.argmin(np.where(np.isfinite(values), values, np.inf)))

    everything = list(range(n))
    best = best_of(everything)
    labels = [r.label for r in recordings]
    # leave one recording out: the trial best on the others, scored on the one left out
    validation = {labels[j]: float(table[best_of([i for i in everything if i != j]), j]) for j in everything}
    train = {labels[j]: float(table[best, j]) for j in everything}

    def by_dataset(values: dict[str, float]) -> dict[str, float]:
        return {d: float(np.mean([values[labels[j]] for j in everything if datasets[j] == d])) for d in sorted(set(datasets))}

    try:
        importances = {k: float(v) for k, v in optuna.importance.get_param_importances(study).items()}
    except (RuntimeError, ValueError):  # too few distinct trials to fit the evaluator
        importances = {}
    params = {k: float(v) for k, v in study.trials[best].params.items()}
    val_by = by_dataset(validation)
    return TuneResult(
        name, params, objective(table[best], datasets, base.scores_heading),
        objective(np.array([validation[x] for x in labels]), datasets, base.scores_heading), train, validation,
        by_dataset(train), val_by, importances, len(scores), labels,
        {d: k.replace("_", " ") for d, k in zip(datasets, keys)},
    )


#: A batch of trials gives each worker this many task floors of work (by the first guess), so
#: its tasks stay above the floor when the jobs run faster than guessed.
_FLOORS_PER_WORKER = 2


def trials_per_batch(runner: Runner, one_trial: list[report.TrialJob]) -> int:
    """How many trials a batch asks Optuna for: 1 when serial; on a cluster, the workers ×
    the trials that make ``_FLOORS_PER_WORKER`` of the runner's task floors, ``one_trial``'s
    jobs (one per recording) costed by ``report.expected_job_seconds`` — the first guess, not
    timings, so the batches, and with them the study, do not depend on the machine's load."""
    if runner.client is None:
        return 1
    workers = max(1, runner.info.workers)
    trial_s = sum(report.expected_job_seconds(job) for job in one_trial)
    if runner.task_floor_s <= 0 or trial_s <= 0:
        return workers
    return workers * max(1, math.ceil(_FLOORS_PER_WORKER * runner.task_floor_s / trial_s))


def _command_line(args: Any) -> str:
    """The command that reproduces this study (recorded in the preset)."""
    parts = ["ahrs-service", "tune", args.estimator, "--dataset", args.dataset, "--budget", str(args.budget),
             "--seed", str(args.seed)]
    if args.trials:
        parts += ["--trials", args.trials]
    for item in args.space:
        parts += ["--space", item]
    return " ".join(parts)


def recordings_of(dataset: str, data: str | None, pattern: str | None) -> list[Recording]:
    """The recordings of ``--dataset`` (``both``: BROAD's then DIDO's). ``data`` overrides the
    folder of a single data set; with ``both`` each comes from its default folder
    (``$AHRS_BROAD_DIR`` / ``$AHRS_DIDO_DIR``, else ../shared/data/…)."""
    if dataset not in DATASET_CHOICES:
        raise ValueError(f"--dataset {dataset!r}: choose from {', '.join(DATASET_CHOICES)}")
    if data and dataset == "both":
        raise ValueError("--data names one data set's folder; with --dataset both set AHRS_BROAD_DIR and AHRS_DIDO_DIR")
    out: list[Recording] = []
    for key in DATASET_CHOICES[dataset]:
        source = report.DATASETS[key]
        folder = source.check_dir(data if data else source.default_dir())
        out += [Recording(key, str(folder), t) for t in source.list_trials(folder, pattern)]
    return out


def main(args: Any) -> int:
    """Entry of ``ahrs-service tune``."""
    import datetime

    from ahrs_service.execution import open_runner

    try:
        recordings = recordings_of(args.dataset, args.data, args.trials)
        space = search_space(args.estimator) if not args.space else {}
        space |= parse_space(args.space, args.estimator)
        check_space(args.estimator, space)
        if args.budget < 1:
            raise ValueError(f"--budget must be at least 1, not {args.budget}")
        # RunnerError (scheduler, --workers, --task-floor-s): cli.main's one line
        runner = open_runner(args.workers, args.scheduler, task_floor_s=getattr(args, "task_floor_s", None))
    except (FileNotFoundError, ValueError) as exc:
        print(f"ahrs-service tune: error: {exc}", file=sys.stderr)
        return 2
    with runner:
        try:
            result = tune(args.estimator, recordings, space, budget=args.budget, runner=runner,
                          seed=args.seed, progress=not args.quiet and sys.stderr.isatty())
        except ValueError as exc:
            print(f"ahrs-service tune: error: {exc}", file=sys.stderr)
            return 2
    command = _command_line(args)
    out = Path(args.out or f"{args.estimator}.preset.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
    preset = result.preset(command, date=date, dataset=args.dataset, budget=args.budget, seed=args.seed)
    out.write_text(json.dumps(preset, indent=2) + "\n", encoding="utf-8")
    if not args.quiet:
        print(f"{args.estimator}: {result.params}  ({result.trials} trials, {len(recordings)} recordings)")
        for d in result.train_by_dataset:
            print(f"  {d} mean {result.metrics[d]}: train {result.train_by_dataset[d]:.3f}°, "
                  f"leave-one-recording-out validation {result.validation_by_dataset[d]:.3f}°")
        if result.importances:
            print("  importances: " + ", ".join(f"{k} {v:.2f}" for k, v in result.importances.items()))
        print(f"  wrote {out}")
    return 0
