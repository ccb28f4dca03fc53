"""Does the reported attitude uncertainty cover the actual error? A check on BROAD and DIDO.

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

The error models' physical constants are a-priori values (``uncertainty``); ``robust``,
``ekf``, ``triad`` and ``quest`` also carry one scale per angle, chosen on the data.
``--calibrate`` shows how. Each data set present needs the scale that puts the
claimed fraction of its errors within 1σ (BROAD: 12 handheld recordings; DIDO, ``--dataset
dido``: 8 quadrotor flights with attitude truth and no magnetometer, so DIDO scores the
inclination only and has no say in the heading scale). The **chosen scale is the largest of
those needs**: no data set sees its errors under-covered (an overconfident σ, the dangerous
direction for an autopilot fusing it); the others are then conservative. Held out: each
recording (flight) scored under the scale chosen without it — its own data set's need
re-chosen on the other recordings, the other data sets' needs from all of theirs. It also
prints each data set alone (leave-one-recording-out), as before.

Run: ``python -m ahrs_service.evaluation.coverage [--dataset broad|dido] [--data DIR]
[--estimators a,b] [--trials PATTERN] [--calibrate] [--drop-pattern P [--drop-seed N]]``
(prints the tables docs/autopilot.md quotes; with ``--drop-pattern`` the samples are lost as
the gap benchmark loses them, docs/gaps.md). Data: BROAD (see ``broad.CITATION``), DIDO (``dido.CITATION``).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field

import numpy as np

from ahrs_service import estimators
from ahrs_service.core.quaternion import ned_to_enu_array
from ahrs_service.estimators.base import stack_rows, time_steps
from ahrs_service.evaluation import broad, dido, gaps
from ahrs_service.evaluation.metrics import error_angles

#: how often the variance is read, s (the ODOMETRY rate is 30–50 Hz; 10 Hz samples the same statistics)
STEP_S = 0.1
ANGLES = ("heading", "inclination")
#: what an error distributed as the reported σ says gives: (within 1σ, within 2σ)
#: the data sets the check runs on (``--dataset``)
DATASETS = {"broad": broad, "dido": dido}
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
class Reads:
    """One recording's scored reads: per angle the absolute errors and the reported variances
    (rad, rad²), and the scales the estimator's error model applied (1.0 where it has none)."""

    errors: dict[str, np.ndarray]
    variances: dict[str, np.ndarray]
    scales: dict[str, float]


@dataclass
class Coverage:
    estimator: str
    angles: dict[str, AngleCoverage] = field(default_factory=lambda: {a: AngleCoverage() for a in ANGLES})
    #: recording name → its reads (for the cross-validation of a calibration scale)
    reads: dict[str, Reads] = field(default_factory=dict)


def model_scales(est: estimators.Estimator) -> dict[str, float]:
    """The calibration scales of an estimator's ``observed_error_model`` (1.0 without one):
    {"heading": heading_scale, "inclination": tilt_scale}."""
    model = getattr(est, "observed_error_model", None)
    if model is None:
        return {"heading": 1.0, "inclination": 1.0}
    return {"heading": float(model.heading_scale), "inclination": float(model.tilt_scale)}


