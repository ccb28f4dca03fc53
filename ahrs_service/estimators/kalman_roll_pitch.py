"""Kalman "sensor fusion" of roll and pitch: two independent scalar Kalman filters.

Second source paper, eq. 27–32 (after Suh, 2003). Each angle is predicted by integrating the
gyroscope (eq. 27–28, the process; noise ζ, σ_ζ) and corrected by the angle the accelerometer
gives when it senses gravity only (eq. 29–30, the measurement; noise ξ, σ_ξ), eq. 31–32.

Adaptations, all documented in docs/estimators-paper2.md:

* the process input is the Euler-angle rate of eq. 7 rather than the raw body rate; eq. 27–28
  are its small-angle form, and the exact rate keeps the filter right at large roll and pitch;
* the step over a sample (``exact_step`` 1, the default) takes the Euler angles of the attitude
  turned by the gyro's rotation h ω, the exact integral of eq. 7 for a rate constant over the
  sample, as the first paper's complementary filter does. The printed form x + h u with u the
  rate of eq. 7 at the sample's start (``exact_step`` 0, ``preset="paper"``) is first order and
  singular at pitch ±90°: in fast turns it loses the attitude, on BROAD's fast-rotation trial
  several times the exact step's error, the gyro alone and the tuned filter alike (figures:
  docs/estimators-paper2.md, "Why the defaults: measured figures");
* the measurement (eq. 29–30) is written for our specific force in FRD: at rest
  f = g (sin θ, −sin φ cos θ, −cos φ cos θ), so φ_y = atan2(−f_y, −f_z) (all four quadrants,
  upside-down included) and θ_y = atan2(f_x, √(f_y² + f_z²));
* yaw is the integral of eq. 7's yaw rate (no magnetometer: heading drifts with the gyro);
* the accelerometer gate (``acc_gate``, ``acc_lowpass``: ``K.acc_disturbance``) is the
  project's, not the paper's, and off under ``preset="paper"``;
* a gyro-bias estimate (``bias_rate``, the project's; the paper's process has none, so a shut
  gate lets the bias drift into roll and pitch): the process input is the gyro less a bias that
  follows the gyro while the sensor rests — the steady-state estimate of Valenti's own
  implementation (ROS ``imu_tools``), ``K.rest_bias_update``, as the QKF's, learning only
  while most recent samples passed its steady-state test (``rest_time``,
  ``K.rest_share_bias_update``); 0 under ``preset="paper"``;
* the process noise enters as h ζ with h the actual time step of each sample (eq. 31–32), so the
  filter is right for any sample timing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_from_euler, quat_integrate, quat_to_euler
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable
from ahrs_service.estimators.uncertainty import AttitudeVariance

STATE = Layout(
    "kalman_roll_pitch state",
    [
        Slot("euler", 3, "roll, pitch, yaw, rad"),
        Slot("p_roll_pitch", 2, "variances of roll and pitch, rad²"),
        Slot("acc_lp", 3, "low-passed specific force of the gate, m/s², body frame"),
        *K.REST_BIAS_SLOTS,  # the steady-state test of the bias estimate (K.rest_bias_update)
        *K.REST_SHARE_SLOTS,  # its share of steady samples (K.rest_share_bias_update)
    ],
    start=K.HEADER,
)
ROLL, P_ROLL, ACC_LP, GYR_PREV, REST_SHARE = STATE.index
STATE_SIZE = STATE.end

# |cos θ| floor of eq. 7 at gimbal lock: a finite rate instead of a division by zero
_COS_MIN = 1e-6


@njit(cache=True, inline="always")
def _wrap(a):
    """Angle wrapped to (−π, π]."""
    a -= 2.0 * math.pi * math.floor((a + math.pi) / (2.0 * math.pi))
    if a <= -math.pi:
        a += 2.0 * math.pi
    return a


@dataclass
class KalmanRollPitchParams:
    """Tuning of :class:`KalmanRollPitch` (σ values of eq. 31–32; only their ratio and the
    sample time set the gain, so the paper's degree units carry over unchanged).

    sigma_zeta: process noise σ_ζ, the gyro rate noise, rad/s. Paper: 5.
    sigma_xi: measurement noise σ_ξ, the accelerometer-angle noise, rad. Paper: 3.
    acc_gate: not in the paper (as the complementary filter's gate): no measurement update
        from a sample whose specific-force magnitude is off g by more than acc_gate·g, which
        linear acceleration then dominates; 1e9 (the paper) never gates.
    acc_lowpass: not in the paper: time constant (s) of the gyro-turned low-pass of the
        specific force whose magnitude the gate tests (vibration passes, a sustained
        acceleration does not); 0 (the paper's value, moot there) tests each sample's own.
    exact_step: 1 (default): the Euler angles after the gyro's exact rotation over the sample;
        0 (the paper's form, eq. 31–32): the first-order step x + h·u with u the rates of
        eq. 7 at the sample's start, which loses the attitude in fast turns.
    bias_rate: not in the paper (whose process has no bias): the rate, 1/s, at which a gyro-bias
        estimate follows the gyro while the sensor rests (per sample 1 − exp(−bias_rate·Δt),
        the steady-state test of Valenti's implementation, ``K.rest_bias_update``, as the
        QKF's); the process input is the gyro less it. 0 (the paper): no bias.
    rest_time: not in the paper: time constant (s) of the low-passed share of steady samples;
        the bias learns from a steady sample only while that share is at least a half, so the
        short runs of samples that pass the test in motion do not move it
        (``K.rest_share_bias_update``). 0 (the paper, moot there): each steady sample.
    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``.
    """

    # only σ_ζ/σ_ξ sets the gain: σ_ξ stays at the paper's value and σ_ζ alone is searched
    sigma_zeta: float = tunable(0.19050155232040536, paper=5.0, search=SearchRange(0.005, 20.0, log=True))  # rad/s
    sigma_xi: float = tunable(3.0, paper=3.0)  # rad
    acc_gate: float = tunable(0.024239690871633166, paper=1e9, search=SearchRange(0.02, 1.0, log=True))
    acc_lowpass: float = tunable(0.02732930832203962, paper=0.0, search=SearchRange(0.0, 0.2))  # s
    exact_step: float = tunable(1.0, paper=0.0)  # 1: exact step over the sample; 0: eq. 31–32's first order
    # not in the paper (Valenti's implementation's steady-state bias, as the QKF's); 0: no bias
    bias_rate: float = tunable(0.238775736531582, paper=0.0, search=SearchRange(1e-3, 10.0, log=True))  # 1/s
    rest_time: float = tunable(1.201720803150506, paper=0.0, search=SearchRange(0.0, 2.0))  # s; 0: every steady sample

    def __post_init__(self) -> None:
        if not self.sigma_zeta >= 0:
            raise ValueError(f"sigma_zeta must be >= 0, got {self.sigma_zeta}")
        if not self.sigma_xi > 0:
            raise ValueError(f"sigma_xi must be > 0, got {self.sigma_xi}")
        if not self.acc_gate > 0:
            raise ValueError(f"acc_gate must be > 0, got {self.acc_gate}")
        if not self.acc_lowpass >= 0:
            raise ValueError(f"acc_lowpass must be >= 0, got {self.acc_lowpass}")
        if not self.bias_rate >= 0:
            raise ValueError(f"bias_rate must be >= 0, got {self.bias_rate}")
        if not self.rest_time >= 0:
            raise ValueError(f"rest_time must be >= 0, got {self.rest_time}")
        if self.exact_step not in (0.0, 1.0):
            raise ValueError(f"exact_step must be 0 (first-order step) or 1 (exact step), got {self.exact_step}")


_P = param_index(KalmanRollPitchParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def kalman_roll_pitch_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _kalman_roll_pitch_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _kalman_roll_pitch_update(s, p, x)


@njit(cache=True)
def _kalman_roll_pitch_update(s, p, x):
    sigma_zeta, sigma_xi = p[_P.sigma_zeta], p[_P.sigma_xi]
    r_meas = sigma_xi * sigma_xi
    gyro_ok, acc_ok, _ = K.check_sample(s, x, False)
    phase = K.initialise_from_sample(s, x, acc_ok, False)
    if phase == K.STARTED:
        roll, pitch, yaw = quat_to_euler(K.load_quat(s))
        s[ROLL], s[ROLL + 1], s[ROLL + 2] = roll, pitch, yaw
        s[P_ROLL] = r_meas
        s[P_ROLL + 1] = r_meas
    if phase:
        return
    roll, pitch, yaw = s[ROLL], s[ROLL + 1], s[ROLL + 2]
    if gyro_ok:
        h = x[K.DT]
        if p[_P.bias_rate] > 0.0:  # not in the paper: the steady-state bias estimate (imu_tools)
            K.rest_share_bias_update(s, GYR_PREV, REST_SHARE, x, 1.0 - math.exp(-p[_P.bias_rate] * h), p[_P.rest_time], h)
        # the process input of eq. 27–28: the gyro less the bias estimate (0 in the paper)
        gp, gq, gr = x[0] - s[K.BIAS], x[1] - s[K.BIAS + 1], x[2] - s[K.BIAS + 2]
        if p[_P.exact_step] != 0.0:
            # eq. 7 over the whole sample: the Euler angles of the attitude turned by the
            # gyro's rotation h ω (exact for a rate constant over the sample, finite at ±90°;
            # the stored quaternion is the one of the stored angles)
            roll, pitch, yaw = quat_to_euler(quat_integrate(K.load_quat(s), gp, gq, gr, h))
        else:
            # eq. 27–28 / 31–32 as printed, x_{k+1} = x_k + h u_k, with u the Euler rates of
            # eq. 7 at the sample's start (first order: loses track in fast turns near ±90°)
            sr, cr = math.sin(roll), math.cos(roll)
            cp = math.cos(pitch)
            if abs(cp) < _COS_MIN:
                cp = _COS_MIN if cp >= 0.0 else -_COS_MIN
            tp = math.sin(pitch) / cp
            roll += h * (gp + tp * (gq * sr + gr * cr))
            pitch += h * (gq * cr - gr * sr)
            yaw += h * (gq * sr + gr * cr) / cp
            # pitch past ±90°: the same attitude with pitch mirrored and roll, yaw turned by π
            if pitch > 0.5 * math.pi:
                pitch = math.pi - pitch
                roll += math.pi
                yaw += math.pi
            elif pitch < -0.5 * math.pi:
                pitch = -math.pi - pitch
                roll += math.pi
                yaw += math.pi
            roll, yaw = _wrap(roll), _wrap(yaw)
        # Algorithm 1 line 2: P ← A P Aᵀ + H Q Hᵀ with A = 1, H = h
        qn = h * h * sigma_zeta * sigma_zeta
        s[P_ROLL] += qn
        s[P_ROLL + 1] += qn
    fx, fy, fz = x[3], x[4], x[5]
    # the gate (not the paper's): a specific force far from g is mostly linear acceleration
    if acc_ok and K.acc_disturbance(s, ACC_LP, x, p[_P.acc_lowpass]) <= p[_P.acc_gate]:
        # eq. 29–30 in FRD specific force
        y_roll = math.atan2(-fy, -fz)
        y_pitch = math.atan2(fx, math.sqrt(fy * fy + fz * fz))
        # Algorithm 1 lines 4–6, C = 1: G = P / (P + R), x ← x + G (y − x), P ← (1 − G) P
        g = s[P_ROLL] / (s[P_ROLL] + r_meas)
        roll = _wrap(roll + g * _wrap(y_roll - roll))
        s[P_ROLL] *= 1.0 - g
        g = s[P_ROLL + 1] / (s[P_ROLL + 1] + r_meas)
        pitch += g * (y_pitch - pitch)
        s[P_ROLL + 1] *= 1.0 - g
    s[ROLL], s[ROLL + 1], s[ROLL + 2] = roll, pitch, yaw
    K.store_quat(s, quat_from_euler(roll, pitch, yaw))


@njit(cache=True)
def kalman_roll_pitch_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        kalman_roll_pitch_step(s, p, rows[i])
        out[i] = s[:4]


class KalmanRollPitch(Estimator):
    """Two scalar Kalman filters on roll and pitch (eq. 27–32); yaw from gyro integration."""

    name = "kalman_roll_pitch"
    Params = KalmanRollPitchParams
    uses_mag = False
    observes_heading = False
    state_size = STATE_SIZE
    step = staticmethod(kalman_roll_pitch_step)
    batch = staticmethod(kalman_roll_pitch_batch)

    def _model_variance(self) -> AttitudeVariance:
        """The two filters' own variances of roll and pitch (rad²); yaw NaN (not observed)."""
        s = self.state
        if not s[K.INITIALISED]:
            return AttitudeVariance.unknown()
        roll, pitch = s[STATE.slices.p_roll_pitch]
        return AttitudeVariance(float(roll), float(pitch), float("nan"))
