"""One execution layer for the batch commands (``evaluate``, fleet ``replay``, ``tune``): each job
is a Dask task.

``open_runner(workers=N, scheduler=ADDRESS)`` gives a :class:`Runner` whose :meth:`Runner.map`
runs ``fn(job)`` for every job and returns the results **in the jobs' order**, whatever order
they finish in, so a parallel run's results are the serial run's.

- ``workers=1`` and no scheduler: in-process, one job after another, no Dask imported.
- ``workers=N`` (N > 1, default: the machine's cores): an embedded ``distributed.LocalCluster``
  of N worker *processes*, one thread each (the estimators are compiled numba loops holding
  the GIL; threads would not run them in parallel), bound to 127.0.0.1, no dashboard.
- ``scheduler="tcp://HOST:8786"``: a cluster started elsewhere (``dask scheduler`` plus
  ``dask worker tcp://HOST:8786`` on each machine, or dask-jobqueue / dask-kubernetes); see
  docs/fleet.md. An unreachable address fails after ``connect_timeout_s`` with a
  :class:`RunnerError` naming it.

Faults: a task whose worker dies is rescheduled by the scheduler on another worker (Dask's
``allowed-failures``, 3 by default); a task that *raises* is retried ``retries`` times and then
its exception is raised here.

Data locality: a job names its input (a recording's folder and name, a log's path) rather than
carrying it, and the job function loads it on the worker through a per-process cache
(:func:`worker_cache`), so each worker reads each recording at most once and nothing large
crosses the network per task. Kernels: each worker process compiles (or loads from numba's
on-disk cache) an estimator's kernels at its first job and keeps them for the rest of the run.

Requires the ``fleet`` extra (``pip install 'ahrs-service[fleet]'``) for N > 1 or a scheduler.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import signal
import sys
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Callable, Hashable, Iterator, Sequence, TypeVar

J = TypeVar("J")
R = TypeVar("R")

DEFAULT_CONNECT_TIMEOUT_S = 5.0


class RunnerError(RuntimeError):
    """The execution layer could not start or reach its cluster (message names the address)."""


@dataclass(frozen=True)
class RunnerInfo:
    """What a runner runs on, for the reports: ``mode`` is "serial", "local" or "scheduler"."""

    mode: str
    workers: int
    address: str = ""


def default_workers() -> int:
    """One worker process per core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


# entries a worker keeps (a recording takes a few: its data, IMU delay, recovered steps):
# evaluate's jobs come recording by recording, but a tune study cycles over every recording
# of BROAD and DIDO in each trial (20 recordings, ≈ 200 MB), so the whole set must fit
_CACHE_SIZE = 128


def worker_cache(key: Any, load: Callable[[], R]) -> R:
    """``load()`` once per process for ``key``, then the same object: a worker's data cache.

    Lives in this module, so it lasts as long as the worker process (and, in a serial run, as
    long as the command); the least recently used of more than a few entries is dropped. Keys
    must identify the data fully (e.g. folder + name).
    """
    if key in _cache:
        _cache.move_to_end(key)
        return _cache[key]
    value = load()
    _cache[key] = value
    while len(_cache) > _CACHE_SIZE:
        _cache.popitem(last=False)
    return value


_cache: "OrderedDict[Any, Any]" = OrderedDict()


def clear_worker_cache() -> None:
    """Empties this process's :func:`worker_cache` (a benchmark's repeated serial run)."""
    _cache.clear()


def _run_after(fn: Callable[[J], R], job: J, _prepared: Any) -> R:
    """``fn(job)`` as a task that depends on its input's prepare task (placed beside it)."""
    return fn(job)


