"""Pipeline cost per sample: blocks of n rows against the same code fed one row a block, and
against the per-sample pipeline before blocks (taken from git), in alternating runs.

    python benchmarks/blocks.py [--samples 5000] [--runs 5] [--estimator madgwick] [--old 833221e]

Each run feeds the same 1 kHz samples (a calibration with every term, a 100 Hz magnetometer)
through a fresh pipeline: ``old per-sample`` is ``EstimationPipeline.process`` of revision
``--old`` (one ``ImuSample`` at a time: calibrate, fill the row, ``update_row``); ``block of 1``
is the current ``process`` (a one-row block: ``SampleBlock.from_samples`` + ``process_block``, the
polling path); ``block of 10`` is ``process_block`` over 10-row blocks built beforehand (a FIFO
drained at 100 Hz, as the FIFO board hands them). Printed: the median µs per sample of each and
the ratios, and whether the three end in the same estimator state (they must: bit for bit).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ahrs_service import estimators
from ahrs_service import pipeline as new_pipeline
from ahrs_service.core.calibration import SensorCalibration
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSample, SampleBlock

REPO = Path(__file__).resolve().parents[1]


def old_pipeline(rev: str):
    """``ahrs_service/pipeline.py`` of git revision ``rev`` as a module."""
    src = subprocess.run(["git", "show", f"{rev}:ahrs_service/pipeline.py"], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout
    path = Path(tempfile.mkdtemp()) / "old_pipeline.py"
    path.write_text(src)
    spec = importlib.util.spec_from_file_location("old_pipeline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["old_pipeline"] = module
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--estimator", default="madgwick")
    ap.add_argument("--old", default="833221e", help="git revision of the per-sample pipeline")
    args = ap.parse_args(argv)
    old = old_pipeline(args.old)
    cal = SensorCalibration.from_dict({"gyro_bias": [0.01, 0, 0], "acc_bias": [0.1, 0, 0],
                                       "mag_hard_iron": [3, 1, 0], "mounting_rpy_deg": [180, 0, 90]})
    rng = np.random.default_rng(0)
    n = args.samples
    samples = [ImuSample(1_000_000 * k, rng.normal(0, 0.1, 3), np.array([0, 0, -9.8]) + rng.normal(0, 0.1, 3),
                         np.array([20.0, 0, 45]),
                         GYR_VALID | ACC_VALID | MAG_VALID | (MAG_NEW if k % 10 == 0 else 0)) for k in range(n)]
    blocks10 = [SampleBlock.from_samples(samples[i:i + 10]) for i in range(0, n, 10)]

    def fresh(module):
        p = module.EstimationPipeline(estimators.create(args.estimator), cal, nominal_dt=0.001)
        p.warm_up()
        return p

    def timed(module, method: str, feed: list):
        """Seconds to hand every item of ``feed`` to ``method`` of a fresh pipeline, and its final state."""
        p = fresh(module)
        step = getattr(p, method)
        t = time.perf_counter()
        for item in feed:
            step(item)
        return time.perf_counter() - t, p.estimator.state.copy()

    kinds = {"old per-sample": (old, "process", samples), "block of 1 (polling)": (new_pipeline, "process", samples),
             "block of 10 (FIFO)": (new_pipeline, "process_block", blocks10)}
    times: dict[str, list[float]] = {k: [] for k in kinds}
    states: dict[str, np.ndarray] = {}
    for _ in range(args.runs):
        for name, kind in kinds.items():
            seconds, state = timed(*kind)
            times[name].append(seconds / n * 1e6)
            states[name] = state
    ref = float(np.median(times["old per-sample"]))
    same = all(np.array_equal(s, states["old per-sample"], equal_nan=True) for s in states.values())
    print(f"| {args.estimator}, {n} samples, {args.runs} alternating runs | µs per sample (median) | ratio to old |")
    print("|---|---|---|")
    for name in kinds:
        med = float(np.median(times[name]))
        print(f"| {name} | {med:.2f} | {med / ref:.2f} |")
    print(f"same final state, bit for bit: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
