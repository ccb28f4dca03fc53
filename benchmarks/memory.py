"""Memory benchmark: PSS of every process of the README's default run, first start and warm.

    python benchmarks/memory.py [--seconds 20] [--runs cold,warm] [--interval 0.1] [--without scipy]
                                [--warm-cache DIR] [--venv] [--markdown]

Runs ``ahrs-service run --duration S`` with its defaults (the embedded configuration: a
simulated GY-80 on a simulated I2C bus, ``robust``, MAVLink to 127.0.0.1:14550, the MCAP log;
only the log folder is a temporary one) as a subprocess of this interpreter, and samples the
memory of the service and every process it starts (a kernel-compile child, a log writer
process) every ``--interval`` s from /proc: PSS from ``/proc/PID/smaps_rollup`` (shared
pages divided among the processes sharing them, so the sum over processes is what the
service costs the machine), and RSS.

* ``cold``: the first start on a machine — ``NUMBA_CACHE_DIR`` a fresh empty folder, so the
  estimator kernels compile;
* ``warm``: the same cache again, the kernels load from it.

Printed per run: the peak of the summed PSS (sampled: a peak shorter than the interval can be
missed), the summed peak RSS of the processes (their kernel-kept ``VmHWM``: exact, but shared
pages count once per process), the steady PSS, USS and RSS (medians of the samples from 3 s
after the loop's "running" line to the end), the time to that line, and the largest process
count. PSS depends on the rest of the machine: a library another process maps too (numba's
LLVM in a second Python) is charged half to each. USS (private pages only) is the floor that
does not, RSS the ceiling.

``--without scipy``: the service runs with those top-level packages made unimportable (a
meta-path finder, as tests/test_lean_install.py does), which is what a lean install without
them does; numba, for one, imports scipy.linalg at start-up whenever scipy is importable.

``--venv``: also creates a fresh virtual environment, ``pip install``s this checkout into it
(no extras; minutes, and it needs the package index) and prints its size on disk with the
largest distributions; without it, the same closure of ``pyproject.toml``'s dependencies is
measured in this interpreter's environment from the installed distributions' file lists.

Targets (issue 37): steady PSS ≤ 150 MB, peak during a first start ≤ 300 MB, lean
virtual environment ≤ 350 MB.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
MB = 1024 * 1024
#: samples within this long after the loop's "running" line are still the start, s
SETTLE_S = 3.0
TARGET_STEADY_MB, TARGET_PEAK_MB, TARGET_VENV_MB = 150.0, 300.0, 350.0

_BLOCKER = """
import runpy, sys
BLOCKED = set(sys.argv.pop(1).split(","))
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None
sys.meta_path.insert(0, Block())
sys.argv[0] = "ahrs-service"
runpy.run_module("ahrs_service.cli", run_name="__main__", alter_sys=True)
"""


def _children(pid: int) -> list[int]:
    kids: list[int] = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as fh:
                kids.extend(int(x) for x in fh.read().split())
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        pass
    return kids


def process_tree(pid: int) -> list[int]:
    """``pid`` and all its descendants alive now."""
    found, todo = [], [pid]
    while todo and len(found) < 1000:
        p = todo.pop()
        found.append(p)
        todo.extend(_children(p))
    return found


def _kib_field(path: str, name: str) -> int | None:
    try:
        with open(path) as fh:
            for line in fh:
                if line.startswith(name + ":"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return None


@dataclass
class Sample:
    t: float  # s since the start of the run
    pss: int  # bytes, summed over the processes
    rss: int
    uss: int  # private pages only (Private_Clean + Private_Dirty)
    processes: int


@dataclass
class RunResult:
    name: str
    samples: list[Sample] = field(default_factory=list)
    peak_rss_hwm: dict[int, int] = field(default_factory=dict)  # pid -> VmHWM, bytes
    running_at: float | None = None  # s, the loop's "running" line
    returncode: int | None = None
    output_tail: str = ""

    @property
    def peak_pss(self) -> int:
        return max((s.pss for s in self.samples), default=0)

    def steady(self, what: str) -> float:
        """Median of the summed ``what`` ("pss", "rss", "uss") once the loop runs, bytes."""
        if self.running_at is None:
            return float("nan")
        steady = [getattr(s, what) for s in self.samples if s.t >= self.running_at + SETTLE_S]
        return statistics.median(steady) if steady else float("nan")

    @property
    def start_peak_pss(self) -> int:
        end = self.running_at if self.running_at is not None else float("inf")
        return max((s.pss for s in self.samples if s.t <= end), default=0)


def measure_run(name: str, seconds: float, cache_dir: Path, interval: float, without: list[str]) -> RunResult:
    """One ``ahrs-service run --duration seconds`` with ``NUMBA_CACHE_DIR=cache_dir``, sampled."""
    log_dir = Path(tempfile.mkdtemp(prefix="memory-bench-logs-"))
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache_dir), PYTHONUNBUFFERED="1")
    env.pop("NOTIFY_SOCKET", None)
    args = ["run", "--duration", f"{seconds:g}", "--log-dir", str(log_dir)]
    if without:
        cmd = [sys.executable, "-c", _BLOCKER, ",".join(without), *args]
    else:
        cmd = [sys.executable, "-m", "ahrs_service.cli", *args]
    result = RunResult(name)
    lines: list[str] = []
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=env, cwd=log_dir)

    def read_output() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if result.running_at is None and re.search(r"\brunning: ", line):
                result.running_at = time.monotonic() - t0

    reader = threading.Thread(target=read_output, daemon=True)
    reader.start()
    # a cold start compiles for minutes on a slow machine; the bound only stops a hung run
    deadline = t0 + seconds + 1800.0
    try:
        while proc.poll() is None and time.monotonic() < deadline:
            pss = rss = uss = 0
            pids = process_tree(proc.pid)
            for pid in pids:
                pss += _kib_field(f"/proc/{pid}/smaps_rollup", "Pss") or 0
                uss += (_kib_field(f"/proc/{pid}/smaps_rollup", "Private_Clean") or 0) + \
                    (_kib_field(f"/proc/{pid}/smaps_rollup", "Private_Dirty") or 0)
                rss += _kib_field(f"/proc/{pid}/status", "VmRSS") or 0
                hwm = _kib_field(f"/proc/{pid}/status", "VmHWM")
                if hwm is not None:
                    result.peak_rss_hwm[pid] = max(hwm, result.peak_rss_hwm.get(pid, 0))
            result.samples.append(Sample(time.monotonic() - t0, pss, rss, uss, len(pids)))
            time.sleep(interval)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
        reader.join(10.0)
        shutil.rmtree(log_dir, ignore_errors=True)
    result.returncode = proc.returncode
    result.output_tail = "".join(lines[-5:])
    return result


def _distribution_sizes(requirements: list[str]) -> dict[str, int]:
    """Bytes on disk of each distribution in the closure of ``requirements`` (no extras),
    from this environment's installed file lists."""
    from importlib import metadata

    from packaging.requirements import Requirement

    sizes: dict[str, int] = {}
    todo = [Requirement(r) for r in requirements]
    while todo:
        req = todo.pop()
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue
        key = req.name.lower().replace("_", "-")
        if key in sizes:
            continue
        try:
            dist = metadata.distribution(req.name)
        except metadata.PackageNotFoundError:
            sizes[key] = 0
            continue
        total = 0
        for f in dist.files or []:
            try:
                total += (Path(dist.locate_file(f))).stat().st_size
            except OSError:
                pass
        sizes[key] = total
        todo.extend(Requirement(r) for r in (dist.requires or []))
    return sizes