def trial_coverage(
    name: str,
    trial: broad.Trial,
    into: Coverage | None = None,
    step_s: float = STEP_S,
    drop_pattern: gaps.DropPattern | str | None = None,
    seed: int = 0,
) -> Coverage:
    """Runs estimator ``name`` (defaults) over ``trial`` (a BROAD trial or a DIDO flight: its
    recorded stamps are used when it has them) and adds its reads to ``into``.

    ``drop_pattern`` (``gaps.parse``): the rows the pattern drops with ``seed`` are lost, as
    the gap benchmark loses them (docs/gaps.md); the reads are then the kept rows' and the
    variance is what the estimator reports across and after the gaps."""
    cov = into if into is not None else Coverage(name)
    est = estimators.create(name)
    mag = trial.mag if est.uses_mag else None
    if drop_pattern is None:
        stamps = getattr(trial, "timestamps", None)
        dt = time_steps(len(trial), None, stamps) if stamps is not None else 1.0 / trial.rate_hz
        rows = stack_rows(trial.gyr, trial.acc, mag, dt)
        row_index = np.arange(len(trial))
    else:
        keep = gaps.kept_rows(gaps.sample_times(trial), drop_pattern, seed=seed, scored=trial.movement)
        rows = stack_rows(trial.gyr[keep], trial.acc[keep], None if mag is None else mag[keep],
                          gaps.gapped_steps(trial, keep))
        row_index = np.flatnonzero(keep)
    block = max(1, int(round(step_s * trial.rate_hz)))
    ends, q_est, var = [], [], []
    for start in range(0, len(rows) - block + 1, block):
        q = est.run_rows(rows[start : start + block])
        v = est.attitude_variance()
        ends.append(row_index[start + block - 1])
        q_est.append(q[-1])
        var.append((v.roll, v.pitch, v.yaw))
    idx = np.array(ends)
    q_est_a = np.array(q_est)
    var_a = np.array(var)
    ref = trial.ref[idx]
    scored = trial.movement[idx] & np.all(np.isfinite(ref), axis=1)
    _, heading, inclination = error_angles(ned_to_enu_array(q_est_a[scored]), ref[scored])
    v = var_a[scored]
    per_angle = {"heading": (heading, v[:, 2]), "inclination": (inclination, 0.5 * (v[:, 0] + v[:, 1]))}
    if np.isnan(trial.mag).all():
        # no magnetometer (DIDO): the reference's heading is arbitrary, heading is not scored
        per_angle["heading"] = (heading, np.full_like(heading, np.nan))
    for angle, (err, var) in per_angle.items():
        cov.angles[angle].add(err, var)
    cov.reads[trial.name] = Reads(
        errors={a: np.abs(e) for a, (e, _) in per_angle.items()},
        variances={a: vv for a, (_, vv) in per_angle.items()},
        scales=model_scales(est),
    )
    return cov


def broad_coverage(
    name: str,
    data_dir,
    trials: list[str] | None = None,
    dataset: str = "broad",
    drop_pattern: gaps.DropPattern | str | None = None,
    seed: int = 0,
) -> Coverage:
    """Coverage of estimator ``name`` over the recordings of ``dataset`` (all, or ``trials``),
    with the rows ``drop_pattern`` drops lost (``trial_coverage``)."""
    source = DATASETS[dataset]
    cov = Coverage(name)
    for t in trials if trials is not None else source.list_trials(data_dir):
        trial_coverage(name, source.load_trial(data_dir, t), cov, drop_pattern=drop_pattern, seed=seed)
    return cov


@dataclass
class Calibration:
    """The scale of one angle's σ that gives the claimed 1σ coverage, and how it holds out.

    scale: relative to the model without its scale (1.0: the σ as the model computes it).
    held_out_1, held_out_2: fractions within 1σ / 2σ of every recording's reads under the
    scale chosen on the other recordings (leave-one-recording-out); per_recording: the
    held-out 1σ fraction of each."""

    angle: str
    scale: float
    current: float
    held_out_1: float
    held_out_2: float
    per_recording: dict[str, float]


def scale_ratios(cov: Coverage, angle: str) -> dict[str, np.ndarray]:
    """Recording name → |error| / σ_unscaled of its scored reads of ``angle`` (the σ the model
    computes before its calibration scale; recordings without a finite σ left out)."""
    ratios: dict[str, np.ndarray] = {}
    for name, r in cov.reads.items():
        err, var = r.errors[angle], r.variances[angle]
        ok = np.isfinite(err) & np.isfinite(var) & (var > 0)
        if ok.any():
            ratios[name] = err[ok] / (np.sqrt(var[ok]) / r.scales[angle])
    return ratios


def calibrate(cov: Coverage, angle: str) -> Calibration | None:
    """Leave-one-recording-out choice of the scale of ``angle``'s σ on one data set: on each
    recording's complement the scale is the EXPECTED 1σ quantile of |error| / σ_unscaled (so
    that the claimed fraction falls within 1σ there), then applied to the left-out recording.
    None when no recording has a finite σ. The returned ``scale`` is the one from all
    recordings: what this data set needs (``calibrate_across`` combines the data sets)."""
    ratios = scale_ratios(cov, angle)
    if not ratios:
        return None
    q = EXPECTED[angle][0]
    within_1 = within_2 = total = 0
    per: dict[str, float] = {}
    for name, r in ratios.items():
        rest = [v for m, v in ratios.items() if m != name]
        if not rest:
            continue
        k = float(np.quantile(np.concatenate(rest), q))
        per[name] = float(np.mean(r <= k))
        within_1 += int(np.count_nonzero(r <= k))
        within_2 += int(np.count_nonzero(r <= 2.0 * k))
        total += r.size
    scale = float(np.quantile(np.concatenate(list(ratios.values())), q))
    current = next(iter(cov.reads.values())).scales[angle]
    return Calibration(angle, scale, current, within_1 / total if total else math.nan, within_2 / total if total else math.nan, per)


