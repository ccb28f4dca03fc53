"""``ahrs-service tune ESTIMATOR``: an Optuna search of an estimator's parameters on BROAD.

Search space: declared beside each ``Params`` field as ``dataclasses.field(metadata={"search":
SearchRange(low, high, log)})`` in the estimator's module (see :func:`search_space`), or given
on the command line as ``--space NAME=LOW:HIGH[:log]``. A name the estimator does not have, or a
range whose end the ``Params`` class itself rejects (its ``__post_init__`` bounds), is a
ValueError naming it.

Trials: Optuna's ask-and-tell interface; each batch asks as many trials as there are workers,
and every (trial × recording) pair is one task of the execution layer
(``report.run_trial_job``, the same scoring as ``evaluate``). Objective: the mean over the
training recordings of the total RMSE (inclination RMSE for an estimator without heading), in
degrees. Cross-validation reuses the study's per-recording scores: for each recording left out,
the trial best on the others is scored on it (leave-one-recording-out); the mean of those is
the validation score. Parameter importances: Optuna's fANOVA evaluator.

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
from ahrs_service.evaluation import broad, report
from ahrs_service.execution import Runner


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
        for end in (rng.low, rng.high):
            try:
                estimators.create(name, **{key: end})
            except ValueError as exc:
                raise ValueError(f"search range of {name}.{key} = {rng.low}:{rng.high} is outside its bounds: {exc}") from None


@dataclass
class TuneResult:
    """The study's outcome: best parameters, their training score, cross-validation, importances."""

    estimator: str
    params: dict[str, float]
    train_rmse_deg: float
    validation_rmse_deg: float
    validation: dict[str, float]  # held-out recording → its RMSE at the trial best on the others
    importances: dict[str, float]
    trials: int
    recordings: list[str]
    metric: str

    def preset(self, command: str) -> dict[str, Any]:
        return {"estimator": self.estimator, "params": self.params, "command": command,
                "metric": self.metric, "train_rmse_deg": self.train_rmse_deg,
                "validation_rmse_deg": self.validation_rmse_deg, "validation": self.validation,
                "importances": self.importances, "trials": self.trials, "recordings": self.recordings}


def tune(
    name: str,
    data_dir: str,
    trial_names: list[str],
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
    if len(trial_names) < 2:
        raise ValueError("tuning needs at least two recordings (one is held out in the cross-validation)")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize", sampler=optuna.samplers.TPESampler(seed=seed))
    dists = {k: optuna.distributions.FloatDistribution(r.low, r.high, log=r.log) for k, r in space.items()}
    base = report.make_columns([name], [], {})[0]
    kind = "total_rmse" if base.scores_heading else "inclination_rmse"
    data_dir = str(Path(data_dir).resolve())
    scores: list[np.ndarray] = []  # per Optuna trial: (recordings,) RMSE
    batch = max(1, runner.info.workers)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=budget, unit="trial", desc=f"tune {name}", file=sys.stderr, dynamic_ncols=True)
    try:
        while len(scores) < budget:
            asked = [study.ask(dists) for _ in range(min(batch, budget - len(scores)))]
            jobs = [
                report.TrialJob(data_dir, t, dataclasses.replace(base, params=dict(tr.params)), False)
                for tr in asked for t in trial_names
            ]
            results = runner.map(report.run_trial_job, jobs)
            for i, tr in enumerate(asked):
                per = np.array([r.row[kind] for r in results[i * len(trial_names):(i + 1) * len(trial_names)]], float)
                scores.append(per)
                value = float(np.mean(per))
                study.tell(tr, value if math.isfinite(value) else float("inf"))
                if bar is not None:
                    bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    table = np.vstack(scores)  # (trials, recordings)
    means = np.mean(table, axis=1)
    best = int(np.nanargmin(np.where(np.isfinite(means), means, np.inf)))
    validation: dict[str, float] = {}
    for j, held in enumerate(trial_names):
        rest = np.delete(table, j, axis=1).mean(axis=1)
        pick = int(np.argmin(np.where(np.isfinite(rest), rest, np.inf)))
        validation[held] = float(table[pick, j])
    try:
        importances = {k: float(v) for k, v in optuna.importance.get_param_importances(study).items()}
    except (RuntimeError, ValueError):  # too few distinct trials to fit the evaluator
        importances = {}
    params = {k: float(v) for k, v in study.trials[best].params.items()}
    return TuneResult(name, params, float(means[best]), float(np.mean(list(validation.values()))),
                      validation, importances, len(scores), list(trial_names), kind.replace("_", " "))


def _command_line(args: Any) -> str:
    """The command that reproduces this study (recorded in the preset)."""
    parts = ["ahrs-service", "tune", args.estimator, "--dataset", args.dataset, "--budget", str(args.budget),
             "--seed", str(args.seed)]
    if args.trials:
        parts += ["--trials", args.trials]
    for item in args.space:
        parts += ["--space", item]
    return " ".join(parts)


def main(args: Any) -> int:
    """Entry of ``ahrs-service tune``."""
    from ahrs_service.execution import open_runner

    try:
        data_dir = broad.check_dir(args.data if args.data else broad.default_dir())
        trial_names = broad.list_trials(data_dir, args.trials)
        space = search_space(args.estimator) if not args.space else {}
        space |= parse_space(args.space, args.estimator)
        check_space(args.estimator, space)
        if args.budget < 1:
            raise ValueError(f"--budget must be at least 1, not {args.budget}")
        runner = open_runner(args.workers, args.scheduler)  # RunnerError: cli.main's one line
    except (FileNotFoundError, ValueError) as exc:
        print(f"ahrs-service tune: error: {exc}", file=sys.stderr)
        return 2
    with runner:
        try:
            result = tune(args.estimator, str(data_dir), trial_names, space, budget=args.budget, runner=runner,
                          seed=args.seed, progress=not args.quiet and sys.stderr.isatty())
        except ValueError as exc:
            print(f"ahrs-service tune: error: {exc}", file=sys.stderr)
            return 2
    command = _command_line(args)
    out = Path(args.out or f"{args.estimator}.preset.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result.preset(command), indent=2) + "\n", encoding="utf-8")
    if not args.quiet:
        print(f"{args.estimator}: {result.params}  ({result.trials} trials, {len(trial_names)} recordings)")
        print(f"  mean {result.metric}: train {result.train_rmse_deg:.3f}°, "
              f"leave-one-recording-out validation {result.validation_rmse_deg:.3f}°")
        if result.importances:
            print("  importances: " + ", ".join(f"{k} {v:.2f}" for k, v in result.importances.items()))
        print(f"  wrote {out}")
    return 0
