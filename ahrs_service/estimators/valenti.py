"""Valenti's quaternion complementary filter (2015), as in the third source paper.

R.G. Valenti, I. Dryanovski, J. Xiao, "Keeping a good attitude: a quaternion-based
orientation filter for IMUs and MARGs", Sensors 15, 2015; presented in the third source paper
eq. 47–61 and its annex 3 (numbers below refer to it).

The gyroscope predicts (eq. 47–48); two delta quaternions then correct the prediction, first
from the accelerometer (roll and pitch only, eq. 50–57), then from the magnetometer (a
rotation about the earth's vertical only, eq. 58–61), so a disturbed magnetic field can never
tilt the estimate. Each delta is shrunk towards identity by LERP, or SLERP when it is larger
than the threshold ε = 0.9 on its scalar part (eq. 54–56).

Derivation for our conventions. Valenti's quaternion is q_local←global with the global z axis
up; ours is q_earth←body in NED. Let g_p = R(q_ω)(−f/|f|) be the measured "down" seen in the
earth frame by the prediction. The accelerometer delta is the smallest rotation taking g_p to
the earth's down (0, 0, 1), applied on the earth side: q' = Δq_acc ⊗ q_ω. For g_z ≥ 0

    Δq_acc = (√((1 + g_z)/2),  g_y/√(2(1 + g_z)),  −g_x/√(2(1 + g_z)),  0)

and for g_z < 0 (prediction off by more than 90°) a 180° turn about north is composed in
first, Δq_acc = (g_y/k, √((1 − g_z)/2), 0, g_x/k), k = √(2(1 − g_z)) — eq. 53 with the signs
of our frame. The magnetometer delta turns l = R(q') m about the vertical onto the north–down
plane, a rotation by −atan2(l_y, l_x): with Γ = l_x² + l_y²,

    Δq_mag = (√(Γ + l_x√Γ)/√(2Γ), 0, 0, −l_y/√(2(Γ + l_x√Γ)))           for l_x ≥ 0,
    Δq_mag = (|l_y|/√(2(Γ − l_x√Γ)), 0, 0, −sgn(l_y)√(Γ − l_x√Γ)/√(2Γ))  for l_x < 0,

(eq. 60). Every delta is taken with a non-negative scalar part, so interpolation towards
identity always takes the short way.

Gains. Valenti's α and β are fractions of the delta applied per sample; the annex uses
α = 0.03, β = 0.3 on 100 Hz data. To keep the filter's bandwidth when the rate changes or
samples jitter, a sample of length Δt applies 1 − (1 − α)^(Δt · gain_rate_hz): exactly α at
``gain_rate_hz``. The adaptive gain (annex 3) scales α by 1 below a relative specific-force
magnitude error of 0.1, by 0 above 0.2, linearly in between.

Two additions, each off in ``preset="paper"``:

* Gyro-bias estimation as in the authors' own implementation (R.G. Valenti, the
  ``imu_complementary_filter`` of ROS ``imu_tools``, BSD, CCNY Robotics Lab 2015): while the
  sensor is in a steady state — |‖f‖ − g| ≤ 0.1 m/s², every gyro axis within 0.01 rad/s of
  the previous sample and within 0.2 rad/s of the bias — the bias follows the gyro by a
  low-pass filter, b ← b + α_b (ω − b), and the prediction integrates ω − b
  (``_kernel.rest_bias_update``, shared with the QKF's variant). ``bias_alpha``
  is α_b per sample at ``gain_rate_hz`` like alpha and beta (the implementation's default
  0.01; 0, the paper's filter, estimates no bias).
* A magnetic-disturbance gate (the project's, as the EKF's ``mag_gate``): a field sample
  whose magnitude or dip departs from a reference the filter learns from the accepted samples
  (``_kernel.mag_gate_accepts``) gives no heading correction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.core.layout import Layout, param_index
from ahrs_service.core.quaternion import quat_mul, quat_normalize, quat_rotate
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable

#: the threshold on the delta's scalar part above which LERP replaces SLERP (eq. 54–56)
EPSILON = 0.9
# after the common header (the bias itself is in the header's BIAS slots)
STATE = Layout(
    "valenti state",
    [*K.REST_BIAS_SLOTS, *K.MAG_REFERENCE_SLOTS],
    start=K.HEADER,
)
GYR_PREV, MAG_REF = STATE.index.gyr_prev, STATE.index.mag_norm_ref
STATE_SIZE = STATE.end


@dataclass
class ValentiParams:
    """Tuning of :class:`Valenti`.

    alpha: accelerometer gain, the fraction of the tilt delta applied per sample at
        ``gain_rate_hz`` (eq. 54). The third paper's annex 3 (``preset="paper"``) uses 0.03,
        which on BROAD follows linear acceleration far too closely (docs/estimators-paper1-3.md).
    beta: magnetometer gain, the same for the heading delta (eq. 60–61). The annex's 0.3
        makes heading as noisy as the magnetometer.
    gain_rate_hz: the sample rate at which alpha and beta are per-sample fractions, Hz.
        100, the rate of the third paper's data.
    adaptive_low, adaptive_high: relative specific-force magnitude errors |‖f‖ − g|/g
        between which the accelerometer gain falls from alpha to zero (annex 3: 0.1, 0.2).
    bias_alpha: gyro-bias gain α_b, the fraction of ω − b the bias moves per steady-state
        sample at ``gain_rate_hz`` (the authors' implementation; 0 = no bias estimation, the
        paper's filter).
    mag_gate: magnetometer disturbance gate (not in the paper): a field sample gives no heading
        correction when |‖m‖/m_ref − 1| + |sin δ − sin δ_ref| exceeds it, δ the field's dip
        below the horizon, the references learned from the accepted samples with a 10 s time
        constant (as the EKF's gate; 1e9, the paper, accepts every sample).
    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``.
    """

    # paper: annex 3's gains; the two thresholds' ranges are disjoint, so low < high holds
    alpha: float = tunable(0.000603792810148083, paper=0.03, search=SearchRange(1e-4, 0.1, log=True))
    beta: float = tunable(0.0037464629054970973, paper=0.3, search=SearchRange(1e-5, 0.3, log=True))
    gain_rate_hz: float = tunable(100.0, paper=100.0)  # Hz; a unit of alpha and beta, not tuned
    adaptive_low: float = tunable(0.04957639622582108, paper=0.1, search=SearchRange(0.01, 0.15))
    adaptive_high: float = tunable(0.5733138622254811, paper=0.2, search=SearchRange(0.16, 1.0))
    # the authors' implementation (imu_tools); 0 (the paper's filter) estimates no bias
    bias_alpha: float = tunable(0.0016351555924922138, paper=0.0, search=SearchRange(1e-4, 0.3, log=True))
    # not in the paper (as the EKF's mag_gate); 1e9 (the paper) never gates
    mag_gate: float = tunable(0.020207317852193128, paper=1e9, search=SearchRange(0.02, 1.0, log=True))

    def __post_init__(self) -> None:
        for name in ("alpha", "beta", "bias_alpha"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {v}")
        if not self.mag_gate > 0:
            raise ValueError(f"mag_gate must be > 0, got {self.mag_gate}")
        if not self.gain_rate_hz > 0:
            raise ValueError(f"gain_rate_hz must be > 0, got {self.gain_rate_hz}")
        if not 0.0 <= self.adaptive_low < self.adaptive_high:
            raise ValueError(
                f"need 0 <= adaptive_low < adaptive_high, got {self.adaptive_low}, {self.adaptive_high}"
            )


_inline = njit(cache=True, inline="always")


@_inline
def _shrink(dq, gain):
    """The delta quaternion moved a fraction ``gain`` of the way from identity (eq. 54–56)."""
    if dq[0] > EPSILON:
        # eq. 54–55: LERP, then back to unit norm
        return quat_normalize(((1.0 - gain) + gain * dq[0], gain * dq[1], gain * dq[2], gain * dq[3]))
    # eq. 56: SLERP between identity and Δq
    omega = math.acos(min(1.0, dq[0]))
    so = math.sin(omega)
    a = math.sin((1.0 - gain) * omega) / so
    b = math.sin(gain * omega) / so
    return quat_normalize((a + b * dq[0], b * dq[1], b * dq[2], b * dq[3]))


@_inline
def _positive(q):
    if q[0] < 0.0:
        return (-q[0], -q[1], -q[2], -q[3])
    return q


@_inline
def _accelerometer_delta(gx, gy, gz):
    """Smallest rotation taking the predicted down g_p onto (0, 0, 1) (eq. 51–53, NED)."""
    if gz >= 0.0:
        k = math.sqrt(2.0 * (1.0 + gz))
        return (math.sqrt(0.5 * (1.0 + gz)), gy / k, -gx / k, 0.0)
    k = math.sqrt(2.0 * (1.0 - gz))
    return _positive((gy / k, math.sqrt(0.5 * (1.0 - gz)), 0.0, gx / k))


@_inline
def _magnetometer_delta(lx, ly):
    """Rotation about the vertical taking (l_x, l_y) onto north (eq. 59–60, NED)."""
    gamma = lx * lx + ly * ly
    sg = math.sqrt(gamma)
    if lx >= 0.0:
        a = math.sqrt(gamma + lx * sg)
        return (a / math.sqrt(2.0 * gamma), 0.0, 0.0, -ly / (math.sqrt(2.0) * a))
    a = math.sqrt(gamma - lx * sg)
    sign = 1.0 if ly >= 0.0 else -1.0
    return (abs(ly) / (math.sqrt(2.0) * a), 0.0, 0.0, -sign * a / math.sqrt(2.0 * gamma))


@_inline
def _per_sample(gain, dt, rate):
    # the same bandwidth at any rate: (1 − gain) per reference period, compounded over dt
    return 1.0 - (1.0 - gain) ** (dt * rate)


#: the largest accelerometer gain per reference period a gap's recovery may raise α to
ALPHA_MAX = 0.5

_P = param_index(ValentiParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def valenti_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _valenti_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _valenti_update(s, p, x)


@njit(cache=True)
def _valenti_update(s, p, x):
    alpha, beta, rate = p[_P.alpha], p[_P.beta], p[_P.gain_rate_hz]
    # after a gap: the accelerometer's gain raised while its error is corrected (_kernel)
    alpha = min(ALPHA_MAX, alpha * K.recovery_gain(s))
    t_low, t_high = p[_P.adaptive_low], p[_P.adaptive_high]
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok) or not gyro_ok:
        return
    q = K.load_quat(s)
    dt = x[K.DT]
    if p[_P.bias_alpha] > 0.0:  # not in the paper: the authors' implementation
        K.rest_bias_update(s, GYR_PREV, x, _per_sample(p[_P.bias_alpha], dt, rate))

    # eq. 47–48: q_ω = q + Δt · ½ q ⊗ (0, ω − b), unit norm (b = 0 without bias estimation)
    wx, wy, wz = x[0] - s[K.BIAS], x[1] - s[K.BIAS + 1], x[2] - s[K.BIAS + 2]
    qd = quat_mul(q, (0.0, 0.5 * wx, 0.5 * wy, 0.5 * wz))
    q = quat_normalize((q[0] + qd[0] * dt, q[1] + qd[1] * dt, q[2] + qd[2] * dt, q[3] + qd[3] * dt))

    if acc_ok:
        na = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
        # annex 3: adaptive gain from the magnitude error of the specific force
        err = abs(na - K.GRAVITY) / K.GRAVITY
        if err <= t_low:
            factor = 1.0
        elif err >= t_high:
            factor = 0.0
        else:
            factor = (t_high - err) / (t_high - t_low)
        gain = _per_sample(alpha * factor, dt, rate)
        if gain > 0.0:
            # eq. 50: predicted down in the earth frame
            gx, gy, gz = quat_rotate(q, (-x[3] / na, -x[4] / na, -x[5] / na))
            # eq. 53–57
            q = quat_normalize(quat_mul(_shrink(_accelerometer_delta(gx, gy, gz), gain), q))

    if mag_ok:
        lx, ly, lz = quat_rotate(q, (x[6], x[7], x[8]))  # eq. 58
        gain = _per_sample(beta, dt, rate)
        nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
        # the gate (not the paper's): a field whose magnitude or dip left the learned ones is a magnet's
        accepted = K.mag_gate_accepts(s, MAG_REF, nm, lz / nm, p[_P.mag_gate], dt)
        if accepted and lx * lx + ly * ly > 1e-12 and gain > 0.0:
            # eq. 60–61
            q = quat_normalize(quat_mul(_shrink(_magnetometer_delta(lx, ly), gain), q))

    K.store_quat(s, q)


@njit(cache=True)
def valenti_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        valenti_step(s, p, rows[i])
        out[i] = s[:4]


class Valenti(Estimator):
    """Valenti's quaternion complementary filter: tilt from gravity, heading from the magnetometer."""

    name = "valenti"
    Params = ValentiParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(valenti_step)
    batch = staticmethod(valenti_batch)
