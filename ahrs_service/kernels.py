"""Compiling the estimator kernels ahead of the loop: ``ahrs-service compile``, and the child
process that compiles for a start under systemd and for a reload to another estimator.

The first use of an estimator on a machine compiles its numba kernels (seconds for a paper
filter, a minute or more for ``robust``, longer on a Raspberry Pi: docs/systemd.md); afterwards
they load from numba's on-disk cache (``__pycache__`` beside the sources, or
``$NUMBA_CACHE_DIR``). Compiling holds the interpreter lock for long stretches (LLVM), so it
can neither run on the estimation loop nor on a thread beside it: a thread would stall the
loop just the same. It runs in a **child process** instead (:class:`ChildCompile`, the
command ``ahrs-service compile``), which fills the on-disk cache; the parent then loads the
kernels from the cache, which blocks only for that load (see ``benchmarks/kernel_load.py``).

* start under systemd (:func:`compile_in_child`): the service waits for the child and sends
  ``EXTEND_TIMEOUT_USEC`` every ``EXTEND_EVERY_S`` meanwhile, so systemd's start timeout
  cannot kill a first start that compiles;
* reload to another estimator (``Service.reload``): the child compiles while the loop goes on
  with the old estimator; the reload completes once the child is done (docs/systemd.md).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Callable

from ahrs_service import estimators

#: each EXTEND_TIMEOUT_USEC asks systemd for this much more time, s
EXTEND_TIMEOUT_S = 30.0
#: how often the service sends it while a child compiles, s (well inside EXTEND_TIMEOUT_S)
EXTEND_EVERY_S = 5.0
#: how often a waiting start looks at the child and at a stop request, s
POLL_S = 0.1
#: nice value of a reload's compile child: the estimation loop beside it keeps the CPU it needs.
#: A start's child runs at the service's own priority: no loop runs yet, and on a busy
#: machine a niced compile would get a sliver of a core while systemd and the user wait.
CHILD_NICE = 5


def loaded(name: str) -> bool:
    """True when this process has compiled, or loaded from the cache, the kernel the service
    runs estimator ``name`` with (its ``batch`` over a block of rows; numba's
    ``Dispatcher.signatures``): using it costs no compile."""
    return bool(estimators.get(name).batch.signatures)


def warm_up(name: str) -> float:
    """Compiles (or loads from the cache) every kernel the service's per-sample path uses
    with estimator ``name``, in this process; returns the seconds it took."""
    from ahrs_service.core.vibration import VibrationMonitor
    from ahrs_service.pipeline import EstimationPipeline

    t0 = time.monotonic()
    EstimationPipeline(estimators.create(name)).warm_up()
    VibrationMonitor.warm_up()
    return time.monotonic() - t0


def child_command(names: list[str], nice: int = 0) -> list[str]:
    """The command line of a compile child: ``ahrs-service compile`` of this interpreter,
    ``nice`` added to its nice value."""
    return [sys.executable, "-m", "ahrs_service.cli", "compile", "--nice", str(nice), *names]


@dataclass
class ChildCompile:
    """A running ``ahrs-service compile`` child process and what it reports.

    ``poll()`` never blocks (the loop calls it); ``error`` is the last line the child wrote
    to stderr when it failed. Times on the monotonic clock, ns.
    """

    names: list[str]
    process: subprocess.Popen
    started_ns: int
    _stderr: object = field(repr=False, default=None)
    ended_ns: int | None = None
    error: str = ""

    @classmethod
    def start(cls, names: list[str], *, nice: int = 0) -> "ChildCompile":
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")}
        stderr = tempfile.TemporaryFile(mode="w+b")  # a pipe nobody reads could fill and block it
        process = subprocess.Popen(child_command(names, nice), stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                   stderr=stderr, env=env)
        return cls(list(names), process, time.monotonic_ns(), stderr)

    @property
    def ok(self) -> bool:
        return self.process.returncode == 0

    @property
    def seconds(self) -> float:
        return ((self.ended_ns or time.monotonic_ns()) - self.started_ns) / 1e9

    def poll(self) -> bool:
        """True once the child has ended (then ``ok``, ``error``, ``seconds`` are final)."""
        if self.ended_ns is not None:
            return True
        if self.process.poll() is None:
            return False
        self._finish()
        return True

    def wait(self, timeout_s: float) -> bool:
        """Waits at most ``timeout_s`` for the child to end; True if it has."""
        try:
            self.process.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return False
        return self.poll()

    def kill(self) -> None:
        """Ends the child (a stop while it compiles); nothing it wrote to the cache is harmed:
        numba writes each cache file whole (temporary name, then rename)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()
        self.poll()

    def _finish(self) -> None:
        self.ended_ns = time.monotonic_ns()
        if self._stderr is not None:
            if self.process.returncode != 0:
                self._stderr.seek(0)
                lines = [x for x in self._stderr.read().decode(errors="replace").splitlines() if x.strip()]
                self.error = lines[-1].strip() if lines else f"exit status {self.process.returncode}"
            self._stderr.close()
            self._stderr = None


