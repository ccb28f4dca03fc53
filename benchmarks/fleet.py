"""Benchmark of the execution layer: ``evaluate`` on BROAD with 1 worker against N, same run.

    python benchmarks/fleet.py [--data DIR] [--workers 2] [--estimators all] [--trials PATTERN]
                               [--repeat K] [--floor] [--scheduler] [--task-floor-s 0.5]

Prints one row per runner: the task granularity (``--task-floor-s``: jobs are grouped into
tasks expected to take at least this long, docs/fleet.md "Task granularity"; 0 = one task per
job), the number of tasks it made, cluster start-up, task phase wall time, jobs per second
(the throughput), the sum of the time spent inside the jobs, the cluster's overhead per task:

    overhead/task = (workers × task-phase wall − Σ in-task time) / tasks

and the peak resident memory (VmHWM) of the client process and of the largest worker, MB.

(in-task time: the jobs' and the prepare tasks' that load each recording beside its jobs),
i.e. the worker-seconds the cluster spent on anything but running jobs (scheduling,
serialising, gathering, idle tails), per task. The ratio row is the N-worker throughput over
the 1-worker throughput measured in the same run. A warm-up pass (one task per estimator on
every worker) runs before the timed phase so that numba's cache loading is not counted.
``--repeat K`` runs the pair K times and prints each ratio and the median.

``--scheduler`` adds a row per repeat through ``--scheduler`` on a ``dask scheduler`` and N
``dask worker`` processes started by hand (``tests/dask_cluster.py``, with the settings
docs/fleet.md gives for a cluster of one's own: ``execution.LOCAL_CLUSTER_CONFIG`` in a Dask
configuration file). The cluster lives through the repeats; its first run ("cold") has no
warm-up, so each worker loads its kernels from numba's on-disk cache inside the timed phase,
and its ratio is against the serial run with the serial warm-up counted too.

``--floor`` adds Dask's own floor on this machine: the same number of tasks, each burning the
CPU time its job took in the serial run (a busy loop on the thread's CPU clock, no data, no
project code), placed the same way (one prepare task per recording, burning that recording's
load time), on the same cluster: what the cluster costs tasks of these durations by itself.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ahrs_service.evaluation import broad, report  # noqa: E402
from ahrs_service.execution import (  # noqa: E402
    DEFAULT_TASK_FLOOR_S,
    LOCAL_CLUSTER_CONFIG,
    clear_worker_cache,
    open_runner,
    worker_cache,
)
from tests.dask_cluster import hand_started_cluster  # noqa: E402


@dataclass
class Timed:
    result: report.TrialResult | None  # None: a floor task (no job)
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


def peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM), MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def burn(seconds: float) -> float:
    """A synthetic job: ``seconds`` of this thread's CPU time, nothing else."""
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        pass
    return seconds


