"""One execution layer for the batch commands (``evaluate``, fleet ``replay``, ``tune``): jobs run
as Dask tasks, grouped so that each task is worth scheduling (``task_floor_s``, below).

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

Task granularity: Dask spends a few milliseconds of CPU on every task (scheduler, client and
worker event loops), as much as a 20-40 ms job's tenth. :meth:`Runner.map` therefore groups
jobs into tasks expected to take at least ``task_floor_s`` seconds each (default
:data:`DEFAULT_TASK_FLOOR_S`, ``--task-floor-s``), a recording's jobs together where possible,
from a cost model: the caller's first guess per job (``cost=``, seconds), scaled by what the
runner's finished tasks of the same job function took. See :func:`plan_tasks` and docs/fleet.md,
"Task granularity".

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
import logging
import math
import os
import signal
import statistics
import sys
import threading
import time
from collections import Counter, OrderedDict, deque
from dataclasses import dataclass
from typing import Any, Callable, Hashable, Iterable, Iterator, Sequence, TypeVar

J = TypeVar("J")
R = TypeVar("R")

DEFAULT_CONNECT_TIMEOUT_S = 5.0

#: Tasks shorter than this (seconds, expected) are grouped: Dask's 3-4 ms of CPU per task on
#: 2 cores stays under 1 % of a task's time (docs/fleet.md, "Task granularity").
DEFAULT_TASK_FLOOR_S = 0.5


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


def check_task_floor(seconds: float, label: str = "--task-floor-s") -> float:
    """``seconds`` as a float when it is a finite number >= 0; else :class:`RunnerError` naming ``label``."""
    try:
        value = float(seconds)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise RunnerError(f"{label} must be a number of seconds >= 0, not {seconds!r}")
    return value


#: Tasks a plan aims at per worker: enough that the workers, each taking the next task as it
#: finishes one, end within about one small task of each other (largest tasks first)
TASKS_PER_WORKER = 8
#: A task's share of the work is at most this many floors (a large workload still reports
#: progress and loses little to a worker's death)
SHARE_CAP_FLOORS = 4


def plan_tasks(
    expected_s: Sequence[float | None],
    keys: Sequence[Hashable] | None = None,
    *,
    floor_s: float = DEFAULT_TASK_FLOOR_S,
    workers: int = 1,
) -> list[list[int]]:
    """The jobs' indices grouped into tasks, each expected to take ``floor_s`` seconds or more.

    ``expected_s``: each job's expected duration (seconds; None where unknown). ``keys``: each
    job's input (``place_by``): a key's jobs are kept together, keys in their first
    appearance's order, so a task reads one input or a few neighbours. The least a task may
    hold is the floor, or more when the total gives more than :data:`TASKS_PER_WORKER` tasks
    per worker (at most :data:`SHARE_CAP_FLOORS` floors). An input's jobs are one piece
    unless they exceed two of those and 1.25 times a worker's share of the total (only then
    is it read by more than one task: each of its jobs is a piece). The total is cut between
    pieces into equal shares (a piece goes where its middle falls): as many as fit with
    every share at or above the least, a multiple of ``workers`` (the last round keeps every
    worker busy). Every job is its own task when
    ``floor_s`` is 0 or a duration is unknown (nothing to size the tasks by yet); everything
    is one task when the total is under the floor. Tasks come in the jobs' order.
    """
    n = len(expected_s)
    order = list(range(n))
    if keys is not None:
        rank: dict[Hashable, int] = {}
        for key in keys:
            rank.setdefault(key, len(rank))
        order.sort(key=lambda i: rank[keys[i]])
    if n == 0 or floor_s <= 0 or any(e is None or not math.isfinite(e) for e in expected_s):
        return [[i] for i in order]
    costs = [max(0.0, float(e)) for e in expected_s]
    total = sum(costs)
    least = max(floor_s, min(total / (TASKS_PER_WORKER * max(1, workers)), SHARE_CAP_FLOORS * floor_s))
    # the pieces the shares are cut between: an input's jobs together (read once) unless
    # they are more than two tasks' and a worker's worth, with a quarter's slack (nearly equal
    # inputs stay whole): then the input is cut between its jobs
    whole = max(2 * least, 1.25 * total / max(1, workers)) * (1 + 1e-9)
    units: list[list[int]] = []
    for block in _blocks(order, keys):
        units += [block] if sum(costs[i] for i in block) <= whole else [[i] for i in block]
    unit_costs = [sum(costs[i] for i in unit) for unit in units]
    # as many shares as the total allows, a multiple of the workers (the last round keeps
    # every worker busy), fewer while a share would fall under the least
    for count in range(max(1, min(len(units), int(total / least + 1e-9))), 0, -1):
        if count >= workers and count % workers:
            continue
        tasks = _shares(units, unit_costs, count)
        if count == 1 or min(sum(costs[i] for i in task) for task in tasks) >= least - 1e-9:
            break
    return tasks


def _shares(units: list[list[int]], unit_costs: list[float], count: int) -> list[list[int]]:
    """The pieces in ``count`` shares of their total: a piece goes to the share its middle
    falls in, so the shares cut the total evenly (empty shares dropped)."""
    width = sum(unit_costs) / count
    slots: list[list[int]] = [[] for _ in range(count)]
    done = 0.0
    for unit, unit_cost in zip(units, unit_costs):
        slot = min(count - 1, int((done + unit_cost / 2) / width)) if width > 0 else 0
        slots[slot] += unit
        done += unit_cost
    return [slot for slot in slots if slot]


def _blocks(order: list[int], keys: Sequence[Hashable] | None) -> list[list[int]]:
    """``order`` cut where the input changes (every job alone without ``keys``)."""
    if keys is None:
        return [[i] for i in order]
    out: list[list[int]] = []
    for i in order:
        if out and keys[out[-1][-1]] == keys[i]:
            out[-1].append(i)
        else:
            out.append([i])
    return out


def _run_batch(pickled_fn: bytes, jobs: list[J], *_prepared: Any) -> tuple[str, list[tuple[Any, float]]]:
    """The job function over ``jobs`` as one task (after the prepare tasks it is given, so
    placed beside them): the worker's address, and each result with its wall time in seconds,
    which sizes the runner's next tasks.

    The function travels cloudpickled: as an argument of the task, Dask would pickle it by
    reference, and a function a script or a test registers to be pickled by value would not
    load in a scheduler or worker started elsewhere."""
    import cloudpickle
    from distributed import get_worker

    fn = cloudpickle.loads(pickled_fn)
    out = []
    for job in jobs:
        t0 = time.perf_counter()
        out.append((fn(job), time.perf_counter() - t0))
    return get_worker().address, out


def _learning_key(fn: Callable[..., Any], guesses: list[float] | None) -> tuple[Any, bool]:
    """What a runner's measured durations are kept under: the job function (itself, or its
    identity when it cannot be hashed) and whether its jobs came with a guess."""
    try:
        hash(fn)
    except TypeError:
        return (id(fn), guesses is not None)
    return (fn, guesses is not None)


#: Measured durations a runner keeps per job function to scale its cost guesses (the median
#: of the newest ones: a worker's first job, which loads data and kernels, is an outlier).
_LEARNED_JOBS = 1024


class Runner:
    """Runs jobs serially or as Dask tasks; results in job order. Use as a context manager."""

    def __init__(
        self,
        client: Any = None,
        cluster: Any = None,
        info: RunnerInfo | None = None,
        retries: int = 1,
        task_floor_s: float = DEFAULT_TASK_FLOOR_S,
    ) -> None:
        self._client = client
        self._cluster = cluster
        self.info = info or RunnerInfo("serial", 1)
        self.retries = retries
        #: the least expected duration of a task of :meth:`map`, seconds
        self.task_floor_s = check_task_floor(task_floor_s)
        #: job tasks :meth:`map` has submitted (prepare tasks not counted)
        self.tasks_submitted = 0
        self._prepare_futures: dict[Hashable, Any] = {}
        # input key -> the address of the worker whose task last loaded it (a placement hint)
        self._loaded_at: dict[Hashable, str] = {}
        # measured/guessed duration ratios (jobs with a guess) or durations in seconds (without)
        self._learned: dict[tuple[Any, bool], deque[float]] = {}  # see _learning_key

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
        cost: Callable[[J], float] | None = None,
        task_floor_s: float | None = None,
    ) -> list[R]:
        """``[fn(job) for job in jobs]``, as Dask tasks of several jobs when on a cluster; same order as ``jobs``.

        Task granularity (on a cluster): the jobs are grouped into tasks expected to take at
        least ``task_floor_s`` seconds each (default: the runner's :attr:`task_floor_s`; 0: one
        task per job), by :func:`plan_tasks`. A job's expected duration is ``cost(job)``
        (seconds, the caller's cheap first guess, e.g. samples × the estimator's µs/sample)
        times the median ratio of measured to guessed duration over the jobs of ``fn`` this
        runner has finished; without ``cost``, the median measured duration of ``fn``'s jobs,
        and one task per job while nothing of ``fn`` has been measured yet. A task that raises
        is retried as a whole; a task whose worker died is rerun elsewhere.

        Data locality (``place_by`` and ``prepare``, both or neither): jobs with the same
        ``place_by(job)`` key read the same input (a recording, a log), and a task holds one
        key's jobs, or a few neighbouring keys', so that each input is read about once in the
        whole run instead of once per worker. A task that holds all of a key's jobs loads the
        input itself in its first job, as a serial run does; the tasks are submitted largest
        first, each to whichever worker is free, or, in a later ``map`` over the same inputs (a
        tuning study's next batch), to the worker that loaded its input last. A key cut over
        several tasks (a large one, :func:`plan_tasks`) gets one ``prepare(key)`` task
        that loads the input into its worker's :func:`worker_cache`, and those tasks depend on
        it, so the scheduler places them beside it; it stays in the cluster for the runner's
        lifetime. Dask's work stealing may still move a task to an idle worker, which then
        loads the input itself: ``fn`` must not rely on ``prepare`` having run in its process.
        Serially, ``prepare`` is not called: the first job of a key loads it.
        """
        if (place_by is None) != (prepare is None):
            raise ValueError("place_by and prepare go together")
        floor_s = self.task_floor_s if task_floor_s is None else check_task_floor(task_floor_s, "task_floor_s")
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
            import cloudpickle
            from distributed import as_completed

            pickled_fn = cloudpickle.dumps(fn)
            guesses = [float(cost(job)) for job in jobs] if cost is not None else None
            keys = [place_by(job) for job in jobs] if place_by is not None else None
            expected = self._expected_seconds(fn, guesses, len(jobs))
            tasks = plan_tasks(expected, keys, floor_s=floor_s, workers=self._worker_count())
            if all(e is not None for e in expected):  # largest first: the last to finish are small
                tasks.sort(key=lambda members: -sum(expected[i] for i in members))
            split: set[Hashable] = set()
            if keys is not None:
                task_of: dict[Hashable, int] = {}
                for t, members in enumerate(tasks):
                    for i in members:
                        if task_of.setdefault(keys[i], t) != t:
                            split.add(keys[i])
            futures = [self._submit_task(pickled_fn, jobs, members, keys, split, prepare) for members in tasks]
            self.tasks_submitted += len(futures)
            if bar is not None:
                size = {future.key: len(members) for future, members in zip(futures, tasks)}
                for future in as_completed(futures):
                    bar.update(size[future.key])
            out_of_order = self._client.gather(futures)
            results: list[Any] = [None] * len(jobs)
            seconds = [0.0] * len(jobs)
            for members, (address, timed) in zip(tasks, out_of_order):
                for i, (result, took) in zip(members, timed):
                    results[i] = result
                    seconds[i] = took
                if keys is not None:
                    self._loaded_at.update(dict.fromkeys((keys[i] for i in members), address))
            self._learn(fn, guesses, seconds)
            return results
        finally:
            if bar is not None:
                bar.close()

    def _worker_count(self) -> int:
        """The cluster's workers now (the scheduler's last report), at least 1."""
        return max(1, len(self._client.scheduler_info().get("workers", {})) or self.info.workers)

    def _expected_seconds(self, fn: Callable[..., Any], guesses: list[float] | None, n: int) -> list[float | None]:
        """Each job's expected duration (seconds): the guess scaled by what ``fn``'s jobs took."""
        learned = self._learned.get(_learning_key(fn, guesses))
        if guesses is None:
            return [statistics.median(learned) if learned else None] * n
        scale = statistics.median(learned) if learned else 1.0
        return [g * scale for g in guesses]

    def _learn(self, fn: Callable[..., Any], guesses: list[float] | None, seconds: list[float]) -> None:
        """Keeps the finished jobs' measured durations (against their guesses, if any)."""
        learned = self._learned.setdefault(_learning_key(fn, guesses), deque(maxlen=_LEARNED_JOBS))
        if guesses is None:
            learned.extend(seconds)
        else:
            learned.extend(took / guess for took, guess in zip(seconds, guesses) if guess > 0 and math.isfinite(guess))

    def stream(self, fn: Callable[[J], R], jobs: Iterable[J], *, max_in_flight: int | None = None) -> Iterator[tuple[int, R]]:
        """``(i, fn(job_i))`` for every job, yielded **as the jobs finish** (serially: in order).

        Nothing is gathered: on a cluster at most ``max_in_flight`` tasks are submitted at a
        time (default: twice the workers, so none idles while the client takes a result), a
        finished task's result is released from the cluster once yielded, and ``jobs`` is read
        only as tasks are submitted, so it may be a generator. The client's and the
        scheduler's memory stay bounded whatever the number of jobs. A task that raises is
        retried ``retries`` times, then its exception is raised here; closing the iterator
        early cancels the tasks still submitted.
        """
        numbered = enumerate(jobs)
        if self._client is None:
            for i, job in numbered:
                yield i, fn(job)
            return
        from distributed import as_completed

        if max_in_flight is None:
            workers = len(self._client.scheduler_info().get("workers", {})) or self.info.workers
            max_in_flight = 2 * max(1, workers)
        if max_in_flight < 1:
            raise ValueError(f"max_in_flight must be at least 1, not {max_in_flight}")
        index_of: dict[str, int] = {}
        running = as_completed(loop=self._client.loop)  # this client's: it is not the default one

        def submit_next() -> None:
            for i, job in numbered:  # at most one: the loop only fetches the next job
                future = self._client.submit(fn, job, pure=False, retries=self.retries)
                index_of[future.key] = i
                running.add(future)
                return

        try:
            for _ in range(max_in_flight):
                submit_next()
            for future in running:
                i = index_of.pop(future.key)
                result = future.result()
                future.release()
                submit_next()  # before the yield: the cluster works while the caller writes
                yield i, result
        finally:
            for future in running.futures:
                future.cancel()
            running.clear()

    def _submit_task(self, pickled_fn: bytes, jobs: list[Any], members: list[int], keys: list[Hashable] | None,
                     split: set[Hashable], prepare: Callable[[Any], Any] | None) -> Any:
        """One task of ``map``, placed by its inputs (``split``: the inputs whose jobs are in
        more than one task). An input split over tasks gets its prepare task, which those
        tasks depend on, so that they run beside it and it is read about once. An input whose
        jobs are all in this task is loaded by the task itself (its first job, as serially):
        the task goes to the worker that loaded most of its inputs in an earlier ``map``, if
        any did, else to whichever worker is free first."""
        ready, where = [], Counter()
        for key in dict.fromkeys(keys[i] for i in members) if keys is not None else ():
            if key in split or key in self._prepare_futures:
                ready.append(self._prepared(key, prepare))
            elif key in self._loaded_at:
                where[self._loaded_at[key]] += 1
        # pure=False: two equal batches are still two runs (the timings differ); a worker named
        # is a preference: another may take the task when that one is busy or gone
        placement = {"workers": [where.most_common(1)[0][0]], "allow_other_workers": True} if where else {}
        return self._client.submit(
            _run_batch, pickled_fn, [jobs[i] for i in members], *ready, pure=False, retries=self.retries, **placement
        )

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
        self._loaded_at.clear()
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
    task_floor_s: float | None = None,
) -> Runner:
    """A :class:`Runner`: serial for ``workers == 1``, else a LocalCluster, or the given scheduler.

    ``workers=None`` means :func:`default_workers`; ``task_floor_s`` (seconds, None:
    :data:`DEFAULT_TASK_FLOOR_S`) is the least expected duration of a task of
    :meth:`Runner.map`. Raises :class:`RunnerError` (one line, names the address or the
    option) when the scheduler cannot be reached within ``connect_timeout_s`` seconds, or for
    a worker count below 1 or a negative floor.
    """
    floor_s = check_task_floor(DEFAULT_TASK_FLOOR_S if task_floor_s is None else task_floor_s)
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
        return Runner(client, None, RunnerInfo("scheduler", n, scheduler), retries, floor_s)
    n = default_workers() if workers is None else int(workers)
    if n < 1:
        raise RunnerError(f"--workers must be at least 1, not {n}")
    if n == 1:
        return Runner(info=RunnerInfo("serial", 1), retries=retries, task_floor_s=floor_s)
    from distributed import Client, LocalCluster

    with _workers_ignore_ctrl_c():
        cluster = _local_cluster(LocalCluster, n)
    client = Client(cluster, set_as_default=False)
    return Runner(client, cluster, RunnerInfo("local", n, cluster.scheduler_address), retries, floor_s)


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
            # /health and /metrics) binds to 127.0.0.1 only (``host``), the scheduler's HTTP
            # server on a free port: at Dask's fixed 8787 a second command's cluster printed a
            # warning that it had moved
            dashboard_address="127.0.0.1:0",
            scheduler_kwargs={"dashboard": False},
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


def add_arguments(parser: Any, task_floor: bool = True) -> None:
    """The ``--workers`` / ``--scheduler`` / ``--task-floor-s`` options the batch commands share
    (``task_floor=False``: a command whose every job is a task's worth, the fleet replay)."""
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
    if not task_floor:
        return
    parser.add_argument(
        "--task-floor-s",
        type=float,
        default=None,
        metavar="SECONDS",
        help=f"on a cluster, group jobs into tasks expected to take at least this long (default {DEFAULT_TASK_FLOOR_S:g}; "
        "0 = one task per job; see docs/fleet.md, 'Task granularity')",
    )