def compile_in_child(
    names: list[str],
    notifier,
    *,
    extend_s: float = EXTEND_TIMEOUT_S,
    every_s: float = EXTEND_EVERY_S,
    stop: Callable[[], bool] = lambda: False,
) -> ChildCompile:
    """Compiles ``names`` in a child and waits for it, telling systemd meanwhile: one
    ``EXTEND_TIMEOUT_USEC`` (``extend_s``) at once and then every ``every_s``, a ``STATUS``
    line, and ``WATCHDOG=1`` when systemd asked for a watchdog. ``notifier`` is a
    :class:`ahrs_service.systemd.Notifier`. ``stop()`` true (SIGTERM) ends the child early.
    """
    child = ChildCompile.start(names)
    notifier.status(f"compiling the {', '.join(names)} kernels (first start after an install or upgrade)")
    # the watchdog, when asked for, is pinged as often as the loop would ping it
    every_ns = int(every_s * 1e9)
    if notifier.watchdog_interval_ns:
        every_ns = min(every_ns, notifier.watchdog_interval_ns)
    next_ns = time.monotonic_ns()
    while True:
        if time.monotonic_ns() >= next_ns:
            next_ns = time.monotonic_ns() + every_ns
            notifier.extend_timeout(extend_s)
            if notifier.watchdog_interval_ns:
                notifier.watchdog()
        if child.wait(POLL_S):
            return child
        if stop():
            child.kill()
            return child


@dataclass(frozen=True)
class LoopCounters:
    """The loop's own counters at one moment: scheduler ticks run, ticks missed and
    overruns (``FixedRateScheduler``), samples estimated (``EstimationPipeline.samples``)."""

    ticks: int
    missed_ticks: int
    overruns: int
    samples: int

    def since(self, before: "LoopCounters") -> "LoopCounters":
        return LoopCounters(self.ticks - before.ticks, self.missed_ticks - before.missed_ticks,
                            self.overruns - before.overruns, self.samples - before.samples)


@dataclass
class ReloadCompile:
    """A reload's compile in a child process: how long it took, what the loop did meanwhile
    (``during``: ticks run and missed, overruns, samples estimated with the old estimator) and
    how long loading the compiled kernels from the cache then held the loop (``load_ms``)."""

    name: str
    seconds: float
    ok: bool
    error: str
    during: LoopCounters
    load_ms: float | None = None

    def text(self) -> str:
        d = self.during
        load = "" if self.load_ms is None else f"; loading it from the cache held the loop {self.load_ms:.0f} ms"
        return (f"reload: {self.name} compiled in a child process in {self.seconds:.1f} s; the loop meanwhile "
                f"ran {d.ticks} ticks, missed {d.missed_ticks} ({d.overruns} overruns), estimated "
                f"{d.samples} samples{load}")


class ReloadCompiler:
    """The service's reload-time compiles: at most one child at a time, and the estimators
    it compiled (loaded from the cache by the reload that follows)."""

    def __init__(self) -> None:
        self.child: ChildCompile | None = None
        self.compiled: set[str] = set()
        self.last: ReloadCompile | None = None
        self._from = LoopCounters(0, 0, 0, 0)

    def needed(self, name: str, running: str, counters: LoopCounters) -> bool:
        """True when a reload to estimator ``name`` must wait for a child compile (started
        here, or already running); False when its kernels are in this process or compiled."""
        if self.child is not None:
            return True  # the reload after it reads the latest file
        if name == running or name in self.compiled or loaded(name):
            return False
        self.child = ChildCompile.start([name], nice=CHILD_NICE)
        self._from = counters
        return True

    def poll(self, counters: LoopCounters) -> ReloadCompile | None:
        """Never blocks: the finished compile once the child has ended, else None."""
        child = self.child
        if child is None or not child.poll():
            return None
        self.child = None
        self.last = ReloadCompile(child.names[0], child.seconds, child.ok, child.error, counters.since(self._from))
        if child.ok:
            self.compiled.add(child.names[0])
        return self.last

    def close(self) -> None:
        if self.child is not None:
            self.child.kill()
            self.child = None
