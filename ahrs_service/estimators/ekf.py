"""Quaternion extended Kalman filter with gyro bias, after Watson (2013), as in the third paper.

State x = [q0 q1 q2 q3 b_x b_y b_z] (eq. 12): q_earth←body and the gyroscope bias (rad/s,
body frame), kept in the common state header (q in 0..3, bias in the BIAS slots). Equation
numbers refer to the third source paper (eq. 10–29, annex 1).

* Prediction (eq. 13–16, 20–21): q ← q + Δt · ½ q ⊗ (0, ω − b), normalised; the bias is
  constant. F = ∂f/∂x is written for our q_earth←body product (the paper's listing uses the
  inverse quaternion's ordering). Q comes from the gyroscope noise propagated through the
  quaternion kinematics, (Δt/2)² σ_g² Ξ(q) Ξ(q)ᵀ, and a bias random walk σ_b² Δt, so it scales
  with each sample's real Δt.
* Accelerometer update (eq. 17–18, 22–26): the normalised specific force is predicted as
  R(q)ᵀ (0, 0, −1) — "up" in the body frame, since at rest the sensor reads −g in NED.
* Magnetometer update (eq. 19): as in Watson's listing, the earth reference b = (b_x, 0, b_z)
  is built from the measured field rotated into the earth frame, so only its heading is
  unknown: the innovation, seen in the earth frame, is horizontal. But the unconstrained gain
  still turns part of it into roll/pitch changes (a rotation about north moves an inclined
  field's east component too), which is how a magnet near the sensor tilts Watson's filter.
  Here the gain is projected so that the magnetometer corrects only the rotation about earth
  down: its quaternion part onto the tangent (0, 0, 0, 1) ⊗ q, its bias part onto the body
  vertical. The covariance then follows the Joseph form, valid for any gain. A disturbed
  field can at most turn heading, never inclination (same principle as Valenti's filter).

A magnet near the sensor also changes the field's magnitude and dip; samples whose magnitude
or dip depart from a slowly learned reference are not used (``mag_gate``, the project's
addition: on BROAD's magnet trials it keeps heading from the gyro instead of the magnet).

The updates run one after the other (accelerometer, then magnetometer), each with a 3 × 3
innovation covariance inverted in closed form; all matrices live in scratch space inside the
state array, so a step allocates nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_normalize, quat_rotate, quat_rotate_inv
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable
from ahrs_service.estimators.uncertainty import (
    SUSTAINED_ACCELERATION_TAU,
    AttitudeVariance,
    CovarianceErrorModel,
    euler_variance_of_quaternion_covariance,
)

N = 7  # state dimension: quaternion (4) + gyro bias (3)
# layout after the common header: covariance, then scratch (contents meaningless between steps)
STATE = Layout(
    "ekf state",
    [
        Slot("p", N * N, "P, 7 × 7, row-major"),
        Slot("fq", 4 * N, "top four rows of F (the bias rows are identity), 4 × 7"),
        Slot("m", N * N, "F·P, 7 × 7"),
        Slot("pht", N * 3, "P·Hᵀ, 7 × 3"),
        Slot("kg", N * 3, "Kalman gain, 7 × 3"),
        Slot("hq", 3 * 4, "H's quaternion columns (bias columns are zero), 3 × 4"),
        *K.MAG_REFERENCE_SLOTS,  # the magnetic-disturbance gate's reference (K.mag_gate_accepts)
        Slot("acc_innov2", 1, "mean square accelerometer innovation |f/|f| − h_a|² over the filter's time constant (error model)"),
        Slot("acc_sustained", 2, "vector mean of the unit specific force's north and east parts, NED (error model)"),
    ],
    start=K.HEADER,
)
P0, FQ, M, PHT, KG, HQ, MAG_NORM_REF, MAG_DIP_REF, ACC_INNOV2, ACC_SUSTAINED = STATE.index
STATE_SIZE = STATE.end


@dataclass
class QuaternionEKFParams:
    """Tuning of :class:`QuaternionEKF` (the paper leaves Q and R to the user).

    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``. The paper gives no Q
    or R: ``paper`` holds the values used before tuning, with the gate off.

    gyro_noise: gyroscope white noise σ_g, rad/s (sets Q of the quaternion).
    bias_noise: bias random walk σ_b, rad/s/√s (sets Q of the bias).
    acc_noise: σ of the normalised specific-force direction (R of the accelerometer,
        dimensionless); it also has to cover linear acceleration.
    mag_noise: σ of the normalised magnetic-field direction (R of the magnetometer).
    init_attitude_std: initial σ of each quaternion component (P0).
    init_bias_std: initial σ of each bias component, rad/s (P0).
    mag_gate: magnetometer disturbance gate (not in the paper): a field sample is not used
        when |‖m‖/m_ref − 1| + |sin δ − sin δ_ref| exceeds it, with δ the field's dip below
        the horizon and the references following accepted samples with a 10 s time
        constant. Before tuning 0.1: the gate cuts BROAD's mean total error by about a third;
        a tighter gate scores about the same but leaves little room for magnetometer noise
        (figures: docs/estimators-paper1-3.md, "Why the defaults: measured figures"). 1e9
        turns it off.
    """

    # paper: Q and R left to the user (the values used before tuning), no gate (1e9)
    gyro_noise: float = tunable(0.01307412846488109, paper=0.01, search=SearchRange(1e-3, 0.3, log=True))  # rad/s
    bias_noise: float = tunable(8.51543990786931e-05, paper=1e-5, search=SearchRange(1e-7, 1e-3, log=True))  # rad/s/√s
    acc_noise: float = tunable(0.15957174291329135, paper=0.2, search=SearchRange(0.02, 2.0, log=True))
    mag_noise: float = tunable(0.30724152088240236, paper=0.3, search=SearchRange(0.05, 5.0, log=True))
    init_attitude_std: float = tunable(0.01, paper=0.01)
    init_bias_std: float = tunable(0.01, paper=0.01)  # rad/s
    mag_gate: float = tunable(0.061570629232089474, paper=1e9, search=SearchRange(0.02, 1.0, log=True))

    def __post_init__(self) -> None:
        for name in ("gyro_noise", "acc_noise", "mag_noise", "init_attitude_std", "mag_gate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("bias_noise", "init_bias_std"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


_inline = njit(cache=True, inline="always")


@_inline
def _predict(s, gx, gy, gz, dt, gyro_noise, bias_noise):
    q0, q1, q2, q3 = s[0], s[1], s[2], s[3]
    wx, wy, wz = gx - s[K.BIAS], gy - s[K.BIAS + 1], gz - s[K.BIAS + 2]
    h = 0.5 * dt
    # eq. 13–15: q + Δt · ½ q ⊗ (0, ω − b)
    K.store_quat(
        s,
        quat_normalize(
            (
                q0 + h * (-q1 * wx - q2 * wy - q3 * wz),
                q1 + h * (q0 * wx - q3 * wy + q2 * wz),
                q2 + h * (q3 * wx + q0 * wy - q1 * wz),
                q3 + h * (-q2 * wx + q1 * wy + q0 * wz),
            )
        ),
    )
    # eq. 16: F = ∂f/∂x; quaternion rows [I + h Ω(ω − b) | −h Ξ(q)], bias rows identity
    f = s[FQ : FQ + 4 * N]
    f[0:7] = (1.0, -h * wx, -h * wy, -h * wz, h * q1, h * q2, h * q3)
    f[7:14] = (h * wx, 1.0, h * wz, -h * wy, -h * q0, h * q3, -h * q2)
    f[14:21] = (h * wy, -h * wz, 1.0, h * wx, -h * q3, -h * q0, h * q1)
    f[21:28] = (h * wz, h * wy, -h * wx, 1.0, h * q2, -h * q1, -h * q0)

    # eq. 21: P ← F P Fᵀ + Q, using F's identity bias rows
    p = s[P0 : P0 + N * N]
    m = s[M : M + N * N]
    for i in range(4):
        for j in range(N):
            acc = 0.0
            for k in range(N):
                acc += f[i * N + k] * p[k * N + j]
            m[i * N + j] = acc
    for i in range(4, N):
        for j in range(N):
            m[i * N + j] = p[i * N + j]
    # P' = M Fᵀ is symmetric: fill the quaternion rows, mirror into the bias rows
    for i in range(4):
        for j in range(i, 4):
            acc = 0.0
            for k in range(N):
                acc += m[i * N + k] * f[j * N + k]
            p[i * N + j] = acc
            p[j * N + i] = acc
        for j in range(4, N):
            p[i * N + j] = m[i * N + j]
            p[j * N + i] = m[i * N + j]
    for i in range(4, N):
        for j in range(4, N):
            p[i * N + j] = m[i * N + j]
    # Q: gyro noise through the kinematics, (h σ_g)² Ξ Ξᵀ, and the bias random walk
    gq = (h * gyro_noise) ** 2
    xi = (
        (-q1, -q2, -q3),
        (q0, -q3, q2),
        (q3, q0, -q1),
        (-q2, q1, q0),
    )
    for i in range(4):
        for j in range(4):
            p[i * N + j] += gq * (xi[i][0] * xi[j][0] + xi[i][1] * xi[j][1] + xi[i][2] * xi[j][2])
    bq = bias_noise * bias_noise * dt
    for i in range(4, N):
        p[i * N + i] += bq


@_inline
def _gain(s, r):
    """P Hᵀ and K = P Hᵀ S⁻¹ for the 3-row H in scratch (eq. 23–24); returns S."""
    p = s[P0 : P0 + N * N]
    hq = s[HQ : HQ + 12]
    pht = s[PHT : PHT + N * 3]
    kg = s[KG : KG + N * 3]
    for i in range(N):
        for j in range(3):
            acc = 0.0
            for k in range(4):
                acc += p[i * N + k] * hq[j * 4 + k]
            pht[i * 3 + j] = acc
    # S = H P Hᵀ + R, symmetric 3 × 3
    s00 = s01 = s02 = s11 = s12 = s22 = 0.0
    for k in range(4):
        s00 += hq[k] * pht[k * 3]
        s01 += hq[k] * pht[k * 3 + 1]
        s02 += hq[k] * pht[k * 3 + 2]
        s11 += hq[4 + k] * pht[k * 3 + 1]
        s12 += hq[4 + k] * pht[k * 3 + 2]
        s22 += hq[8 + k] * pht[k * 3 + 2]
    s00 += r
    s11 += r
    s22 += r
    # closed-form inverse of the symmetric S
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    if not (abs(det) > 1e-300) or not math.isfinite(det):
        return False, (s00, s01, s02, s11, s12, s22)
    inv = 1.0 / det
    i00, i01, i02, i11, i12, i22 = c00 * inv, c01 * inv, c02 * inv, c11 * inv, c12 * inv, c22 * inv
    for i in range(N):
        a, b, c = pht[i * 3], pht[i * 3 + 1], pht[i * 3 + 2]
        kg[i * 3] = a * i00 + b * i01 + c * i02
        kg[i * 3 + 1] = a * i01 + b * i11 + c * i12
        kg[i * 3 + 2] = a * i02 + b * i12 + c * i22
    return True, (s00, s01, s02, s11, s12, s22)


@_inline
def _hold_bias_after_gap(s):
    """While a gap's error is corrected (``_kernel.recovering``) the bias rows of K are 0: the
    bias is a consider state (Schmidt), its estimate and covariance stay as they are and the
    update's P formulas keep the cross-covariance right. The gap's error is a step, not a
    drift: the innovation it makes must not become a bias."""
    if K.recovering(s):
        for i in range(4 * 3, N * 3):
            s[KG + i] = 0.0


@_inline
def _apply(s, y0, y1, y2):
    """x ← x + K y (eq. 25), then unit quaternion."""
    kg = s[KG : KG + N * 3]
    q = (
        s[0] + kg[0] * y0 + kg[1] * y1 + kg[2] * y2,
        s[1] + kg[3] * y0 + kg[4] * y1 + kg[5] * y2,
        s[2] + kg[6] * y0 + kg[7] * y1 + kg[8] * y2,
        s[3] + kg[9] * y0 + kg[10] * y1 + kg[11] * y2,
    )
    for i in range(3):
        s[K.BIAS + i] += kg[(4 + i) * 3] * y0 + kg[(4 + i) * 3 + 1] * y1 + kg[(4 + i) * 3 + 2] * y2
    K.store_quat(s, quat_normalize(q))


@_inline
def _accelerometer_update(s, x, acc_noise, gyro_noise):
    q0, q1, q2, q3 = s[0], s[1], s[2], s[3]
    na = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    # eq. 18 (NED, specific force): h_a = R(q)ᵀ (0, 0, −1), minus R's third row
    h0 = -2.0 * (q1 * q3 - q0 * q2)
    h1 = -2.0 * (q2 * q3 + q0 * q1)
    h2 = -(q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3)
    # error model (attitude_variance): the innovation's mean square over the time constant with
    # which the filter follows the accelerometer, τ = acc_noise / gyro_noise (steady-state gain
    # σ_g Δt / σ_a per sample); the model takes the specific force for gravity, so this is the
    # disagreement that linear acceleration leaves and P does not know about
    e2 = (x[3] / na - h0) ** 2 + (x[4] / na - h1) ** 2 + (x[5] / na - h2) ** 2
    if gyro_noise > 0.0:
        s[ACC_INNOV2] += min(1.0, x[K.DT] * gyro_noise / acc_noise) * (e2 - s[ACC_INNOV2])
    # and the vector mean of the unit specific force's horizontal part in NED (rows 1–2 of
    # R(q)) over SUSTAINED_ACCELERATION_TAU: sustained acceleration, which the filter follows
    k_s = min(1.0, x[K.DT] / SUSTAINED_ACCELERATION_TAU)
    fn = (1.0 - 2.0 * (q2 * q2 + q3 * q3)) * x[3] + 2.0 * (q1 * q2 - q0 * q3) * x[4] + 2.0 * (q1 * q3 + q0 * q2) * x[5]
    fe = 2.0 * (q1 * q2 + q0 * q3) * x[3] + (1.0 - 2.0 * (q1 * q1 + q3 * q3)) * x[4] + 2.0 * (q2 * q3 - q0 * q1) * x[5]
    s[ACC_SUSTAINED] += k_s * (fn / na - s[ACC_SUSTAINED])
    s[ACC_SUSTAINED + 1] += k_s * (fe / na - s[ACC_SUSTAINED + 1])
    hq = s[HQ : HQ + 12]
    hq[0:4] = (2.0 * q2, -2.0 * q3, 2.0 * q0, -2.0 * q1)
    hq[4:8] = (-2.0 * q1, -2.0 * q0, -2.0 * q3, -2.0 * q2)
    hq[8:12] = (-2.0 * q0, 2.0 * q1, 2.0 * q2, -2.0 * q3)
    ok, _ = _gain(s, acc_noise * acc_noise)
    if not ok:
        return
    _hold_bias_after_gap(s)
    # eq. 26: P ← (I − K H) P = P − K (P Hᵀ)ᵀ, symmetric for the optimal gain
    p = s[P0 : P0 + N * N]
    kg = s[KG : KG + N * 3]
    pht = s[PHT : PHT + N * 3]
    for i in range(N):
        for j in range(i, N):
            v = p[i * N + j] - (kg[i * 3] * pht[j * 3] + kg[i * 3 + 1] * pht[j * 3 + 1] + kg[i * 3 + 2] * pht[j * 3 + 2])
            p[i * N + j] = v
            p[j * N + i] = v
    # eq. 22, 25
    _apply(s, x[3] / na - h0, x[4] / na - h1, x[5] / na - h2)


@_inline
def _magnetometer_update(s, x, mag_noise, mag_gate, dt):
    q = (s[0], s[1], s[2], s[3])
    q0, q1, q2, q3 = q
    nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
    mx, my, mz = x[6] / nm, x[7] / nm, x[8] / nm
    # reference field (b_x, 0, b_z) from the measurement seen in the earth frame
    lx, ly, lz = quat_rotate(q, (mx, my, mz))
    # disturbance gate: a field whose magnitude or dip departs from the reference is not earth's
    if not K.mag_gate_accepts(s, MAG_NORM_REF, nm, lz, mag_gate, dt):
        return
    bx = math.sqrt(lx * lx + ly * ly)
    bz = lz
    if bx < 1e-6:
        return  # field along the vertical: no heading information
    # eq. 19: h_m = R(q)ᵀ b and its Jacobian
    h0 = bx * (q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3) + 2.0 * bz * (q1 * q3 - q0 * q2)
    h1 = 2.0 * bx * (q1 * q2 - q0 * q3) + 2.0 * bz * (q2 * q3 + q0 * q1)
    h2 = 2.0 * bx * (q1 * q3 + q0 * q2) + bz * (q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3)
    hq = s[HQ : HQ + 12]
    hq[0:4] = (2.0 * (bx * q0 - bz * q2), 2.0 * (bx * q1 + bz * q3), 2.0 * (-bx * q2 - bz * q0), 2.0 * (-bx * q3 + bz * q1))
    hq[4:8] = (2.0 * (-bx * q3 + bz * q1), 2.0 * (bx * q2 + bz * q0), 2.0 * (bx * q1 + bz * q3), 2.0 * (-bx * q0 + bz * q2))
    hq[8:12] = (2.0 * (bx * q2 + bz * q0), 2.0 * (bx * q3 - bz * q1), 2.0 * (bx * q0 - bz * q2), 2.0 * (bx * q1 + bz * q3))
    ok, sm = _gain(s, mag_noise * mag_noise)
    if not ok:
        return
    kg = s[KG : KG + N * 3]
    # heading-only gain: quaternion rows onto t = (0, 0, 0, 1) ⊗ q (rotation about earth down),
    # bias rows onto the body vertical d = R(q)ᵀ (0, 0, 1)
    t = (-q3, -q2, q1, q0)
    d = quat_rotate_inv((q0, q1, q2, q3), (0.0, 0.0, 1.0))
    for j in range(3):
        a = t[0] * kg[j] + t[1] * kg[3 + j] + t[2] * kg[6 + j] + t[3] * kg[9 + j]
        for i in range(4):
            kg[i * 3 + j] = t[i] * a
        c = d[0] * kg[12 + j] + d[1] * kg[15 + j] + d[2] * kg[18 + j]
        for i in range(3):
            kg[(4 + i) * 3 + j] = d[i] * c
    _hold_bias_after_gap(s)
    # Joseph form for a non-optimal gain: P ← P − K (PHᵀ)ᵀ − (PHᵀ) Kᵀ + K S Kᵀ
    p = s[P0 : P0 + N * N]
    pht = s[PHT : PHT + N * 3]
    s00, s01, s02, s11, s12, s22 = sm
    for i in range(N):
        k0, k1, k2 = kg[i * 3], kg[i * 3 + 1], kg[i * 3 + 2]
        ks0 = k0 * s00 + k1 * s01 + k2 * s02
        ks1 = k0 * s01 + k1 * s11 + k2 * s12
        ks2 = k0 * s02 + k1 * s12 + k2 * s22
        for j in range(i, N):
            v = p[i * N + j] + (
                -(k0 * pht[j * 3] + k1 * pht[j * 3 + 1] + k2 * pht[j * 3 + 2])
                - (pht[i * 3] * kg[j * 3] + pht[i * 3 + 1] * kg[j * 3 + 1] + pht[i * 3 + 2] * kg[j * 3 + 2])
                + ks0 * kg[j * 3] + ks1 * kg[j * 3 + 1] + ks2 * kg[j * 3 + 2]
            )
            p[i * N + j] = v
            p[j * N + i] = v
    _apply(s, mx - h0, my - h1, mz - h2)


_P = param_index(QuaternionEKFParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def ekf_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _ekf_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _ekf_update(s, p, x)


@njit(cache=True)
def _ekf_update(s, p, x):
    gyro_noise, bias_noise, acc_noise, mag_noise = p[_P.gyro_noise], p[_P.bias_noise], p[_P.acc_noise], p[_P.mag_noise]
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok) or not gyro_ok:
        return
    _predict(s, x[0], x[1], x[2], x[K.DT], gyro_noise, bias_noise)
    if acc_ok:
        _accelerometer_update(s, x, acc_noise, gyro_noise)
    if mag_ok:
        _magnetometer_update(s, x, mag_noise, p[_P.mag_gate], x[K.DT])


@njit(cache=True)
def ekf_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        ekf_step(s, p, rows[i])
        out[i] = s[:4]


class QuaternionEKF(Estimator):
    """Quaternion EKF with gyro-bias states; magnetometer restricted to heading."""

    name = "ekf"
    Params = QuaternionEKFParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(ekf_step)
    batch = staticmethod(ekf_batch)

    def initial_state(self) -> np.ndarray:
        """Identity attitude, zero bias, P0 = diag(σ_q² · 4, σ_b² · 3)."""
        s = super().initial_state()
        p = s[P0 : P0 + N * N].reshape(N, N)
        p[np.arange(4), np.arange(4)] = self.params.init_attitude_std**2
        p[np.arange(4, N), np.arange(4, N)] = self.params.init_bias_std**2
        return s

    #: P plus the floors, scaled (``uncertainty.CovarianceErrorModel``); the scales: the
    #: largest either data set needs (inclination: BROAD or DIDO, which binds; heading: BROAD),
    #: docs/autopilot.md "Attitude covariance"
    observed_error_model: ClassVar[CovarianceErrorModel] = CovarianceErrorModel(tilt_scale=0.21, heading_scale=0.067)

    def _model_variance(self) -> AttitudeVariance:
        """Roll, pitch, yaw variances (rad²) from the quaternion block of P (J P_qq Jᵀ), plus
        what the model leaves out, scaled (``uncertainty.CovarianceErrorModel``); yaw NaN
        until the first usable field sample."""
        s = self.state
        if not s[K.INITIALISED]:
            return AttitudeVariance.unknown()
        p = s[STATE.slices.p].reshape(N, N)[:4, :4]
        sin_dip = float(s[MAG_DIP_REF])
        var = self.observed_error_model.variance(
            euler_variance_of_quaternion_covariance(s[K.HEADER_SLICES.q], p),
            acc_disagreement=float(s[ACC_INNOV2]),
            sustained_acceleration=float(s[ACC_SUSTAINED] ** 2 + s[ACC_SUSTAINED + 1] ** 2),
            field_norm=float(s[MAG_NORM_REF]),
            field_dip=math.asin(max(-1.0, min(1.0, sin_dip))),
        )
        if s[K.MAG_AGE] < 0.0:  # K.NO_SAMPLE_YET: no field yet, the heading is the start's guess
            return AttitudeVariance(var.roll, var.pitch, math.nan)
        return var
