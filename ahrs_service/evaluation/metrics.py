"""Attitude error metrics: BROAD's total/heading/inclination RMSE and the second paper's L2 index.

BROAD (Laidig et al., Data 6(7), 2021, doi:10.3390/data6070072) defines, with q_est and q_ref
both q_enu←sensor: q_err = q_est ⊗ q_ref⁻¹ (the error expressed in the earth frame), then per
sample total 2·acos|w|, heading 2·atan|z/w| and inclination 2·acos√(w² + z²); each reduced to
an RMSE in degrees over the ``movement`` samples, samples without reference (NaN) skipped. A
group's figure is the mean of its trials' RMSEs. Our estimators work in NED, so their output
is turned into ENU first (``ned_to_enu_array``).

Heading and inclination split the error rotation into a rotation about the vertical and one
about a horizontal axis; since ENU and NED share the vertical axis, the split does not depend
on which of the two the error is written in — only the reference must be in the same frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Iterable, Mapping

import numpy as np

from ahrs_service.core.quaternion import ned_to_enu_array, quat_conj_array, quat_mul_array, quat_to_rotvec_array

KINDS = ("total", "heading", "inclination")


def error_angles(q_est: np.ndarray, q_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-sample (total, heading, inclination) error in radians of two (N, 4) q_earth←body arrays.

    Both must be against the same earth frame (z vertical). NaN rows give NaN errors.
    """
    e = quat_mul_array(np.asarray(q_est, dtype=float), quat_conj_array(q_ref))
    # normalise: both inputs are unit up to rounding
    e = e / np.linalg.norm(e, axis=-1, keepdims=True)
    w, x, y, z = e[..., 0], e[..., 1], e[..., 2], e[..., 3]
    aw = np.abs(w)
    # atan2 forms of 2·acos|w| and 2·acos√(w² + z²): exact near zero error, where acos is not
    total = 2.0 * np.arctan2(np.sqrt(x * x + y * y + z * z), aw)
    with np.errstate(divide="ignore", invalid="ignore"):
        # |z/w| → ∞ as w → 0: a 180° heading error; arctan handles inf, not 0/0
        ratio = np.where(aw > 0.0, np.abs(z) / np.where(aw > 0.0, aw, 1.0), np.where(np.abs(z) > 0.0, np.inf, 0.0))
    ratio = np.where(np.isnan(w) | np.isnan(z), np.nan, ratio)
    heading = 2.0 * np.arctan(ratio)
    inclination = 2.0 * np.arctan2(np.sqrt(x * x + y * y), np.sqrt(w * w + z * z))
    return total, heading, inclination


