"""Linear quaternion Kalman filter fed by QUEST.

Second source paper, eq. 25–26 and Algorithm 1 (after Yun and Bachmann, 2006). The state is
the quaternion itself, x = [η, ε₁, ε₂, ε₃]; the gyro rates are time-varying parameters of the
transition matrix A = I + (h/2) Ω(p, q, r) (eq. 25, the discretised q̇ = ½ q ⊗ Ω of eq. 9),
with process noise h ζ; the measurement is the QUEST quaternion of the same sample, y = x + ξ
(eq. 26, C = I₄).

Details the paper leaves open:

* QUEST returns q or −q; the measurement is taken with the sign nearer the prediction;
* the state is renormalised after each update (the covariance is kept as is);
* without a usable magnetometer sample the measurement is the prediction tilted onto gravity
  (the gravity-only correction of :mod:`triad`): inclination is observed, yaw is not;
* without a usable accelerometer sample only the prediction runs;
* the earth-field dip is learned from the first usable sample, as in :mod:`quest`.

Three variants, each off in ``preset="paper"``:

* Heading-only field (``mag_heading_only = 1``, the default): the measurement is the factored
  quaternion of the authors' later work (X. Yun, E.R. Bachmann, R.B. McGhee, "A Simplified
  Quaternion-Based Algorithm for Orientation Estimation From Earth Gravity and Magnetic Field
  Measurements", IEEE Trans. Instrumentation and Measurement 57(3), 2008): tilt from gravity
  alone, heading from the field's part perpendicular to it, so a disturbed field turns the
  measurement about the vertical only, where QUEST's weighted fit lets it tilt the estimate.
  QUEST's weights then play no part. 0 is the paper's QUEST measurement.
* A magnetic-disturbance gate (the project's, as the EKF's ``mag_gate``): a field sample whose
  magnitude or dip departs from a reference the filter learns from the accepted samples
  (``_kernel.mag_gate_accepts``) is measured as a sample without a magnetometer (gravity only).
* Gyro-bias estimation (the project's; the paper's four states have no bias): while the sensor
  is in a steady state the bias follows the gyro by a low-pass filter, as in Valenti's own
  implementation of his filter (``_kernel.rest_bias_update``), and eq. 25's A is built from
  the rates less the bias. ``bias_rate = 0`` (the paper) estimates no bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_from_down_and_field, quat_normalize, quat_rotate
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable
from ahrs_service.estimators.quest import DIP, learn_dip, quest_quat
from ahrs_service.estimators.quest import STATE as QUEST_STATE
from ahrs_service.estimators.triad import align_down, down_direction
from ahrs_service.estimators.uncertainty import (
    AttitudeVariance,
    euler_variance_of_quaternion_covariance,
    with_unmodelled_floor,
)

# after QUEST's learned dip (the start-up is QUEST's)
STATE = Layout(
    "quaternion_kf state",
    [
        Slot("p", 16, "4×4 covariance, row-major"),
        Slot("g", 16, "4×4 work area: the Kalman gain"),
        Slot("l", 16, "4×4 work area: A P, then the Cholesky factor of C P Cᵀ + R"),
        *K.MAG_REFERENCE_SLOTS,  # the magnetic-disturbance gate's reference (K.mag_gate_accepts)
        *K.REST_BIAS_SLOTS,  # the steady-state test of the bias estimate (K.rest_bias_update)
    ],
    start=QUEST_STATE.end,
)
P, G, L = STATE.index.p, STATE.index.g, STATE.index.l
MAG_REF, GYR_PREV = STATE.index.mag_norm_ref, STATE.index.gyr_prev
STATE_SIZE = STATE.end


@dataclass
class QuaternionKFParams:
    """Tuning of :class:`QuaternionKF`.

    sigma_zeta: process noise σ_ζ of eq. 25, 1/s (quaternion rate). Paper: 0.1.
    sigma_xi: measurement noise σ_ξ of eq. 26 on each QUEST quaternion component. Paper: 0.1.
    p0: initial variance of each quaternion component (P₀ = p0 I₄). Paper: 1.
    w_acc, w_mag: QUEST weights ρ₁, ρ₂ (eq. 17). Paper: 2 and 2. Not used by the heading-only
        measurement (``mag_heading_only = 1``), so not tuned.
    acc_gate: not in the paper (as the complementary filter's gate): no measurement update
        from a sample whose specific-force magnitude is off g by more than acc_gate·g;
        1e9 (the paper) never gates.
    mag_heading_only: 1 (default) measures the factored quaternion of Yun, Bachmann and
        McGhee 2008 (tilt from gravity, the field sets heading only); 0 is the paper's QUEST
        measurement (paper 0).
    mag_gate: not in the paper: a field sample is measured as one without a magnetometer when
        |‖m‖/m_ref − 1| + |sin δ − sin δ_ref| exceeds it, δ the field's dip below the horizon,
        the references learned from the accepted samples with a 10 s time constant (as the
        EKF's gate; 1e9, the paper, accepts every sample).
    bias_rate: not in the paper: the rate, 1/s, at which the gyro-bias estimate follows the gyro
        while the sensor rests (per sample 1 − exp(−bias_rate·Δt); 0, the paper, no bias).
    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``.
    """

    # QUEST's weights act through their ratio, and the default's factored measurement does not
    # use them: neither is searched
    sigma_zeta: float = tunable(0.0011432187444296177, paper=0.1, search=SearchRange(1e-4, 1.0, log=True))  # 1/s
    sigma_xi: float = tunable(0.008439127971800171, paper=0.1, search=SearchRange(1e-3, 10.0, log=True))
    p0: float = tunable(1.0, paper=1.0)
    w_acc: float = tunable(2.0, paper=2.0)
    w_mag: float = tunable(2.0, paper=2.0)
    acc_gate: float = tunable(0.024454684271719325, paper=1e9, search=SearchRange(0.02, 1.0, log=True))
    mag_heading_only: float = tunable(1.0, paper=0.0)  # 1: Yun et al. 2008's factored measurement; 0: QUEST
    # not in the paper (as the EKF's mag_gate); 1e9 (the paper) never gates
    mag_gate: float = tunable(0.036314005607871847, paper=1e9, search=SearchRange(0.02, 1.0, log=True))
    # not in the paper (Valenti's implementation's steady-state bias); 0 (the paper): no bias
    bias_rate: float = tunable(0.13921086271929187, paper=0.0, search=SearchRange(1e-3, 10.0, log=True))  # 1/s

    def __post_init__(self) -> None:
        for key in ("sigma_zeta", "p0", "bias_rate"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{key} must be >= 0, got {getattr(self, key)}")
        for key in ("sigma_xi", "w_acc", "w_mag"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
        for key in ("acc_gate", "mag_gate"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
        if self.mag_heading_only not in (0.0, 1.0):
            raise ValueError(
                f"mag_heading_only must be 0 (QUEST, the paper's) or 1 (factored, heading only), got {self.mag_heading_only}"
            )


_P = param_index(QuaternionKFParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def quaternion_kf_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _quaternion_kf_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _quaternion_kf_update(s, p, x)


@njit(cache=True)
def _quaternion_kf_update(s, p, x):
    sigma_zeta, sigma_xi, w_acc, w_mag = p[_P.sigma_zeta], p[_P.sigma_xi], p[_P.w_acc], p[_P.w_mag]
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if s[DIP] == 0.0 and s[DIP + 1] == 0.0 and acc_ok and mag_ok:
        learn_dip(s, x)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok):
        return
    q0, q1, q2, q3 = K.load_quat(s)
    if gyro_ok:
        h = x[K.DT]
        if p[_P.bias_rate] > 0.0:  # not in the paper: the steady-state bias estimate
            K.rest_bias_update(s, GYR_PREV, x, 1.0 - math.exp(-p[_P.bias_rate] * h))
        a = 0.5 * h
        wp, wq, wr = a * (x[0] - s[K.BIAS]), a * (x[1] - s[K.BIAS + 1]), a * (x[2] - s[K.BIAS + 2])
        # eq. 25: A = I + (h/2) Ω, rows [1 −p −q −r; p 1 r −q; q −r 1 p; r q −p 1]
        A = (
            (1.0, -wp, -wq, -wr),
            (wp, 1.0, wr, -wq),
            (wq, -wr, 1.0, wp),
            (wr, wq, -wp, 1.0),
        )
        xs = (q0, q1, q2, q3)
        # Algorithm 1 line 3: x ← A x (no input term)
        q0 = A[0][0] * xs[0] + A[0][1] * xs[1] + A[0][2] * xs[2] + A[0][3] * xs[3]
        q1 = A[1][0] * xs[0] + A[1][1] * xs[1] + A[1][2] * xs[2] + A[1][3] * xs[3]
        q2 = A[2][0] * xs[0] + A[2][1] * xs[1] + A[2][2] * xs[2] + A[2][3] * xs[3]
        q3 = A[3][0] * xs[0] + A[3][1] * xs[1] + A[3][2] * xs[2] + A[3][3] * xs[3]
        # Algorithm 1 line 2: P ← A P Aᵀ + H Q Hᵀ, H = h I, Q = σ_ζ² I
        for i in range(4):
            for j in range(4):
                s[L + 4 * i + j] = (
                    A[i][0] * s[P + j] + A[i][1] * s[P + 4 + j] + A[i][2] * s[P + 8 + j] + A[i][3] * s[P + 12 + j]
                )
        qn = h * h * sigma_zeta * sigma_zeta
        for i in range(4):
            for j in range(4):
                v = s[L + 4 * i] * A[j][0] + s[L + 4 * i + 1] * A[j][1] + s[L + 4 * i + 2] * A[j][2]
                v += s[L + 4 * i + 3] * A[j][3]
                s[P + 4 * i + j] = v + (qn if i == j else 0.0)
    fn = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    # the gate (not the paper's): a specific force far from g is mostly linear acceleration
    if acc_ok and abs(fn - K.GRAVITY) <= p[_P.acc_gate] * K.GRAVITY:
        pred = quat_normalize((q0, q1, q2, q3))
        d = down_direction(x)
        ok = False
        if mag_ok:
            # the gate (not the paper's): a field whose magnitude or dip left the learned ones is a magnet's
            nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
            dip = quat_rotate(pred, (x[6] / nm, x[7] / nm, x[8] / nm))[2]
            mag_ok = K.mag_gate_accepts(s, MAG_REF, nm, dip, p[_P.mag_gate], x[K.DT])
        if mag_ok and p[_P.mag_heading_only] != 0.0:
            # Yun et al. 2008 (factored quaternion): tilt from gravity, heading from the field
            y, ok = quat_from_down_and_field(d, (x[6], x[7], x[8]))
        elif mag_ok:  # the dip is known: learn_dip ran above
            y, ok = quest_quat(d, (x[6], x[7], x[8]), (s[DIP], 0.0, s[DIP + 1]), w_acc, w_mag)
        if not ok:
            y = align_down(pred, d)
        # QUEST's q and −q are one attitude: take the sign nearer the prediction
        if y[0] * q0 + y[1] * q1 + y[2] * q2 + y[3] * q3 < 0.0:
            y = (-y[0], -y[1], -y[2], -y[3])
        # Algorithm 1 line 4, C = I: G = P (P + R)⁻¹; P and P + R commute, so G = (P + R)⁻¹ P,
        # solved with the Cholesky factor of P + R
        r = sigma_xi * sigma_xi
        for i in range(4):
            for j in range(i + 1):
                v = s[P + 4 * i + j] + (r if i == j else 0.0)
                for k in range(j):
                    v -= s[L + 4 * i + k] * s[L + 4 * j + k]
                if i == j:
                    s[L + 4 * i + i] = math.sqrt(max(v, 1e-300))
                else:
                    s[L + 4 * i + j] = v / s[L + 4 * j + j]
        for c in range(4):
            for i in range(4):  # forward: L z = P[:, c]
                v = s[P + 4 * i + c]
                for k in range(i):
                    v -= s[L + 4 * i + k] * s[G + 4 * k + c]
                s[G + 4 * i + c] = v / s[L + 4 * i + i]
            for i in range(3, -1, -1):  # backward: Lᵀ g = z
                v = s[G + 4 * i + c]
                for k in range(i + 1, 4):
                    v -= s[L + 4 * k + i] * s[G + 4 * k + c]
                s[G + 4 * i + c] = v / s[L + 4 * i + i]
        # line 6: x ← x + G (y − C x)
        e0, e1, e2, e3 = y[0] - q0, y[1] - q1, y[2] - q2, y[3] - q3
        n0 = q0 + s[G] * e0 + s[G + 1] * e1 + s[G + 2] * e2 + s[G + 3] * e3
        n1 = q1 + s[G + 4] * e0 + s[G + 5] * e1 + s[G + 6] * e2 + s[G + 7] * e3
        n2 = q2 + s[G + 8] * e0 + s[G + 9] * e1 + s[G + 10] * e2 + s[G + 11] * e3
        n3 = q3 + s[G + 12] * e0 + s[G + 13] * e1 + s[G + 14] * e2 + s[G + 15] * e3
        q0, q1, q2, q3 = n0, n1, n2, n3
        # line 5: P ← (I − G C) P, written as P − G P into the work area, then symmetrised
        for i in range(4):
            for j in range(4):
                v = s[P + 4 * i + j]
                for k in range(4):
                    v -= s[G + 4 * i + k] * s[P + 4 * k + j]
                s[L + 4 * i + j] = v
        for i in range(4):
            for j in range(4):
                s[P + 4 * i + j] = 0.5 * (s[L + 4 * i + j] + s[L + 4 * j + i])
    K.store_quat(s, quat_normalize((q0, q1, q2, q3)))


@njit(cache=True)
def quaternion_kf_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        quaternion_kf_step(s, p, rows[i])
        out[i] = s[:4]


class QuaternionKF(Estimator):
    """4-state linear quaternion Kalman filter, gyro process, QUEST measurement (eq. 25–26)."""

    name = "quaternion_kf"
    Params = QuaternionKFParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(quaternion_kf_step)
    batch = staticmethod(quaternion_kf_batch)

    def initial_state(self) -> np.ndarray:
        """Identity attitude, P₀ = p0 I₄ (Algorithm 1's input), no dip learned yet."""
        s = super().initial_state()
        s[P : P + 16] = (self.params.p0 * np.eye(4)).ravel()
        return s

    def _model_variance(self) -> AttitudeVariance:
        """Roll, pitch, yaw variances (rad²) from the filter's 4 × 4 P (J P Jᵀ) plus the floors
        of what the model leaves out (``uncertainty.with_unmodelled_floor``); yaw NaN until
        the first usable field sample (before it the measurement is gravity only)."""
        s = self.state
        if not s[K.INITIALISED]:
            return AttitudeVariance.unknown()
        var = with_unmodelled_floor(
            euler_variance_of_quaternion_covariance(s[K.HEADER_SLICES.q], s[STATE.slices.p].reshape(4, 4))
        )
        if s[K.MAG_AGE] < 0.0:  # K.NO_SAMPLE_YET
            return AttitudeVariance(var.roll, var.pitch, float("nan"))
        return var
