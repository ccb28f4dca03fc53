"""Benchmark of fleet replay: ``ahrs-service replay FLEET --out DIR`` over a generated fleet.

    python benchmarks/fleet_replay.py [--count 1000] [--seed 0] [--logs DIR] [--min-s 10]
                                      [--max-s 600] [--long-fraction 1] [--skip-scheduler] [--skip-resume]

Generates (or reuses: the logs are deterministic) a fleet with ``benchmarks/fleet_logs.py``,
then replays it, each run a separate ``ahrs-service replay`` process as a user runs it:

- ``--workers 1`` (in-process, no Dask) and ``--workers 2`` (the embedded LocalCluster);
- ``--scheduler`` on a ``dask scheduler`` and two ``dask worker`` processes started by hand
  (one thread each), as a real cluster is used.

For each: wall time (cluster start included), logs/s, samples/s, the peak RSS of the client
process and of each worker process (their kernels' ``VmHWM``, sampled every 0.2 s while
they run), and whether the table equals the 1-worker run's (the ``output`` column aside). Then
the ratio of the 2-worker throughput to the 1-worker one and a **resume check**: a 2-worker run
killed (SIGKILL) once half the logs are done, re-run: how many logs the re-run replayed,
whether it redid any finished one, and whether the final table equals the uninterrupted run's.

The numba cache is the environment's (``NUMBA_CACHE_DIR``): warm it first (one replay) so the
workers load the kernels rather than compile them.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

import fleet_logs  # noqa: E402

from ahrs_service import fleet  # noqa: E402
from ahrs_service.execution import LOCAL_CLUSTER_CONFIG  # noqa: E402
from tests.dask_cluster import hand_started_cluster  # noqa: E402

BIN = Path(sys.executable).parent


def _hwm_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def _children(pid: int) -> list[int]:
    """Every thread's children: a nanny starts its worker from its event loop's thread."""
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def _tree(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        todo += _children(p)
    return out


def _is_worker(pid: int) -> bool:
    """A Dask worker process: a multiprocessing child (LocalCluster's, or a nanny's), not the
    resource tracker."""
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return False
    return "multiprocessing" in cmd and "resource_tracker" not in cmd


class PeakRss:
    """Samples the peak RSS (VmHWM) of processes and of their worker descendants."""

    def __init__(self, roots: list[int]) -> None:
        self.roots = roots
        self.peak_kib: dict[int, int] = {}
        self.workers: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.2):
            for root in self.roots:
                for pid in _tree(root):
                    kib = _hwm_kib(pid)
                    if kib:
                        self.peak_kib[pid] = max(self.peak_kib.get(pid, 0), kib)
                        if pid != root and pid not in self.workers and _is_worker(pid):
                            self.workers.add(pid)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def mb(self, pid: int) -> float:
        return self.peak_kib.get(pid, 0) / 1024

    def worker_mb(self) -> list[float]:
        return sorted((self.mb(p) for p in self.workers), reverse=True)


@dataclass
class Run:
    name: str
    wall_s: float
    logs: int
    samples: int
    failed: int
    client_mb: float
    worker_mb: list[float] = field(default_factory=list)
    same_as_serial: bool | None = None

    @property
    def logs_per_s(self) -> float:
        return self.logs / self.wall_s

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.wall_s


def _table(out: Path) -> list[dict]:
    with (out / "fleet.csv").open(newline="") as f:
        return [{k: v for k, v in row.items() if k != "output"} for row in csv.DictReader(f)]


def replay_run(name: str, logs: Path, out: Path, extra: list[str], watch: list[int] = ()) -> Run:
    """One ``ahrs-service replay`` process over the fleet into a fresh ``out``."""
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    proc = subprocess.Popen([str(BIN / "ahrs-service"), "replay", str(logs), "--out", str(out), *extra],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    rss = PeakRss([proc.pid, *watch])
    _, err = proc.communicate()
    wall = time.perf_counter() - t0
    rss.stop()
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"{name}: ahrs-service replay exited {proc.returncode}: {err.strip()[-2000:]}")
    rows = _table(out)
    workers = rss.worker_mb()
    return Run(name, wall, len(rows), sum(int(r["samples"] or 0) for r in rows if not r["error"]),
               sum(bool(r["error"]) for r in rows), rss.mb(proc.pid), workers)


def scheduler_run(logs: Path, out: Path, workers: int = 2) -> Run:
    """The replay through ``--scheduler`` on a hand-started scheduler and ``workers`` workers."""
    pids: list[int] = []
    # with the settings docs/fleet.md gives for a cluster of one's own
    with hand_started_cluster(workers, config=LOCAL_CLUSTER_CONFIG, pids=pids) as address:
        return replay_run(f"--scheduler, {workers} dask workers", logs, out, ["--scheduler", address],
                          watch=pids[1:])


def resume_check(logs: Path, out: Path, count: int, reference: list[dict]) -> dict:
    """A 2-worker run SIGKILLed at half the fleet, then re-run: what the re-run did."""
    shutil.rmtree(out, ignore_errors=True)
    journal = out / "fleet.jsonl"
    cmd = [str(BIN / "ahrs-service"), "replay", str(logs), "--out", str(out), "--workers", "2"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.monotonic() + 3600
    while len(fleet.journal_logs(out)) < count // 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    finished = fleet.journal_logs(out)
    stamps = {}
    for line in journal.read_bytes().split(b"\n")[:-1]:
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if entry["output"]:
            stamps[entry["log"]] = os.stat(entry["output"]).st_mtime_ns
    t0 = time.perf_counter()
    rerun = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    wall = time.perf_counter() - t0
    skipped = next((int(line.split()[0]) for line in rerun.stdout.splitlines()
                    if "were skipped" in line), 0)
    with (out / "fleet.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    redone = sum(1 for r in rows if r["log"] in stamps and os.stat(r["output"]).st_mtime_ns != stamps[r["log"]])
    return {"killed": proc.returncode == -signal.SIGKILL, "done_before_kill": len(set(finished)),
            "rerun_replayed": count - skipped, "finished_redone": redone, "rerun_s": wall,
            "table_equal": [{k: v for k, v in r.items() if k != "output"} for r in rows] == reference,
            "exit": rerun.returncode}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=1000, help="logs in the fleet")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--logs", type=Path, default=None, help="fleet folder (default: a temporary one, kept by seed)")
    parser.add_argument("--min-s", type=float, default=10.0)
    parser.add_argument("--max-s", type=float, default=600.0)
    parser.add_argument("--long-fraction", type=float, default=1.0, help="see fleet_logs.py")
    parser.add_argument("--skip-scheduler", action="store_true")
    parser.add_argument("--skip-resume", action="store_true")
    args = parser.parse_args()
    logs = args.logs or Path(tempfile.gettempdir()) / f"ahrs-fleet-seed{args.seed}-{args.min_s:g}-{args.max_s:g}-{args.long_fraction:g}"
    t0 = time.perf_counter()
    plan = fleet_logs.generate(logs, args.count, args.seed, min_s=args.min_s, max_s=args.max_s,
                                 long_fraction=args.long_fraction, processes=2)
    # a folder may hold more logs than asked (an earlier, larger --count): replay exactly these
    fleet_dir = logs / f"first{args.count}"
    fleet_dir.mkdir(exist_ok=True)
    for log in plan:
        link = fleet_dir / log.name
        if not link.exists():
            link.symlink_to(logs / log.name)
    hours = sum(log.seconds for log in plan) / 3600
    print(f"fleet: {len(plan)} logs, {hours:.2f} h of flight, {sum(log.samples for log in plan)} samples, "
          f"{sum(log.fault == 'truncated' for log in plan)} truncated, {sum(log.fault == 'corrupt' for log in plan)} corrupt "
          f"(generated or found in {time.perf_counter() - t0:.0f} s, {logs})")
    work = Path(tempfile.mkdtemp(prefix="ahrs-fleet-replay-"))
    try:
        runs = [replay_run("--workers 1", fleet_dir, work / "w1", ["--workers", "1"])]
        reference = _table(work / "w1")
        runs.append(replay_run("--workers 2", fleet_dir, work / "w2", ["--workers", "2"]))
        if not args.skip_scheduler:
            runs.append(scheduler_run(fleet_dir, work / "sched"))
        for run, out in zip(runs, ("w1", "w2", "sched")):
            run.same_as_serial = _table(work / out) == reference
        print(f"{'run':28s} {'wall s':>8s} {'logs':>6s} {'failed':>6s} {'logs/s':>7s} {'samples/s':>10s} "
              f"{'client MB':>9s} {'worker peak MB':>16s} same")
        for r in runs:
            workers = ", ".join(f"{mb:.0f}" for mb in r.worker_mb) or "-"
            print(f"{r.name:28s} {r.wall_s:8.1f} {r.logs:6d} {r.failed:6d} {r.logs_per_s:7.2f} {r.samples_per_s:10.0f} "
                  f"{r.client_mb:9.0f} {workers:>16s} {r.same_as_serial}")
        print(f"ratio 2 workers / 1: {runs[1].logs_per_s / runs[0].logs_per_s:.2f}"
              + (f"; --scheduler (2 workers) / 1: {runs[2].logs_per_s / runs[0].logs_per_s:.2f}" if len(runs) > 2 else ""))
        if not args.skip_resume:
            check = resume_check(fleet_dir, work / "resume", len(plan), reference)
            print(f"resume: killed={check['killed']} after {check['done_before_kill']}/{len(plan)} logs; the re-run "
                  f"replayed {check['rerun_replayed']} in {check['rerun_s']:.1f} s, redid {check['finished_redone']} "
                  f"finished log(s); table equal to the uninterrupted run's: {check['table_equal']}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