@dataclass
class JointCalibration:
    """The scale of one angle's σ chosen across data sets, and how it holds out on each.

    The rule: every data set that scores the angle needs the scale that puts the claimed 1σ
    fraction of its errors within 1σ (``calibrate``: the quantile over all its recordings);
    the chosen scale is the largest of those, so that no data set sees its errors
    under-covered (overconfident σ) and the others are then conservative.

    needed: data set → the scale it needs; chosen: their maximum.
    held_out: data set → (within 1σ, within 2σ) of each of its recordings under the scale
    chosen without that recording (its own data set's need re-chosen on the other
    recordings, the other data sets' needs from all of theirs); per_recording: data set →
    recording → its held-out 1σ fraction."""

    angle: str
    current: float
    needed: dict[str, float]
    chosen: float
    held_out: dict[str, tuple[float, float]]
    per_recording: dict[str, dict[str, float]]


def calibrate_across(covs: dict[str, Coverage], angle: str) -> JointCalibration | None:
    """The largest of the scales each data set in ``covs`` (data set name → one estimator's
    coverage on it) needs for ``angle``, with its leave-one-recording-out coverage on each
    (``JointCalibration``). Data sets without a finite σ of the angle (DIDO's heading) take
    no part; None when none has one."""
    q = EXPECTED[angle][0]
    ratios = {ds: r for ds, cov in covs.items() if (r := scale_ratios(cov, angle))}
    if not ratios:
        return None
    needed = {ds: float(np.quantile(np.concatenate(list(r.values())), q)) for ds, r in ratios.items()}
    held_out: dict[str, tuple[float, float]] = {}
    per: dict[str, dict[str, float]] = {}
    for ds, rs in ratios.items():
        others = max((v for d, v in needed.items() if d != ds), default=0.0)
        within_1 = within_2 = total = 0
        per[ds] = {}
        for name, r in rs.items():
            rest = [v for m, v in rs.items() if m != name]
            own = float(np.quantile(np.concatenate(rest), q)) if rest else 0.0
            k = max(own, others)
            if k <= 0.0:
                continue
            per[ds][name] = float(np.mean(r <= k))
            within_1 += int(np.count_nonzero(r <= k))
            within_2 += int(np.count_nonzero(r <= 2.0 * k))
            total += r.size
        held_out[ds] = (within_1 / total, within_2 / total) if total else (math.nan, math.nan)
    current = next(iter(next(iter(covs.values())).reads.values())).scales[angle]
    return JointCalibration(angle, current, needed, max(needed.values()), held_out, per)


