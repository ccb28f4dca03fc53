"""Benchmark of the execution layer: ``evaluate`` on BROAD with 1 worker against N, same run.

    python benchmarks/fleet.py [--data DIR] [--workers 2] [--estimators all] [--trials PATTERN]

Prints one row per runner: cluster start-up, task phase wall time, tasks per second, the sum
of the time spent inside the tasks, and the cluster's overhead per task:

    overhead/task = (workers × task-phase wall − Σ in-task time) / tasks

(in-task time: the jobs' and the prepare tasks' that load each recording beside its jobs),
i.e. the worker-seconds the cluster spent on anything but running jobs (scheduling,
serialising, gathering, idle tails), per task. The ratio row is the N-worker throughput over
the 1-worker throughput measured in the same run. A warm-up pass (one task per estimator on
every worker) runs before the timed phase so that numba's cache loading is not counted.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ahrs_service.evaluation import broad, report  # noqa: E402
from ahrs_service.execution import open_runner, worker_cache  # noqa: E402


@dataclass
class Timed:
    result: report.TrialResult
    seconds: float  # wall time inside the task, on the worker


def timed_job(job: report.TrialJob) -> Timed:
    t0 = time.perf_counter()
    res = report.run_trial_job(job)
    return Timed(res, time.perf_counter() - t0)


def timed_prepare(recording: tuple[str, str, str]) -> bool:
    """``report.prepare_recording``, its time kept in the worker's cache (this function runs
    pickled by value, so a global of this script would not last between tasks)."""
    t0 = time.perf_counter()
    report.prepare_recording(recording)
    seconds = time.perf_counter() - t0
    worker_cache(("benchmark prepare s", recording), lambda: seconds)
    return True


def _prepare_seconds(recordings: list[tuple[str, str, str]]) -> float:
    """The time this worker spent in the prepare tasks of ``recordings``."""
    return sum(worker_cache(("benchmark prepare s", r), lambda: 0.0) for r in recordings)


def _warm_up(warm: list[report.TrialJob]) -> None:
    """Loads the first recording and every estimator's kernels in this process."""
    for job in warm:
        report.run_trial_job(job)


def measure(workers: int, jobs: list[report.TrialJob], warm: list[report.TrialJob]) -> dict:
    t0 = time.perf_counter()
    with open_runner(workers=workers) as runner:
        start_s = time.perf_counter() - t0
        if runner.client is not None:  # on every worker, not wherever the scheduler puts them
            runner.client.run(_warm_up, warm)
        else:
            _warm_up(warm)
        t1 = time.perf_counter()
        out = runner.map(timed_job, jobs, place_by=report.recording_of, prepare=timed_prepare)
        wall = time.perf_counter() - t1
        # a prepare task (a recording's load, once per cluster) is work, as the load inside a
        # serial run's first job of the recording is
        recordings = sorted({report.recording_of(job) for job in jobs})
        prepared = sum(runner.client.run(_prepare_seconds, recordings).values()) if runner.client is not None else 0.0
    inside = sum(t.seconds for t in out) + prepared
    return {
        "workers": workers, "start_s": start_s, "wall_s": wall, "tasks_per_s": len(jobs) / wall,
        "inside_s": inside, "overhead_ms": (workers * wall - inside) / len(jobs) * 1e3,
        "overhead_pct": (workers * wall - inside) / inside * 100.0,
        "rows": [t.result.row for t in out],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--estimators", default="all")
    ap.add_argument("--trials", default=None)
    args = ap.parse_args()
    data_dir = str(broad.check_dir(args.data or broad.default_dir()).resolve())
    trials = broad.list_trials(data_dir, args.trials)
    names, _ = report.select_estimators(args.estimators)
    cols = report.make_columns(names, [], {})
    jobs = [report.TrialJob(data_dir, t, c, False) for t in trials for c in cols]
    warm = [report.TrialJob(data_dir, trials[0], c, False) for c in cols]
    one = measure(1, jobs, warm)
    many = measure(args.workers, jobs, warm)
    strip = lambda rows: [{k: v for k, v in r.items() if k != "us_per_sample"} for r in rows]  # noqa: E731
    same = repr(strip(one["rows"])) == repr(strip(many["rows"]))
    print(f"evaluate: {len(trials)} trials x {len(cols)} estimators = {len(jobs)} tasks; results identical: {same}")
    print("| workers | start s | task phase s | tasks/s | in-task s | overhead ms/task | overhead % |")
    print("|---|---|---|---|---|---|---|")
    for r in (one, many):
        print(f"| {r['workers']} | {r['start_s']:.1f} | {r['wall_s']:.1f} | {r['tasks_per_s']:.2f} | "
              f"{r['inside_s']:.1f} | {r['overhead_ms']:.1f} | {r['overhead_pct']:.1f} |")
    print(f"throughput ratio {args.workers} workers / 1: {many['tasks_per_s'] / one['tasks_per_s']:.2f}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