def installed_closure() -> tuple[int, list[tuple[str, int]]]:
    """Size of pyproject.toml's base dependencies (and theirs) as installed here, bytes."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    sizes = _distribution_sizes(deps)
    return sum(sizes.values()), sorted(sizes.items(), key=lambda kv: -kv[1])


def _du(path: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            try:
                total += os.lstat(os.path.join(dirpath, f)).st_size
            except OSError:
                pass
    return total


def fresh_venv() -> tuple[int, list[tuple[str, int]]]:
    """Creates a virtual environment, installs this checkout without extras; its size, bytes,
    and the largest folders of its site-packages."""
    with tempfile.TemporaryDirectory(prefix="memory-bench-venv-") as tmp:
        venv = Path(tmp) / "venv"
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        subprocess.run([str(venv / "bin" / "pip"), "install", "-q", str(ROOT)], check=True, timeout=3600)
        site = next(venv.glob("lib/python*/site-packages"))
        parts = sorted(((p.name, _du(p) if p.is_dir() else p.stat().st_size) for p in site.iterdir()),
                       key=lambda kv: -kv[1])
        return _du(venv), parts


def _mb(value: float) -> str:
    return "—" if value != value or value == 0 else f"{value / MB:.0f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="run --duration of each run, s (default 20)")
    ap.add_argument("--runs", default="cold,warm", help="comma-separated: cold (fresh kernel cache), warm")
    ap.add_argument("--interval", type=float, default=0.1, help="sampling interval, s (default 0.1)")
    ap.add_argument("--without", default="", metavar="PKG[,PKG]",
                    help="make these top-level packages unimportable for the service (a lean install)")
    ap.add_argument("--warm-cache", type=Path, default=None, metavar="DIR",
                    help="a kernel cache the warm run uses as it is (default: the cold run's, or one filled first)")
    ap.add_argument("--venv", action="store_true", help="also size a fresh lean virtual environment (minutes)")
    ap.add_argument("--markdown", action="store_true", help="print the table as Markdown")
    args = ap.parse_args(argv)
    runs = [r.strip() for r in args.runs.split(",") if r.strip()]
    if any(r not in ("cold", "warm") for r in runs) or not runs:
        ap.error(f"--runs takes cold and/or warm, got {args.runs!r}")
    if not (0 < args.seconds <= 3600 and 0.01 <= args.interval <= 5):
        ap.error("--seconds must be in (0, 3600] and --interval in [0.01, 5]")
    without = [p.strip() for p in args.without.split(",") if p.strip()]

    cache = Path(tempfile.mkdtemp(prefix="memory-bench-numba-"))
    results: list[RunResult] = []
    try:
        for name in runs:
            run_cache = args.warm_cache if name == "warm" and args.warm_cache is not None else cache
            if name == "warm" and "cold" not in runs and args.warm_cache is None:
                print("warm run: filling the kernel cache first (a run not measured)", file=sys.stderr, flush=True)
                measure_run("fill", 1.0, cache, 1.0, without)
            print(f"{name} run: ahrs-service run --duration {args.seconds:g} ...", file=sys.stderr, flush=True)
            res = measure_run(name, args.seconds, run_cache, args.interval, without)
            if res.returncode != 0:
                print(f"{name} run failed (exit {res.returncode}):\n{res.output_tail}", file=sys.stderr)
                return 1
            results.append(res)
    finally:
        shutil.rmtree(cache, ignore_errors=True)

    header = ["run", "steady PSS MB", "steady USS MB", "steady RSS MB", "peak PSS MB", "peak PSS before loop MB",
              "peak RSS (Σ VmHWM) MB", "loop running after s", "processes"]
    rows = [[r.name, _mb(r.steady("pss")), _mb(r.steady("uss")), _mb(r.steady("rss")), _mb(r.peak_pss), _mb(r.start_peak_pss), _mb(sum(r.peak_rss_hwm.values())),
             f"{r.running_at:.1f}" if r.running_at is not None else "—",
             str(max((s.processes for s in r.samples), default=0))] for r in results]
    if args.markdown:
        print("| " + " | ".join(header) + " |")
        print("|" + "---|" * len(header))
        for row in rows:
            print("| " + " | ".join(row) + " |")
    else:
        widths = [max(len(h), *(len(row[i]) for row in rows)) for i, h in enumerate(header)]
        print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
        for row in rows:
            print("  ".join(c.ljust(w) for c, w in zip(row, widths)))
    print(f"targets: steady PSS ≤ {TARGET_STEADY_MB:.0f} MB, peak during a first start ≤ {TARGET_PEAK_MB:.0f} MB"
          + (f"; run without {','.join(without)}" if without else ""))

    closure, parts = installed_closure()
    print(f"base dependencies as installed here: {closure / MB:.0f} MB "
          f"(largest: {', '.join(f'{n} {s / MB:.0f}' for n, s in parts[:5])})")
    if args.venv:
        size, largest = fresh_venv()
        print(f"fresh lean virtual environment: {size / MB:.0f} MB (target ≤ {TARGET_VENV_MB:.0f} MB; "
              f"largest: {', '.join(f'{n} {s / MB:.0f}' for n, s in largest[:6])})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
