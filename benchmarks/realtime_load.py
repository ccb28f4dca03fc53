"""What real-time scheduling of the loop buys on a busy computer: the README's default run
beside CPU-bound processes, at normal priority and with ``--realtime-priority``.

    python benchmarks/realtime_load.py [--burners 3] [--seconds 15] [--rounds 2] [--markdown]

Each round runs ``ahrs-service run --duration S`` (the embedded default: simulated GY-80,
``robust``, MAVLink to 127.0.0.1:14550, the MCAP log in a temporary folder) twice — once at
normal priority, once with ``--realtime-priority 40 --lock-memory`` — while ``--burners``
processes spin on the CPU (each ends by itself after the round). The figures are the
service's own final summary line: samples estimated, samples lost, the loop's jitter p99 and
overruns. Both modes run in the same rounds on the same machine, so their ratio holds where
the absolute figures depend on the load. The real-time mode needs the right to SCHED_FIFO
(root, CAP_SYS_NICE or an rtprio limit); where it is refused the table says so.
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import tempfile
import time

_SUMMARY = re.compile(r"stopped: .*?jitter p99 (\d+) us, overruns (\d+), samples (\d+), lost (\d+)")
_BURN = "import time\nt = time.monotonic()\nwhile time.monotonic() - t < {s}:\n    pass\n"


def _command() -> list[str]:
    return [sys.executable, "-m", "ahrs_service.cli", "run"]


def one_run(seconds: float, realtime: bool, log_dir: str) -> dict[str, float | bool]:
    """The summary figures of one run of the default service for ``seconds``."""
    cmd = [*_command(), "--duration", str(seconds), "--log-dir", log_dir]
    if realtime:
        cmd += ["--realtime-priority", "40", "--lock-memory"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=seconds + 600)
    match = _SUMMARY.search(out.stderr)
    if match is None:
        raise RuntimeError(f"no summary line in the service's output:\n{out.stderr[-2000:]}")
    jitter_us, overruns, samples, lost = (int(g) for g in match.groups())
    return {"jitter_p99_ms": jitter_us / 1e3, "overruns": overruns, "samples": samples, "lost": lost,
            "refused": "realtime_priority = 40 not applied" in out.stderr}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--burners", type=int, default=3, help="CPU-bound processes beside the service (default 3)")
    ap.add_argument("--seconds", type=float, default=15.0, help="length of each run, s (default 15)")
    ap.add_argument("--rounds", type=int, default=2, help="runs per mode (default 2)")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    results: dict[bool, list[dict[str, float | bool]]] = {False: [], True: []}
    with tempfile.TemporaryDirectory(prefix="ahrs-rt-") as tmp:
        one_run(3.0, False, tmp)  # kernels compiled or loaded once before anything is timed
        for _ in range(args.rounds):
            for realtime in (False, True):
                burners = [subprocess.Popen([sys.executable, "-c", _BURN.format(s=args.seconds + 30)])
                           for _ in range(args.burners)]
                try:
                    time.sleep(1.0)  # the burners are running before the service starts
                    results[realtime].append(one_run(args.seconds, realtime, tmp))
                finally:
                    for b in burners:
                        b.kill()
                        b.wait()
    print(f"# {platform.node()} {platform.machine()} {os.cpu_count()} CPUs, python {platform.python_version()}, "
          f"{args.burners} CPU-bound processes beside the service, {args.rounds} x {args.seconds:.0f} s per mode")
    head = ("mode", "samples", "lost", "lost %", "jitter p99 ms (worst)", "overruns")
    rows = []
    for realtime, runs in results.items():
        samples = sum(r["samples"] for r in runs)
        lost = sum(r["lost"] for r in runs)
        mode = "SCHED_FIFO 40 + mlockall" if realtime else "normal priority"
        if realtime and any(r["refused"] for r in runs):
            mode += " (refused: normal)"
        pct = 100.0 * lost / max(1, samples + lost)
        rows.append((mode, samples, lost, pct, max(r["jitter_p99_ms"] for r in runs), sum(r["overruns"] for r in runs)))
    if args.markdown:
        print("| " + " | ".join(head) + " |")
        print("|---|---:|---:|---:|---:|---:|")
        for mode, s, lost, pct, j, o in rows:
            print(f"| {mode} | {s} | {lost} | {pct:.1f} | {j:.1f} | {o} |")
    else:
        print(f"{head[0]:<36}{head[1]:>10}{head[2]:>10}{head[3]:>9}{head[4]:>24}{head[5]:>10}")
        for mode, s, lost, pct, j, o in rows:
            print(f"{mode:<36}{s:>10}{lost:>10}{pct:>9.1f}{j:>24.1f}{o:>10}")
    normal, rt = rows[0][3], rows[1][3]
    print(f"lost share, normal / real-time: {normal:.1f} % / {rt:.1f} %"
          + (f" ({normal / rt:.0f}x fewer lost)" if rt > 0 else " (none lost in real time)"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