class Runner:
    """Runs jobs serially or as Dask tasks; results in job order. Use as a context manager."""

    def __init__(self, client: Any = None, cluster: Any = None, info: RunnerInfo | None = None, retries: int = 1) -> None:
        self._client = client
        self._cluster = cluster
        self.info = info or RunnerInfo("serial", 1)
        self.retries = retries
        self._prepare_futures: dict[Hashable, Any] = {}

    # ---------------------------------------------------------------- running
    def map(
        self,
        fn: Callable[[J], R],
        jobs: Sequence[J],
        *,
        progress: bool = False,
        desc: str = "",
        place_by: Callable[[J], Hashable] | None = None,
        prepare: Callable[[Any], Any] | None = None,
    ) -> list[R]:
        """``[fn(job) for job in jobs]``, each job a task when on a cluster; same order as ``jobs``.

        Data locality (``place_by`` and ``prepare``, both or neither): jobs with the same
        ``place_by(job)`` key read the same input (a recording, a log). On a cluster, one
        ``prepare(key)`` task per key runs first and loads that input into its worker's
        :func:`worker_cache`; the key's jobs depend on it, so the scheduler places them on the
        worker that holds the input, and each input is read about once in the whole run
        instead of once per worker (Dask's work stealing still moves jobs to an idle worker,
        which then loads the input itself: ``fn`` must not rely on ``prepare`` having run in
        its process). The prepare tasks stay in the cluster for the runner's lifetime, so the
        next ``map`` over the same inputs (a tuning study's next batch) lands where they are.
        Serially, ``prepare`` is not called: the first job of a key loads it.
        """
        if (place_by is None) != (prepare is None):
            raise ValueError("place_by and prepare go together")
        jobs = list(jobs)
        bar = progress_bar(len(jobs), desc) if progress and jobs else None
        try:
            if self._client is None:
                out = []
                for job in jobs:
                    out.append(fn(job))
                    if bar is not None:
                        bar.update(1)
                return out
            from distributed import as_completed

            if place_by is None:
                # pure=False: two equal jobs are still two runs (the timings differ)
                futures = self._client.map(fn, jobs, pure=False, retries=self.retries)
            else:
                ready = [self._prepared(place_by(job), prepare) for job in jobs]
                futures = self._client.map(
                    functools.partial(_run_after, fn), jobs, ready, pure=False, retries=self.retries
                )
            if bar is not None:
                for _ in as_completed(futures):
                    bar.update(1)
            return self._client.gather(futures)
        finally:
            if bar is not None:
                bar.close()

    def _prepared(self, key: Hashable, prepare: Callable[[Any], Any]) -> Any:
        """The future of ``prepare(key)`` on the cluster, submitted once per key and runner."""
        future = self._prepare_futures.get(key)
        if future is None:
            future = self._client.submit(prepare, key, pure=False, retries=self.retries)
            self._prepare_futures[key] = future
        return future

    def scatter(self, value: Any) -> Any:
        """``value`` sent once to the workers (a future to pass inside jobs); itself when serial."""
        if self._client is None:
            return value
        return self._client.scatter(value, broadcast=True)

    @property
    def client(self) -> Any:
        """The ``distributed.Client`` (None when serial)."""
        return self._client

    # ---------------------------------------------------------------- lifetime
    def close(self) -> None:
        self._prepare_futures.clear()
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None

    def __enter__(self) -> "Runner":
        return self

    def __exit__(self, exc_type: type[BaseException] | None, *exc: object) -> None:
        if exc_type is not None and issubclass(exc_type, KeyboardInterrupt) and self._client is not None:
            _quiet_interrupted_cluster()
        self.close()


def open_runner(
    workers: int | None = None,
    scheduler: str | None = None,
    *,
    connect_timeout_s: float = DEFAULT_CONNECT_TIMEOUT_S,
    retries: int = 1,
) -> Runner:
    """A :class:`Runner`: serial for ``workers == 1``, else a LocalCluster, or the given scheduler.

    ``workers=None`` means :func:`default_workers`. Raises :class:`RunnerError` (one line, names
    the address) when the scheduler cannot be reached within ``connect_timeout_s`` seconds.
    """
    # a missing ``distributed`` propagates as ModuleNotFoundError: the command line turns it into
    # the one line naming the extra (cli.OPTIONAL_MODULES: distributed -> fleet), as for every extra
    if scheduler:
        from distributed import Client

        try:
            client = Client(scheduler, timeout=f"{connect_timeout_s}s", set_as_default=False)
        except (OSError, TimeoutError) as exc:
            raise RunnerError(f"cannot reach the Dask scheduler at {scheduler} within {connect_timeout_s:g} s") from exc
        except ValueError as exc:  # e.g. an address with an unknown protocol
            raise RunnerError(f"bad Dask scheduler address {scheduler!r}: {exc}") from exc
        n = len(client.scheduler_info().get("workers", {}))
        return Runner(client, None, RunnerInfo("scheduler", n, scheduler), retries)
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise RunnerError(f"--workers must be at least 1, not {n}")
    if n == 1:
        return Runner(info=RunnerInfo("serial", 1), retries=retries)
    from distributed import Client, LocalCluster

    with _workers_ignore_ctrl_c():
        cluster = _local_cluster(LocalCluster, n)
    client = Client(cluster, set_as_default=False)
    return Runner(client, cluster, RunnerInfo("local", n, cluster.scheduler_address), retries)