def format_calibration(rows: list[tuple[str, Calibration]]) -> str:
    lines = [
        "| estimator | error | scale in use | scale (all recordings) | held out: within 1σ | within 2σ | per recording, within 1σ (min–max) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, c in rows:
        lo, hi = (min(c.per_recording.values()), max(c.per_recording.values())) if c.per_recording else (math.nan, math.nan)
        lines.append(
            f"| {name} | {c.angle} | {c.current:.2f} | {c.scale:.3f} | {100 * c.held_out_1:.1f} % | {100 * c.held_out_2:.1f} % "
            f"| {100 * lo:.0f}–{100 * hi:.0f} % |"
        )
    return "\n".join(lines)


def format_joint_calibration(rows: list[tuple[str, JointCalibration]], datasets: list[str]) -> str:
    """One row per estimator and angle: each data set's needed scale, the chosen (largest)
    one, and each data set's held-out 1σ / 2σ coverage under the rule."""
    need = " | ".join(f"{ds} needs" for ds in datasets)
    held = " | ".join(f"{ds} held out: 1σ / 2σ (per recording 1σ min–max)" for ds in datasets)
    lines = [f"| estimator | error | scale in use | {need} | chosen (largest) | {held} |", "|---" * (4 + 2 * len(datasets)) + "|"]
    for name, c in rows:
        cells_need, cells_held = [], []
        for ds in datasets:
            if ds not in c.needed:
                cells_need.append("—")
                cells_held.append("— (not scored)")
                continue
            cells_need.append(f"{c.needed[ds]:.3f}")
            one, two = c.held_out[ds]
            p = c.per_recording[ds]
            span = f"{100 * min(p.values()):.0f}–{100 * max(p.values()):.0f} %" if p else ""
            cells_held.append(f"{100 * one:.1f} % / {100 * two:.1f} % ({span})")
        lines.append(f"| {name} | {c.angle} | {c.current:.3f} | {' | '.join(cells_need)} | {c.chosen:.3f} | {' | '.join(cells_held)} |")
    return "\n".join(lines)


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
    ap.add_argument("--dataset", choices=sorted(DATASETS), default="broad", help="broad (default) or dido (no magnetometer: inclination only)")
    ap.add_argument("--data", default=None, help="data folder (default $AHRS_BROAD_DIR / $AHRS_DIDO_DIR or ../shared/data/<dataset>)")
    ap.add_argument("--estimators", default=",".join(estimators.names()), help="comma-separated names")
    ap.add_argument("--trials", default=None, help="shell pattern of recording names")
    ap.add_argument(
        "--calibrate",
        action="store_true",
        help="also print each σ's scale: what each data set present needs (leave-one-recording-out) and the chosen, largest one",
    )
    ap.add_argument("--drop-pattern", default=None, metavar="PATTERN",
                    help="lose samples as the gap benchmark does (docs/gaps.md), e.g. bursts:20-100ms:10%%, outage:2s")
    ap.add_argument("--drop-seed", type=int, default=0, help="seed of the dropped places (default 0)")
    args = ap.parse_args(argv)
    try:
        drop = gaps.parse(args.drop_pattern) if args.drop_pattern else None
    except ValueError as exc:
        print(f"error: --drop-pattern: {exc}", file=sys.stderr)
        return 2
    if args.calibrate and drop is not None:
        print("error: --calibrate chooses the scales on gap-free runs; leave out --drop-pattern", file=sys.stderr)
        return 2
    source = DATASETS[args.dataset]
    data = args.data or source.default_dir()
    names = [n.strip() for n in args.estimators.split(",") if n.strip()]
    unknown = [n for n in names if n not in estimators.names()]
    if unknown:
        print(f"error: --estimators: unknown estimator(s) {', '.join(unknown)}; known: {', '.join(estimators.names())}", file=sys.stderr)
        return 2
    try:
        trials = source.list_trials(data, args.trials)
    except (FileNotFoundError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    rows = []
    for name in names:
        rows.append(broad_coverage(name, data, trials, args.dataset, drop, args.drop_seed))
        print("\n".join(format_table(rows[-1:]).splitlines()[2:]), flush=True)  # progress
    print()
    for angle, (one, two) in EXPECTED.items():
        print(f"calibrated σ, {angle}: {100 * one:.1f} % within 1σ, {100 * two:.1f} % within 2σ")
    print(format_table(rows))
    if args.calibrate:
        cal = [(c.estimator, k) for c in rows for a in ANGLES if (k := calibrate(c, a)) is not None]
        print(f"\n{args.dataset} alone, leave-one-recording-out (the scale of σ applied to the model's unscaled σ; 1.0 where a model has none):")
        print(format_calibration(cal))
        # the other data sets, when present: the chosen scale is the largest any of them needs
        per_set = {args.dataset: {c.estimator: c for c in rows}}
        for ds, other in DATASETS.items():
            if ds == args.dataset:
                continue
            try:
                other_dir = other.default_dir()
                other_trials = other.list_trials(other_dir)
            except (FileNotFoundError, ValueError) as exc:
                print(f"\n{ds} not included in the calibration: {exc}")
                continue
            print(f"\nrunning the estimators over {ds} ({other_dir}) for the calibration", flush=True)
            per_set[ds] = {n: broad_coverage(n, other_dir, other_trials, ds) for n in names}
        sets = sorted(per_set)
        joint = [(n, k) for n in names for a in ANGLES if (k := calibrate_across({ds: per_set[ds][n] for ds in sets}, a)) is not None]
        print(
            "\nThe scale chosen across data sets (each data set needs the scale that puts the claimed share within 1σ;"
            " the largest is chosen, so that no data set sees its errors under-covered and the others are conservative;"
            " held out: each recording under the scale chosen without it):"
        )
        print(format_joint_calibration(joint, sets))
    print(f"\nData: {source.CITATION}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
