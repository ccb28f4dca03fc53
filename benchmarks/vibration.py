"""What VIBRATION's computation costs the service loop, per call, against references in the
same run.

    python benchmarks/vibration.py [--calls 100000] [--repeats 5]

Rows: ``VibrationMonitor.update`` with one sample row (the per-sample service path) and with a
block of 32 rows (a FIFO burst), beside two references, all timed alternately: the
estimator's own per-sample step (``Estimator.update_row`` of madgwick, the cheapest paper
filter) and an empty call of a compiled numba function (the call overhead floor). Best of
``--repeats``; compare the ratios of one run, not runs.
"""

from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from ahrs_service import estimators
from ahrs_service.core.samples import ACC_VALID, GYR_VALID
from ahrs_service.core.vibration import VibrationMonitor


@numba.njit(cache=True)
def _empty(rows):
    return rows.shape[0]


def _best_alternating(cases: dict, calls: int, repeats: int) -> dict[str, float]:
    """Best time per call of each case; each repeat runs every case once, in turn, so a change
    of the machine's load during the run reaches all of them alike."""
    best = {name: float("inf") for name in cases}
    for _ in range(repeats):
        for name, fn in cases.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                fn()
            best[name] = min(best[name], (time.perf_counter() - t0) / calls)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=100_000)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    block = np.zeros((32, 10))
    block[:, 3:6] = rng.normal(0, 1, (32, 3)) + [0.0, 0.0, -9.81]
    block[:, 9] = 0.001
    row = block[0].copy()
    flags = np.full(32, GYR_VALID | ACC_VALID)
    vib = VibrationMonitor()
    est = estimators.create("madgwick")
    for f in (lambda: vib.update(row, 3), lambda: vib.update(block, flags), lambda: est.update_row(row),
              lambda: _empty(block)):
        f()  # compile / warm
    cases = {
        "update(1 row)": lambda: vib.update(row, int(GYR_VALID | ACC_VALID)),
        "update(32 rows)": lambda: vib.update(block, flags),
        "madgwick update_row (ref)": lambda: est.update_row(row),
        "empty numba call (ref)": lambda: _empty(block),
    }
    times = _best_alternating(cases, args.calls, args.repeats)
    ref = times["madgwick update_row (ref)"]
    print(f"{'case':28s} {'µs/call':>9s} {'µs/row':>9s} {'÷ update_row':>13s}")
    for name, t in times.items():
        rows = 32 if "32" in name else 1
        print(f"{name:28s} {t * 1e6:9.2f} {t * 1e6 / rows:9.3f} {t / ref:13.2f}")


if __name__ == "__main__":
    main()