def floor(workers: int, one: dict, jobs: list[report.TrialJob], task_floor_s: float) -> dict:
    """The serial run's jobs replaced by CPU burns of their own durations (see the module doc).

    The serial run loaded each recording inside its first job: that job's excess over the
    recording's median job is burnt by the recording's prepare task instead, as the real run
    loads it there."""
    by_recording: dict[tuple, list[float]] = {}
    for job, seconds in zip(jobs, one["job_seconds"]):
        by_recording.setdefault(report.recording_of(job), []).append(seconds)
    median = {r: sorted(v)[len(v) // 2] for r, v in by_recording.items()}
    load = {r: max(0.0, v[0] - median[r]) for r, v in by_recording.items()}
    burns, first = [], set()
    for job, seconds in zip(jobs, one["job_seconds"]):
        r = report.recording_of(job)
        burns.append((r, median[r] if r not in first else seconds))
        first.add(r)
    with open_runner(workers=workers, task_floor_s=task_floor_s) as runner:
        runner.client.run(burn, 0.01)
        t1 = time.perf_counter()
        out = runner.map(_timed_burn, burns, place_by=_recording_of_burn,
                         prepare=functools.partial(_burn_load, load), cost=_burn_seconds)
        wall = time.perf_counter() - t1
        tasks = runner.tasks_submitted
    inside = sum(t.seconds for t in out) + sum(load.values())
    return {"workers": workers, "tasks": tasks, "wall_s": wall, "jobs_per_s": len(jobs) / wall, "inside_s": inside,
            "serial_s": sum(s for _, s in burns) + sum(load.values()),
            "overhead_ms": (workers * wall - inside) / tasks * 1e3,
            "overhead_pct": (workers * wall - inside) / inside * 100.0}


def _burn_seconds(burn_job: tuple) -> float:
    return burn_job[1]


def _recording_of_burn(burn_job: tuple) -> tuple:
    return burn_job[0]


def _burn_load(load: dict, recording: tuple) -> bool:
    burn(load[recording])
    return True


def _timed_burn(burn_job: tuple[tuple, float]) -> Timed:
    """A floor task: (recording, seconds) burnt, timed as :func:`timed_job` times a job."""
    t0 = time.perf_counter()
    burn(burn_job[1])
    return Timed(None, time.perf_counter() - t0)


def _warm_up(warm: list[report.TrialJob]) -> None:
    """Loads the first recording and every estimator's kernels in this process."""
    for job in warm:
        report.run_trial_job(job)


def measure(workers: int, jobs: list[report.TrialJob], warm: list[report.TrialJob], task_floor_s: float,
            scheduler: str | None = None, warm_up: bool = True) -> dict:
    """One run of the jobs: serially (``workers`` 1), on an embedded cluster of ``workers``, or
    through ``scheduler`` (a cluster started by hand). ``warm_up`` False: no warm-up pass, so
    each worker's first job of an estimator loads its kernels inside the timed phase."""
    clear_worker_cache()  # a repeated serial run loads its recordings again, as the first did
    t0 = time.perf_counter()
    with open_runner(workers=workers, scheduler=scheduler, task_floor_s=task_floor_s) as runner:
        start_s = time.perf_counter() - t0
        if runner.client is not None:
            runner.client.run(clear_worker_cache)  # a hand-started cluster outlives the run
        t_warm = time.perf_counter()
        # without it the kernels (and the first recording) load inside the timed phase
        if warm_up and runner.client is not None:  # on every worker, not wherever the scheduler puts them
            runner.client.run(_warm_up, warm)
        elif warm_up:
            _warm_up(warm)
        warm_s = time.perf_counter() - t_warm
        t1 = time.perf_counter()
        out = runner.map(timed_job, jobs, place_by=report.recording_of, prepare=timed_prepare,
                         cost=report.expected_job_seconds)
        wall = time.perf_counter() - t1
        # serially every job is a call in this process: counted as a task of no overhead
        tasks = runner.tasks_submitted if runner.client is not None else len(jobs)
        # a prepare task (a recording's load, once per cluster) is work, as the load inside a
        # serial run's first job of the recording is
        recordings = sorted({report.recording_of(job) for job in jobs})
        prepared = sum(runner.client.run(_prepare_seconds, recordings).values()) if runner.client is not None else 0.0
        worker_rss = max(runner.client.run(peak_rss_mb).values()) if runner.client is not None else float("nan")
        workers = runner.info.workers
    inside = sum(t.seconds for t in out) + prepared
    return {
        "workers": workers, "tasks": tasks, "start_s": start_s, "warm_s": warm_s, "wall_s": wall,
        "jobs_per_s": len(jobs) / wall, "client_rss_mb": peak_rss_mb(), "worker_rss_mb": worker_rss,
        "inside_s": inside, "overhead_ms": (workers * wall - inside) / tasks * 1e3,
        "overhead_pct": (workers * wall - inside) / inside * 100.0,
        "rows": [t.result.row for t in out], "job_seconds": [t.seconds for t in out],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--estimators", default="all")
    ap.add_argument("--trials", default=None)
    ap.add_argument("--repeat", type=int, default=1, help="pairs of runs (default 1); prints the median ratio")
    ap.add_argument("--floor", action="store_true", help="also run the synthetic CPU-burn tasks (Dask's floor)")
    ap.add_argument("--scheduler", action="store_true",
                    help="also run through --scheduler on a hand-started dask scheduler + N dask workers")
    ap.add_argument("--task-floor-s", type=float, default=DEFAULT_TASK_FLOOR_S,
                    help=f"task granularity: least expected seconds of a task (default {DEFAULT_TASK_FLOOR_S:g}; 0: one per job)")
    args = ap.parse_args()
    data_dir = str(broad.check_dir(args.data or broad.default_dir()).resolve())
    trials = broad.list_trials(data_dir, args.trials)
    names, _ = report.select_estimators(args.estimators)
    cols = report.make_columns(names, [], {})
    jobs = [report.TrialJob(data_dir, t, c, False) for t in trials for c in cols]
    warm = [report.TrialJob(data_dir, trials[0], c, False) for c in cols]
    strip = lambda rows: [{k: v for k, v in r.items() if k != "us_per_sample"} for r in rows]  # noqa: E731
    print(f"evaluate: {len(trials)} trials x {len(cols)} estimators = {len(jobs)} jobs; "
          f"task floor {args.task_floor_s:g} s")
    print("| run | workers | floor s | tasks | start s | task phase s | jobs/s | in-task s | overhead ms/task | "
          "overhead % | client RSS MB | worker RSS MB | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ratios, overheads, floor_ratios, floor_overheads, all_same = [], [], [], [], True
    remote_ratios: list[float] = []
    with contextlib.ExitStack() as stack:
        # the hand-started cluster lives through the repeats, as a real one does: its first
        # run loads the kernels from numba's on-disk cache inside the timed phase ("cold")
        address = (stack.enter_context(hand_started_cluster(args.workers, config=LOCAL_CLUSTER_CONFIG))
                   if args.scheduler else None)
        for k in range(1, args.repeat + 1):
            one = measure(1, jobs, warm, args.task_floor_s)
            many = measure(args.workers, jobs, warm, args.task_floor_s)
            all_same &= repr(strip(one["rows"])) == repr(strip(many["rows"]))
            ratio = many["jobs_per_s"] / one["jobs_per_s"]
            ratios.append(ratio)
            overheads.append(many["overhead_pct"])
            rows = [(f"{k}", one, ""), (f"{k}", many, f"{ratio:.2f}")]
            if address is not None:
                cold = k == 1
                remote = measure(args.workers, jobs, warm, args.task_floor_s, scheduler=address, warm_up=not cold)
                all_same &= repr(strip(one["rows"])) == repr(strip(remote["rows"]))
                # cold: against the serial run with its own kernel loading (the warm-up) counted
                serial_s = one["wall_s"] + (one["warm_s"] if cold else 0.0)
                remote_ratios.append(serial_s / remote["wall_s"])
                rows.append((f"{k} scheduler{' cold' if cold else ''}", remote, f"{remote_ratios[-1]:.2f}"))
            for label, r, shown in rows:
                print(f"| {label} | {r['workers']} | {args.task_floor_s:g} | {r['tasks']} | {r['start_s']:.1f} | "
                      f"{r['wall_s']:.1f} | {r['jobs_per_s']:.2f} | {r['inside_s']:.1f} | {r['overhead_ms']:.1f} | "
                      f"{r['overhead_pct']:.1f} | {r['client_rss_mb']:.0f} | {r['worker_rss_mb']:.0f} | {shown} |",
                      flush=True)
            if args.floor:
                f = floor(args.workers, one, jobs, args.task_floor_s)
                floor_ratios.append(f["serial_s"] / f["wall_s"])
                floor_overheads.append(f["overhead_pct"])
                print(f"| {k} floor | {f['workers']} | {args.task_floor_s:g} | {f['tasks']} | | {f['wall_s']:.1f} | "
                      f"{f['jobs_per_s']:.2f} | {f['inside_s']:.1f} | {f['overhead_ms']:.1f} | {f['overhead_pct']:.1f} | | | "
                      f"{floor_ratios[-1]:.2f} |", flush=True)
    med = lambda v: sorted(v)[len(v) // 2]  # noqa: E731
    print(f"results identical to the serial run: {all_same}")
    print(f"throughput ratio {args.workers} workers / 1 (target >= 1.7): median {med(ratios):.2f} of "
          f"{', '.join(f'{r:.2f}' for r in ratios)}; overhead (target <= 5 %): median {med(overheads):.1f} %")
    if remote_ratios:
        print(f"through --scheduler ({args.workers} hand-started dask workers) / serial (target >= 1.7): "
              f"{', '.join(f'{r:.2f}' for r in remote_ratios)} (the first cold: kernels loaded in the timed phase, "
              f"against the serial run with its warm-up)")
    if args.floor:
        print(f"Dask's floor (CPU burns of the same durations, same placement): ratio median "
              f"{med(floor_ratios):.2f}, overhead median {med(floor_overheads):.1f} %")
    return 0 if all_same else 1


if __name__ == "__main__":
    sys.exit(main())
