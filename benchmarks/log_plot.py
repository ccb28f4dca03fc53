"""How long ``ahrs-service log plot`` takes on a long log, against reading the same log.

Writes a synthetic log with the service's own writer (``--minutes`` at ``--rate-hz``: /imu/raw,
/attitude with diagnostics at 10 Hz, /attitude/truth, /tf at 50 Hz, /loop at 1 Hz), then
times, alternately (``--repeats`` pairs, best of each), the reference — iterating the log's
messages with ``MessageSource``, no decoding — and the whole quick look: read + decode the
drawn fields, decimate, draw and save a PNG. Prints a table; the target is one hour at 200 Hz
in ≤ 30 s on the reference machine.

    python benchmarks/log_plot.py [--minutes 60] [--rate-hz 200] [--repeats 1] [--markdown]
"""

from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_VALID
from ahrs_service.logs.plot import build_figure, read_series
from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.writer import FlightLogWriter


def write_log(directory: Path, minutes: float, rate_hz: float) -> Path:
    n = int(minutes * 60 * rate_hz)
    dt_ns = int(1e9 / rate_hz)
    w = FlightLogWriter(directory, fsync=False, queue_size=1 << 22)
    w.write_config(0, {"estimator": {"name": "robust", "params": {}}})
    flags = GYR_VALID | ACC_VALID | MAG_VALID
    rng = np.random.default_rng(1)
    diag_every = max(1, int(rate_hz / 10))
    for i in range(n):
        t = i / rate_hz
        t_ns = 1_000_000_000 + i * dt_ns
        a = 0.3 * math.sin(0.5 * t)
        row = np.array([0.15 * math.cos(0.5 * t), 0.0, 0.0, *(rng.normal(0, 0.05, 3) + (0, 0, -9.8)),
                        20.0, 0.0, 45.0, 1 / rate_hz])
        q = np.array([math.cos(a / 2), math.sin(a / 2), 0.0, 0.0])
        diag = {"mag_disturbed": False, "rest": False, "reduced": False} if i % diag_every == 0 else None
        w.write_sample(t_ns, row, flags, q=q, estimator="robust", bias=np.zeros(3), truth_q=q, diagnostics=diag)
        if i % int(rate_hz) == 0:
            w.write_loop(t_ns, {"period_jitter_p99_us": 80.0, "lateness_p99_us": 40.0, "overruns": 0, "missed_ticks": 0})
        if i % 20000 == 0:
            while len(w._q) > 100_000:  # keep memory bounded: let the writer thread catch up
                time.sleep(0.05)
    w.close(timeout=600)
    (path,) = Path(directory).glob("*.mcap")
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--rate-hz", type=float, default=200.0)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        path = write_log(Path(tmp), args.minutes, args.rate_hz)
        write_s = time.perf_counter() - t0
        read_s, plot_s, messages = math.inf, math.inf, 0
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            messages = sum(1 for _ in MessageSource(path))
            read_s = min(read_s, time.perf_counter() - t0)
            t0 = time.perf_counter()
            series = read_series(path, progress=False)
            build_figure(series, path.name).savefig(Path(tmp) / "q.png", dpi=110)
            plot_s = min(plot_s, time.perf_counter() - t0)
        rows = [
            ("log", f"{args.minutes:g} min at {args.rate_hz:g} Hz, {messages} messages, "
                    f"{path.stat().st_size / 1e6:.0f} MB (written in {write_s:.0f} s)"),
            ("read messages (reference) s", f"{read_s:.1f}"),
            ("log plot (read + decode + draw + PNG) s", f"{plot_s:.1f}"),
            ("plot / read", f"{plot_s / read_s:.2f}"),
            ("target", "<= 30 s for 60 min at 200 Hz: " + (("ok" if plot_s <= 30 else "MISSED")
                                                           if (args.minutes, args.rate_hz) == (60, 200) else "n/a (another log)")),
        ]
    if args.markdown:
        print("| measure | value |\n|---|---|")
        for k, v in rows:
            print(f"| {k} | {v} |")
    else:
        for k, v in rows:
            print(f"{k:42s} {v}")


if __name__ == "__main__":
    main()