def rmse(values: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Root mean square over the masked, non-NaN entries; NaN when none is left."""
    v = np.asarray(values, dtype=float)
    if mask is not None:
        v = v[np.asarray(mask, dtype=bool)]
    v = v[~np.isnan(v)]
    return float(np.sqrt(np.mean(v * v))) if v.size else math.nan


def l2_index(error: np.ndarray, dt: float | np.ndarray, mask: np.ndarray | None = None) -> float:
    """The second paper's performance index (its eq. 38): L2(e) = √( 1/(t − t0) ∫ |e| dt ).

    ``error`` per sample (any unit u; the index is in √u), ``dt`` the time step(s) in s. The
    integral is the rectangle sum over the masked, non-NaN samples and t − t0 the time they
    cover, so gaps in the reference do not count as zero error.
    """
    e = np.asarray(error, dtype=float)
    d = np.broadcast_to(np.asarray(dt, dtype=float), e.shape)
    keep = ~np.isnan(e)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)
    span = float(np.sum(d[keep]))
    if not span > 0.0:
        return math.nan
    return math.sqrt(float(np.sum(np.abs(e[keep]) * d[keep])) / span)


def reference_rate(q_ref: np.ndarray, rate_hz: float) -> np.ndarray:
    """Body angular rate of a reference orientation, rad/s: (N − 1, 3), row k the mean rate
    over samples k → k+1 (so it belongs to the instant k + ½), from q_k⁻¹ ⊗ q_k+1.

    ``q_ref`` (N, 4) q_earth←body in any earth frame; NaN rows give NaN rates.
    """
    q = np.asarray(q_ref, dtype=float)
    return quat_to_rotvec_array(quat_mul_array(quat_conj_array(q[:-1]), q[1:])) * rate_hz


def imu_delay(
    gyr: np.ndarray,
    q_ref: np.ndarray,
    rate_hz: float,
    movement: np.ndarray | None = None,
    *,
    max_samples: float = 5.0,
) -> float:
    """How late the IMU's samples are against the reference, in sample periods.

    Gyro sample k is compared with the reference's body rate (``reference_rate``) at the
    instant k − d, linearly interpolated; d is the delay that minimises the RMS difference
    over the ``movement`` samples, searched over ±``max_samples`` in steps of ¼ sample, then
    of 1/50 sample around the best, refined by a parabola through the best step and its
    neighbours. Positive: the IMU data lag the reference (a sensor's filter delay, or an
    offset left by the synchronisation).
    The gyro bias adds the same offset at every d, so it does not move the minimum.
    NaN when fewer than 100 samples can be compared or the reference does not move.
    """
    g = np.asarray(gyr, dtype=float)
    w_ref = reference_rate(q_ref, rate_hz)
    t_ref = np.arange(len(w_ref)) + 0.5
    k = np.arange(len(g), dtype=float)
    mask = np.ones(len(g), bool) if movement is None else np.asarray(movement, dtype=bool)
    mask = mask & np.isfinite(g).all(axis=1)

    def cost(d: float) -> float:
        w = np.stack([np.interp(k - d, t_ref, w_ref[:, j], left=np.nan, right=np.nan) for j in range(3)], axis=1)
        ok = mask & np.isfinite(w).all(axis=1)
        return float(np.mean((g[ok] - w[ok]) ** 2)) if ok.sum() >= 100 else math.nan

    # coarse steps of ¼ sample, then 1/50 sample around the best, then a parabola
    best = math.nan
    for step, half_width in ((0.25, max_samples), (0.02, 0.3)):
        centre = 0.0 if math.isnan(best) else best
        delays = centre + np.arange(-half_width, half_width + 1e-9, step)
        costs = np.array([cost(d) for d in delays])
        if np.isnan(costs).all() or np.nanmax(costs) - np.nanmin(costs) <= 1e-9 * np.nanmax(costs):
            return math.nan  # nothing to compare, or no motion that would tell one shift from another
        i = int(np.nanargmin(costs))
        best = float(delays[i])
    if 0 < i < len(delays) - 1 and np.isfinite(costs[i - 1 : i + 2]).all():
        c0, c1, c2 = costs[i - 1 : i + 2]
        curvature = c0 - 2.0 * c1 + c2
        if curvature > 0.0:
            best += step * 0.5 * (c0 - c2) / curvature
    return best


@dataclass
class TrialScore:
    """Errors of one estimator on one trial, degrees.

    total_rmse/heading_rmse are None when heading is not scored (estimator without heading or
    run without magnetometer). ``l2`` is the eq. 38 index of the scored error (total error when
    heading is scored, else inclination) in √deg; ``mean`` that error's mean in degrees (the
    third paper's "mean value").
    """

    inclination_rmse: float
    total_rmse: float | None = None
    heading_rmse: float | None = None
    l2: float = math.nan
    mean: float = math.nan
    samples: int = 0

    def get(self, kind: str) -> float | None:
        return getattr(self, f"{kind}_rmse")

    def as_dict(self) -> dict:
        return asdict(self)


def score(
    q_est_ned: np.ndarray,
    q_ref_enu: np.ndarray,
    movement: np.ndarray | None = None,
    *,
    rate_hz: float,
    with_heading: bool = True,
) -> TrialScore:
    """Scores an (N, 4) NED estimate against an (N, 4) ENU reference as BROAD does.

    ``movement`` selects the scored samples (default all); ``with_heading`` False scores the
    inclination only (total and heading become None).
    """
    q_est_ned = np.asarray(q_est_ned, dtype=float)
    q_ref_enu = np.asarray(q_ref_enu, dtype=float)
    if q_est_ned.shape != q_ref_enu.shape or q_est_ned.ndim != 2 or q_est_ned.shape[1] != 4:
        raise ValueError(f"estimate {q_est_ned.shape} and reference {q_ref_enu.shape} must both be (N, 4)")
    mask = np.ones(len(q_est_ned), bool) if movement is None else np.asarray(movement, dtype=bool)
    if mask.shape != (len(q_est_ned),):
        raise ValueError(f"movement must have shape ({len(q_est_ned)},), got {mask.shape}")
    total, heading, incl = (np.degrees(a) for a in error_angles(ned_to_enu_array(q_est_ned), q_ref_enu))
    scored = total if with_heading else incl
    valid = mask & ~np.isnan(scored)
    return TrialScore(
        inclination_rmse=rmse(incl, mask),
        total_rmse=rmse(total, mask) if with_heading else None,
        heading_rmse=rmse(heading, mask) if with_heading else None,
        l2=l2_index(scored, 1.0 / rate_hz, mask),
        mean=float(np.mean(scored[valid])) if valid.any() else math.nan,
        samples=int(valid.sum()),
    )


def group_mean(per_trial: Mapping[str, float | None], members: Iterable[str]) -> float | None:
    """A group's figure: the mean of its trials' values (None when any member has no value)."""
    values = [per_trial.get(t) for t in members]
    if not values or any(v is None for v in values):
        return None
    return float(np.mean(values))