#: Dask settings of the embedded LocalCluster (docs/fleet.md, "The embedded cluster's
#: settings"): Dask's defaults spend several times more of the scheduler's and each worker's
#: CPU beside the tasks than these (figures: benchmarks/README.md, "Dask's own cost on 2
#: cores") — on 2 cores, CPU the cluster spends on itself is taken from the jobs.
LOCAL_CLUSTER_CONFIG: dict[str, Any] = {
    # Dask's nannies set MALLOC_TRIM_THRESHOLD_, which freezes glibc's mmap threshold: every
    # array of a recording's size became a fresh mmap and the jobs ran 2x slower
    "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
    # the statistical profiler samples every worker's stacks every 10 ms for the dashboard's
    # profile page; this cluster has no dashboard (half the workers' own CPU)
    "distributed.worker.profile.enabled": False,
    # each process's event-loop health tick (20 ms): a blocked loop is still reported, once
    # a second instead of fifty times (half the scheduler process's own CPU)
    "distributed.admin.tick.interval": "1s",
    # memory and system monitors (100 ms / 500 ms): a worker over its memory limit is still
    # paused, spilled or restarted, within a second
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.admin.system-monitor.interval": "2s",
}


def _local_cluster(LocalCluster: Any, n: int) -> Any:
    import dask

    with dask.config.set(LOCAL_CLUSTER_CONFIG):
        return LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            # no dashboard; what still listens (scheduler, workers, their small HTTP servers for
            # /health and /metrics) binds to 127.0.0.1 only (``host``)
            dashboard_address=None,
            # the workers' own log lines: a task's failure reaches the command as the task's
            # exception (retried first), a worker's death as the retry; at ERROR a worker also
            # printed its lost heartbeats with tracebacks when the scheduler went first (Ctrl-C)
            silence_logs=logging.CRITICAL,
        )


@contextlib.contextmanager
def _workers_ignore_ctrl_c() -> Iterator[None]:
    """Worker processes started inside keep SIGINT ignored (Python leaves a SIGINT that its
    parent ignored alone): Ctrl-C reaches the whole foreground process group, and the
    command, not each worker, answers it — its runner closes the cluster, which stops the
    workers (before, each worker printed a KeyboardInterrupt traceback)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _quiet_interrupted_cluster() -> None:
    """Ctrl-C or SIGTERM during a run on a cluster: the command ends with its own one line
    (cli.main), so the shutdown's expected noise is not shown: the client's pending gather
    ends in ``AllExit`` (asyncio: "Task exception was never retrieved" and a traceback) and
    the closing scheduler's comms raise in its threads."""
    for name in ("asyncio", "distributed", "tornado"):
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def progress_bar(total: int, desc: str, unit: str = "task"):
    """A tqdm bar on stderr (``update``, ``close``), or None without tqdm."""
    try:
        from tqdm import tqdm
    except ImportError:  # the bar is a nicety: no analysis extra, no bar
        return None
    return tqdm(total=total, unit=unit, desc=desc or None, file=sys.stderr, dynamic_ncols=True)


def add_arguments(parser: Any) -> None:
    """The ``--workers`` / ``--scheduler`` options every batch command shares."""
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        metavar="N",
        help="worker processes of the embedded Dask cluster (default: one per core; 1 = in-process, no cluster)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run on an existing Dask cluster instead, e.g. tcp://HOST:8786 (see docs/fleet.md)",
    )

