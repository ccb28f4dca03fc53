"""Attitude uncertainty: the roll, pitch and yaw variances an estimator reports with its attitude.

Every estimator answers ``Estimator.attitude_variance()`` with an :class:`AttitudeVariance`
(rad², NaN = unknown, as MAVLink's covariance fields define it). Where it comes from:

* **its own covariance** — the EKF (7 × 7 P) and the quaternion KF (4 × 4 P) carry a
  covariance of the quaternion; :func:`euler_variance_of_quaternion_covariance` maps it onto
  the ZYX angles with the Jacobian of the angles against the normalised quaternion
  (Σ_e = J P Jᵀ, diagonal kept). P is how well the state is known *if the model holds*; both
  models take the accelerometer for gravity alone and the field for undisturbed. The EKF adds
  floors, the sustained acceleration it follows into its tilt and, to the heading, the tilt
  error its accelerometer innovation shows (:class:`CovarianceErrorModel`); the quaternion KF adds the a-priori
  floors of :class:`ErrorModel` (:func:`with_unmodelled_floor`). The roll/pitch Kalman filter
  keeps its two variances itself (its paper's σ_ξ is large: no floor added).
* **an error model over what the filter observes** — ``robust`` (:class:`ObservedErrorModel`):
  the gyro drift its corrections have not yet removed (bias covariance, scale error times the
  tilt rate and the net angle turned, the rejection state and the time without a field), the
  sustained acceleration it follows into its tilt and the disturbance of the fields it used; TRIAD and QUEST (:class:`SnapshotErrorModel`): the linear
  acceleration and field disturbance of the sample they were solved from.
* **an a-priori error model** — the complementary filters (complementary, Mahony, Madgwick,
  Valenti, immersion and invariance): :class:`ErrorModel` gives each angle a floor σ plus the
  gyro drift integrated since the last usable correction (the header's ``acc_age`` /
  ``mag_age``, kept by the shared kernel).

The physical constants are sensor figures (each documented where defined). ``robust``, ``ekf``,
``triad`` and ``quest`` carry one scale per angle: the largest any data set needs for its
claimed 1σ share — inclination the larger of BROAD's (handheld) and DIDO's (quadrotor), heading
BROAD's (DIDO has no magnetometer) — so that no data set sees its errors under-covered and the
other is then conservative (``python -m ahrs_service.evaluation.coverage --calibrate``;
docs/autopilot.md, "Attitude covariance", gives the held-out coverage on each).
* **NaN** — heading of the estimators that do not observe it (the 6D filters: their yaw is the
  integrated gyro from an arbitrary start) and of any estimator before its first usable field
  sample; every angle before the estimator is initialised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ahrs_service.core.quaternion import euler_of

DEG = math.pi / 180.0

#: time constant of the vector mean of the accelerometer's disagreement with the estimated
#: vertical, s: what outlasts it is sustained acceleration (a vehicle's turn), which a filter
#: follows into its attitude; hand jerks, taps and vibration average out. Chosen from 0.3, 1 and
#: 3 s on BROAD and DIDO together (docs/autopilot.md "Attitude covariance")
SUSTAINED_ACCELERATION_TAU = 0.3


@dataclass(frozen=True, slots=True)
class AttitudeVariance:
    """Variances of the ZYX Euler angles of the current attitude, rad² (NaN: unknown)."""

    roll: float
    pitch: float
    yaw: float

    @classmethod
    def unknown(cls) -> "AttitudeVariance":
        return cls(math.nan, math.nan, math.nan)

    def plus(self, variance: float, yaw_variance: float | None = None) -> "AttitudeVariance":
        """These variances with ``variance`` (rad²) added to roll and pitch, and to yaw
        ``yaw_variance`` (default: ``variance``); NaN stays unknown."""
        yaw_variance = variance if yaw_variance is None else yaw_variance
        if variance <= 0.0 and yaw_variance <= 0.0:
            return self
        return AttitudeVariance(self.roll + variance, self.pitch + variance, self.yaw + yaw_variance)

    def as_dict(self) -> dict[str, float]:
        """{"roll", "pitch", "yaw"} in rad² (the log writes NaN as null)."""
        return {"roll": self.roll, "pitch": self.pitch, "yaw": self.yaw}

    def sigma_deg(self) -> tuple[float, float, float]:
        """(roll, pitch, yaw) standard deviations, degrees (NaN: unknown)."""
        return tuple(math.sqrt(v) / DEG if v >= 0 else math.nan for v in (self.roll, self.pitch, self.yaw))  # type: ignore[return-value]


@dataclass(frozen=True, slots=True)
class ErrorModel:
    """Error model of an estimator without a covariance (σ of each Euler angle):

    σ_tilt² = tilt_sigma² + (drift · t_acc)²,  σ_yaw² = heading_sigma² + (drift · t_mag)²

    with t_acc, t_mag the time since the last usable accelerometer / magnetometer sample (s).

    tilt_sigma: roll/pitch σ while the accelerometer corrects, rad. Default 2°: a vehicle's
        or hand's sustained linear acceleration of about 0.35 m/s² tilts the gravity reference
        by atan(0.35 / 9.81) = 2°.
    heading_sigma: yaw σ while the magnetometer corrects, rad. Default 5°: a field distortion
        of 4 µT across a 50 µT field turns its horizontal part by up to asin(4 / 45) = 5°.
    drift: gyro-bias residual the filter does not remove, rad/s. Default 0.2 °/s, the turn-on
        bias of a calibrated MEMS gyroscope (ICM-20948, BMI088 datasheets: ±0.5 °/s before
        calibration); integrated over the time without corrections.
    """

    tilt_sigma: float = 2.0 * DEG
    heading_sigma: float = 5.0 * DEG
    drift: float = 0.2 * DEG

    def variance(self, acc_age_s: float, mag_age_s: float, observes_heading: bool) -> AttitudeVariance:
        tilt = self.tilt_sigma**2 + (self.drift * acc_age_s) ** 2
        yaw = math.nan
        if observes_heading and math.isfinite(mag_age_s):
            yaw = self.heading_sigma**2 + (self.drift * mag_age_s) ** 2
        if not math.isfinite(tilt):
            tilt = math.nan
        return AttitudeVariance(tilt, tilt, yaw)


@dataclass(frozen=True, slots=True)
class ObservedErrorState:
    """What a filter records about the errors it has not yet corrected (``ObservedErrorModel``).

    tilt_drift, yaw_drift: gyro drift of the inclination / heading since the corrections last
        removed it, rad (accumulated from the residual bias and the scale error, shrunk by each
        correction's gain: ``robust._drift_of_the_error_model``).
    field_mean_square: mean square heading error of the fields that corrected the heading,
        rad², from their norm and dip deviations from the learned reference.
    field_norm, field_dip: the learned reference field, µT and rad.
    has_field: False before the first usable field sample (heading unknown).
    sustained_acceleration: |LP(e_h)|², the squared length of the vector mean (first-order
        low-pass, ``SUSTAINED_ACCELERATION_TAU``) of the horizontal part of each unit specific
        force in the inclination frame: the tilt sustained linear acceleration pulls the
        estimate towards, rad² for small angles (0 at rest and for zero-mean jerks).
    """

    tilt_drift: float
    yaw_drift: float
    field_mean_square: float
    field_norm: float
    field_dip: float
    has_field: bool
    sustained_acceleration: float = 0.0


@dataclass(frozen=True, slots=True)
class ObservedErrorModel:
    """Attitude variances from what the filter observes (``robust``):

    v_tilt = s_tilt² · (tilt_floor² + u_tilt² + ā²)
    v_yaw  = s_yaw² · ((field_floor / (B cos d))² + e_field² + u_yaw² + tan² d · v_tilt / s_tilt²)

    u: the uncorrected gyro drifts; ā²: the sustained acceleration's tilt
    (``ObservedErrorState.sustained_acceleration``); e_field²: mean square heading error of the used fields;
    B, d: the reference field's norm and dip. A tilt error ε turns an inclined field's
    horizontal part by up to ε tan d, which the heading filter then follows.

    tilt_floor: σ left without motion, rad: a calibrated accelerometer's residual offset of
        0.05 m/s² tilts gravity by atan(0.05 / 9.81) = 0.3°.
    field_floor: a calibrated magnetometer's residual (hard and soft iron) plus the
        building's distortion that the norm and dip tests cannot see, µT: 0.5 µT.
    tilt_scale, heading_scale: the one calibration each angle gets, the largest scale any data
        set needs for its claimed 1σ share (``python -m ahrs_service.evaluation.coverage
        --calibrate``, docs/autopilot.md "Attitude covariance"); 1.0 is the model uncalibrated.
    """

    tilt_floor: float = math.atan(0.05 / 9.81)
    field_floor: float = 0.5
    tilt_scale: float = 1.0
    heading_scale: float = 1.0

    def raw_variance(self, e: ObservedErrorState) -> tuple[float, float]:
        """(tilt, yaw) variances before the scales, rad² (yaw NaN without a field)."""
        tilt = self.tilt_floor**2 + e.tilt_drift**2 + e.sustained_acceleration
        yaw = math.nan
        horizontal = e.field_norm * math.cos(e.field_dip)
        if e.has_field and horizontal > 0.0:
            yaw = (self.field_floor / horizontal) ** 2 + e.field_mean_square + e.yaw_drift**2 + math.tan(e.field_dip) ** 2 * tilt
        return tilt, yaw

    def variance(self, e: ObservedErrorState) -> AttitudeVariance:
        """The scaled variances (NaN where unknown or not finite)."""
        tilt, yaw = self.raw_variance(e)
        tilt *= self.tilt_scale**2
        yaw *= self.heading_scale**2
        if not math.isfinite(tilt):
            tilt = math.nan
        if not math.isfinite(yaw):
            yaw = math.nan
        return AttitudeVariance(tilt, tilt, yaw)


@dataclass(frozen=True, slots=True)
class SnapshotErrorState:
    """The disturbance the newest samples of a single-sample solution (TRIAD, QUEST) show.

    linear_acceleration: √| |f|² − g² | of the newest specific force, m/s² (a horizontal
        acceleration a gives |f|² = g² + a²).
    field_norm, field_dip: the slowly learned reference field, µT and rad (0: none yet).
    field_norm_deviation, field_dip_deviation: the newest field's relative norm deviation and
        dip deviation (rad) from it.
    field_age, acc_age: time since the last usable field / accelerometer sample, s (inf: none).
    """

    linear_acceleration: float
    field_norm: float
    field_dip: float
    field_norm_deviation: float
    field_dip_deviation: float
    field_age: float
    acc_age: float


@dataclass(frozen=True, slots=True)
class SnapshotErrorModel:
    """Variances of a single-sample solution: it takes each sample's specific force for
    gravity and its field for the earth's, so its error is the disturbance of that sample:

    v_tilt = s_tilt² · (tilt_floor² + atan²(a / g) + (drift t_acc)²)
    v_yaw  = s_yaw² · ((field_floor / (B cos d))² + (Δn² + Δd²) / cos² d + tan² d · v_tilt / s_tilt² + (drift t_mag)²)

    a: the linear acceleration the sample shows; Δn, Δd: the field's relative norm and dip
    deviations, a disturbance of that size turning the horizontal field by about
    √(Δn² + Δd²) / cos d; a tilt error turns it by up to tan d times itself; drift: the
    gyro's while it carries the attitude between fixes (``ErrorModel.drift``). Floors as in
    ``ObservedErrorModel``; the scales chosen like its.
    """

    tilt_floor: float = math.atan(0.05 / 9.81)
    field_floor: float = 0.5
    drift: float = 0.2 * DEG
    tilt_scale: float = 1.0
    heading_scale: float = 1.0

    def variance(self, e: SnapshotErrorState) -> AttitudeVariance:
        tilt = self.tilt_floor**2 + math.atan(e.linear_acceleration / 9.81) ** 2 + (self.drift * e.acc_age) ** 2
        yaw = math.nan
        horizontal = e.field_norm * math.cos(e.field_dip)
        if math.isfinite(e.field_age) and horizontal > 0.0:
            c2 = math.cos(e.field_dip) ** 2
            yaw = (
                (self.field_floor / horizontal) ** 2
                + (e.field_norm_deviation**2 + e.field_dip_deviation**2) / c2
                + math.tan(e.field_dip) ** 2 * tilt
                + (self.drift * e.field_age) ** 2
            )
        tilt *= self.tilt_scale**2
        yaw *= self.heading_scale**2
        return AttitudeVariance(
            tilt if math.isfinite(tilt) else math.nan, tilt if math.isfinite(tilt) else math.nan, yaw if math.isfinite(yaw) else math.nan
        )


def with_unmodelled_floor(var: AttitudeVariance, model: ErrorModel = ErrorModel()) -> AttitudeVariance:
    """``var`` plus the model's tilt and heading floors (variances add: independent errors);
    NaN stays NaN."""
    t, h = model.tilt_sigma**2, model.heading_sigma**2
    return AttitudeVariance(var.roll + t, var.pitch + t, var.yaw + h)


@dataclass(frozen=True, slots=True)
class CovarianceErrorModel:
    """Variances of a filter with a covariance P that takes the specific force for gravity
    (``ekf``): its own J P Jᵀ plus what the model leaves out, times one scale per angle:

    v_tilt = s_tilt² · (J P Jᵀ + tilt_floor² + ā²)
    v_yaw  = s_yaw² · (J P Jᵀ + (field_floor / (B cos d))² + tan² d · ē²)

    P is how well the state is known if the specific force were gravity alone. ā² is the
    squared length of the vector mean (``SUSTAINED_ACCELERATION_TAU``) of the horizontal part
    of each unit specific force in the navigation frame: sustained linear acceleration, which
    the filter follows into its tilt (rad² for small angles). ē² is the mean square
    accelerometer innovation over the filter's own time constant (how far the measured gravity
    direction disagreed with the estimate); a tilt error turns an inclined field's horizontal
    part by up to tan d times itself, which the heading follows. ē² is *not* in the tilt: it
    counts jerks of which the filter follows little as much as sustained acceleration of which
    it follows much; across BROAD (handheld) and DIDO (quadrotor) the tilt scales they need
    differ most with ē², less with neither, and agree with ā² (figures: docs/autopilot.md
    "Attitude covariance"). The floors are ``ObservedErrorModel``'s (accelerometer offset, magnetometer
    residual), B and d the filter's reference field. tilt_scale, heading_scale: the largest
    scale any data set needs (``python -m ahrs_service.evaluation.coverage --calibrate``).
    """

    tilt_floor: float = math.atan(0.05 / 9.81)
    field_floor: float = 0.5
    tilt_scale: float = 1.0
    heading_scale: float = 1.0

    def variance(
        self, from_p: AttitudeVariance, acc_disagreement: float, field_norm: float, field_dip: float, sustained_acceleration: float = 0.0
    ) -> AttitudeVariance:
        """``from_p``: J P Jᵀ; ``acc_disagreement``: ē², rad²; ``field_norm`` (µT, 0: none
        yet) and ``field_dip`` (rad): the reference field; ``sustained_acceleration``: ā², rad².
        NaN stays NaN."""
        t, h = self.tilt_scale**2, self.heading_scale**2
        horizontal = field_norm * math.cos(field_dip)
        field = (self.field_floor / horizontal) ** 2 if horizontal > 0.0 else ErrorModel().heading_sigma ** 2
        yaw = (from_p.yaw + field + math.tan(field_dip) ** 2 * acc_disagreement) * h
        floor = self.tilt_floor**2 + sustained_acceleration
        return AttitudeVariance((from_p.roll + floor) * t, (from_p.pitch + floor) * t, yaw)


def euler_jacobian(q: np.ndarray) -> np.ndarray:
    """J = ∂(roll, pitch, yaw)/∂q (3 × 4) of the ZYX angles of q/‖q‖ at ``q`` (central
    differences; the normalisation makes the direction along q itself carry no angle)."""
    q = np.asarray(q, dtype=np.float64)
    eps = 1e-7
    jac = np.empty((3, 4))
    for k in range(4):
        d = np.zeros(4)
        d[k] = eps
        hi = np.array(euler_of(tuple((q + d) / np.linalg.norm(q + d))))
        lo = np.array(euler_of(tuple((q - d) / np.linalg.norm(q - d))))
        diff = hi - lo
        diff = (diff + math.pi) % (2.0 * math.pi) - math.pi  # yaw across ±π
        jac[:, k] = diff / (2.0 * eps)
    return jac


def euler_variance_of_quaternion_covariance(q: np.ndarray, p: np.ndarray, observes_heading: bool = True) -> AttitudeVariance:
    """Roll, pitch, yaw variances (rad²) of an attitude q [w, x, y, z] whose quaternion
    covariance is ``p`` (4 × 4): the diagonal of J P Jᵀ. Yaw is NaN unless observed."""
    jac = euler_jacobian(q)
    cov = jac @ np.asarray(p, dtype=np.float64) @ jac.T
    roll, pitch, yaw = (float(cov[i, i]) for i in range(3))
    return AttitudeVariance(roll, pitch, yaw if observes_heading else math.nan)
