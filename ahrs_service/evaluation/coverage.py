"""Does the reported attitude uncertainty cover the actual error? A check on BROAD.

For each estimator and recording the estimator runs in blocks of ``STEP_S``; after each block
its ``attitude_variance()`` (``estimators.uncertainty``) is compared with the error of that
block's last sample against BROAD's optical reference, split as BROAD splits it
(``metrics.error_angles``): the **heading** error (the rotation about the vertical) against
the reported yaw σ, and the **inclination** error (the rotation about a horizontal axis)
against the tilt σ = √((σ²_roll + σ²_pitch) / 2), the σ of each of its two components.
Scored are the reference's ``movement`` samples with a reference and a finite variance.

A calibrated σ puts a one-dimensional Gaussian error (heading) within 1σ / 2σ in 68.3 % /
95.4 % of the reads; the inclination is the length of a two-dimensional error (Rayleigh),
within 1σ / 2σ in 39.3 % / 86.5 %.

The error models' constants are a-priori values (``uncertainty.ErrorModel``); nothing here
feeds back into them: BROAD is where they are checked, not where they are fitted.

Run: ``python -m ahrs_service.evaluation.coverage [--data DIR] [--estimators a,b] [--trials PATTERN]``
(prints the table docs/autopilot.md quotes). Data: BROAD (see ``broad.CITATION``).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field

import numpy as np

from ahrs_service import estimators
from ahrs_service.estimators.base import stack_rows
from ahrs_service.evaluation import broad
from ahrs_service.evaluation.metrics import error_angles
from ahrs_service.quaternion import ned_to_enu_array

#: how often the variance is read, s (the ODOMETRY rate is 30–50 Hz; 10 Hz samples the same statistics)
STEP_S = 0.1
ANGLES = ("heading", "inclination")
#: what an error distributed as the reported σ says gives: (within 1σ, within 2σ)
EXPECTED = {"heading": (0.683, 0.954), "inclination": (1.0 - math.exp(-0.5), 1.0 - math.exp(-2.0))}


@dataclass
class AngleCoverage:
    """Of ``n`` scored reads: how many errors were within 1σ and 2σ, and the errors' and the
    σ's root mean squares (degrees)."""

    n: int = 0
    within_1: int = 0
    within_2: int = 0
    sum_err2: float = 0.0
    sum_var: float = 0.0

    def add(self, err: np.ndarray, var: np.ndarray) -> None:
        ok = np.isfinite(err) & np.isfinite(var) & (var >= 0)
        err, sigma = np.abs(err[ok]), np.sqrt(var[ok])
        self.n += int(err.size)
        self.within_1 += int(np.count_nonzero(err <= sigma))
        self.within_2 += int(np.count_nonzero(err <= 2.0 * sigma))
        self.sum_err2 += float(np.sum(err * err))
        self.sum_var += float(np.sum(var[ok]))

    @property
    def frac_1(self) -> float:
        return self.within_1 / self.n if self.n else math.nan

    @property
    def frac_2(self) -> float:
        return self.within_2 / self.n if self.n else math.nan

    @property
    def rms_error_deg(self) -> float:
        return math.degrees(math.sqrt(self.sum_err2 / self.n)) if self.n else math.nan

    @property
    def rms_sigma_deg(self) -> float:
        return math.degrees(math.sqrt(self.sum_var / self.n)) if self.n else math.nan


@dataclass
class Coverage:
    estimator: str
    angles: dict[str, AngleCoverage] = field(default_factory=lambda: {a: AngleCoverage() for a in ANGLES})


def trial_coverage(name: str, trial: broad.Trial, into: Coverage | None = None, step_s: float = STEP_S) -> Coverage:
    """Runs estimator ``name`` (defaults) over ``trial`` and adds its reads to ``into``."""
    cov = into if into is not None else Coverage(name)
    est = estimators.create(name)
    rows = stack_rows(trial.gyr, trial.acc, trial.mag if est.uses_mag else None, 1.0 / trial.rate_hz)
    block = max(1, int(round(step_s * trial.rate_hz)))
    ends, q_est, var = [], [], []
    for start in range(0, len(rows) - block + 1, block):
        q = est.run_rows(rows[start : start + block])
        v = est.attitude_variance()
        ends.append(start + block - 1)
        q_est.append(q[-1])
        var.append((v.roll, v.pitch, v.yaw))
    idx = np.array(ends)
    q_est_a = np.array(q_est)
    var_a = np.array(var)
    ref = trial.ref[idx]
    scored = trial.movement[idx] & np.all(np.isfinite(ref), axis=1)
    _, heading, inclination = error_angles(ned_to_enu_array(q_est_a[scored]), ref[scored])
    v = var_a[scored]
    cov.angles["heading"].add(heading, v[:, 2])
    cov.angles["inclination"].add(inclination, 0.5 * (v[:, 0] + v[:, 1]))
    return cov


def broad_coverage(name: str, data_dir, trials: list[str] | None = None) -> Coverage:
    """Coverage of estimator ``name`` over the BROAD recordings (all, or ``trials``)."""
    cov = Coverage(name)
    for t in trials if trials is not None else broad.list_trials(data_dir):
        trial_coverage(name, broad.load_trial(data_dir, t), cov)
    return cov


def format_table(rows: list[Coverage]) -> str:
    head = "| estimator | error | reads | within 1σ | within 2σ | RMS error ° | RMS σ ° |"
    lines = [head, "|---|---|---|---|---|---|---|"]
    for c in rows:
        for angle, a in c.angles.items():
            if a.n == 0:
                lines.append(f"| {c.estimator} | {angle} | 0 | (NaN: not reported) | | | |")
                continue
            lines.append(
                f"| {c.estimator} | {angle} | {a.n} | {100 * a.frac_1:.1f} % | {100 * a.frac_2:.1f} % "
                f"| {a.rms_error_deg:.2f} | {a.rms_sigma_deg:.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ahrs_service.evaluation.coverage", description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="BROAD folder (default $AHRS_BROAD_DIR or ../shared/data/broad)")
    ap.add_argument("--estimators", default=",".join(estimators.names()), help="comma-separated names")
    ap.add_argument("--trials", default=None, help="shell pattern of recording names")
    args = ap.parse_args(argv)
    data = args.data or broad.default_dir()
    try:
        trials = broad.list_trials(data, args.trials)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = []
    for name in args.estimators.split(","):
        rows.append(broad_coverage(name.strip(), data, trials))
        print("\n".join(format_table(rows[-1:]).splitlines()[2:]), flush=True)  # progress
    print()
    for angle, (one, two) in EXPECTED.items():
        print(f"calibrated σ, {angle}: {100 * one:.1f} % within 1σ, {100 * two:.1f} % within 2σ")
    print(format_table(rows))
    print(f"\nData: {broad.CITATION}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
