"""The Euler-angle complementary filter of the first source paper, reduced and full forms.

I.J.R. Sánchez, A.C. Limache, "Estimación de orientación espacial basada en filtrado
complementario", Mecánica Computacional XXXVI, 2018 (numbers below refer to its equations).

Both forms run the paper's "short implementation" (fig. 2b): one first-order low-pass with
cut-off ω0 applied to Θs = Θ̇_HF/ω0 + Θ_LF (eq. 22), where Θ̇_HF is the Euler-angle rate from
the gyroscope (eq. 4–5) and Θ_LF the attitude seen by the slow sensors:

* reduced form (table 1): roll and pitch from gravity (eq. 29–30), yaw kept from the estimate,
  so yaw is gyro integration only (we use the gyro-propagated estimate Θ̂ + Θ̇Δt where the
  table has Θ̂₃, so that yaw integrates the gyro exactly instead of by 1/(1 + ω0Δt) of it);
* full form (table 2): yaw from the tilt-compensated magnetometer heading (eq. 43) plus the
  magnetic declination (eq. 44).

Adaptations to the project's conventions and to real data:

* Specific force: a level sensor at rest reads f = (0, 0, −g), so the gravity direction of
  eq. 28 is −f; eq. 29–30 become φ = atan2(−f_y, −f_z), θ = atan2(f_x, √(f_y² + f_z²)).
* Euler rates over a whole sample: Θ̇_HF = (Θ(q̂ ⊗ exp(ω Δt/2)) − Θ̂)/Δt, the change of the
  Euler angles when the estimate turns by the gyro's rotation over the sample. To first order
  this is eq. 4, B(Θ̂) ω, but it never evaluates B's tan θ and 1/cos θ, so it stays finite and
  exact through gimbal lock (pitch ±90°), where B(Θ) is singular. Multiplying B(Θ̂) ω by Δt
  loses track in fast rotations, because roll and yaw rates blow up whenever pitch nears ±90°:
  on BROAD it about doubles the mean total error (figures: docs/estimators-paper1-3.md, "Why
  the defaults: measured figures"). Past ±90° the Euler angles are kept canonical (θ in [−π/2, π/2],
  roll and yaw turned by π), as the gravity angles of eq. 29–30 are.
* Declination is positive east (magnetic north east of true north, as in the World Magnetic
  Model and ArduPilot's COMPASS_DEC), the sense of α in eq. 31–33. With that α the heading is
  ψ = ψ_M + α; eq. 38/44 print the opposite sign, which contradicts eq. 31–33. The heading of
  eq. 43 is tilt-compensated with the gyro-propagated roll and pitch of the same sample.
* Angles wrap: each Θ_LF component is unwrapped against the estimate before filtering, so
  yaw (and roll when upside down) crosses ±180° without a jump; the output is wrapped back.
* Linear-acceleration gate (not in the paper): a sample whose specific-force magnitude
  differs from g by more than ``acc_gate``·g gives no gravity angles (the gyro carries roll
  and pitch through it). Without it the filter follows the accelerations of BROAD's
  fast-translation trials (docs/estimators-paper1-3.md, ``acc_gate``). With ``acc_lowpass`` > 0 the
  gate tests the magnitude of the specific force low-passed with that time constant in a frame
  turned with the gyro (``K.acc_disturbance``): vibration averages out and no longer shuts the
  gate, a sustained acceleration still does. 0 (``preset="paper"``): each sample's own.
  With ``acc_soft`` 1 (the reduced form's default) the gate is a weight instead:
  Θ_LF = Θ_p + w (Θ_acc − Θ_p), w = 1/(1 + (dev/acc_gate)²).
* Gyro bias (not in the paper, reduced form): with ``bias_rate`` > 0 the Euler rates come from
  the gyro less a bias estimate that follows the gyro while the sensor rests — the
  steady-state estimate of Valenti's own implementation (ROS ``imu_tools``),
  ``K.rest_bias_update``, as the QKF's, learning only while most recent samples passed its
  steady-state test (``rest_time``, ``K.rest_share_bias_update``). 0 (``preset="paper"``, and
  the full form): none.
* Field-disturbance gate (not in the paper, full form): a field sample whose magnitude or dip
  departs from a reference learned from accepted samples gives no heading (``mag_gate``, the
  EKF's gate, shared as ``K.mag_gate_accepts``); the gyro carries yaw through it. 1e9
  (``preset="paper"``) accepts every sample.
* The filter coefficient α = Δt/(1/ω0 + Δt) (eq. 13) is computed from each sample's real Δt.
* With gimbal lock itself (|θ| = 90°) roll and yaw are not separable: the gravity angles and
  the tilt compensation stay finite (atan2), and the quaternion output is exact, but the two
  angles are only defined up to their sum/difference there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_from_euler, quat_integrate, quat_rotate, quat_to_euler
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable

# state after the common header: the filtered Euler angles Θ̂
STATE = Layout(
    "complementary state",
    [
        Slot("phi", 1, "roll φ̂, rad"),
        Slot("theta", 1, "pitch θ̂, rad"),
        Slot("psi", 1, "yaw ψ̂, rad"),
        Slot("acc_lp", 3, "low-passed specific force of the gate, m/s², body frame"),
        *K.MAG_REFERENCE_SLOTS,  # the field gate's reference (K.mag_gate_accepts), full form only
        *K.REST_BIAS_SLOTS,  # the steady-state test of the bias estimate (K.rest_bias_update), reduced form
        *K.REST_SHARE_SLOTS,  # its share of steady samples (K.rest_share_bias_update), reduced form
    ],
    start=K.HEADER,
)
PHI, THETA, PSI, ACC_LP, MAG_NORM_REF, _, GYR_PREV, REST_SHARE = STATE.index
STATE_SIZE = STATE.end

#: standard gravity, m/s²


def _check_omega0(omega0: float) -> None:
    if not omega0 > 0:
        raise ValueError(f"omega0 must be > 0, got {omega0}")


def _check_acc_gate(acc_gate: float) -> None:
    if not acc_gate > 0:
        raise ValueError(f"acc_gate must be > 0, got {acc_gate}")


def _check_acc_lowpass(acc_lowpass: float) -> None:
    if not acc_lowpass >= 0:
        raise ValueError(f"acc_lowpass must be >= 0, got {acc_lowpass}")


def _check_acc_soft(acc_soft: float) -> None:
    if acc_soft not in (0.0, 1.0):
        raise ValueError(f"acc_soft must be 0 (hard gate) or 1 (soft weight), got {acc_soft}")


@dataclass
class ComplementaryReducedParams:
    """Tuning of :class:`ComplementaryReduced`.

    omega0: cut-off of the low-pass, rad/s. Below it the attitude follows gravity, above it
        the gyroscope. The paper gives no value (``preset="paper"``: 0.2).
    acc_gate: largest relative error |‖f‖ − g|/g of a specific-force sample still used for
        roll and pitch. The paper has no gate (``preset="paper"``: 1e9).
    acc_lowpass: time constant (s) of the gyro-turned low-pass of f whose magnitude the gate
        tests; 0 (``preset="paper"``): each sample's own f.
    acc_soft: 1 (default): instead of a hard gate, the gravity angles are weighted by
        1/(1 + (dev/acc_gate)²), dev the (low-passed) |‖f‖/g − 1|: Θ_LF moves from the
        gyro-propagated angles that fraction of the way to the gravity angles. 0: the hard
        gate (``preset="paper"``, where the gate is open).
    bias_rate: not in the paper (whose gyro has no bias): the rate, 1/s, at which a gyro-bias
        estimate follows the gyro while the sensor rests (per sample 1 − exp(−bias_rate·Δt),
        the steady-state test of Valenti's implementation, ``K.rest_bias_update``, as the
        QKF's); Θ̇_HF is taken from the gyro less it. 0 (``preset="paper"``): no bias.
    rest_time: not in the paper: time constant (s) of the low-passed share of steady samples;
        the bias learns from a steady sample only while that share is at least a half, so the
        short runs of samples that pass the test in motion do not move it
        (``K.rest_share_bias_update``). 0 (``preset="paper"``, moot there): each steady sample.
    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``.
    """

    # paper: no ω0 given (0.2, the value used before tuning), no gate (1e9)
    omega0: float = tunable(0.3432932275711204, paper=0.2, search=SearchRange(0.01, 5.0, log=True))  # rad/s
    acc_gate: float = tunable(0.005861034520329941, paper=1e9, search=SearchRange(0.005, 1.0, log=True))
    acc_lowpass: float = tunable(0.01279544145790455, paper=0.0, search=SearchRange(0.0, 0.2))  # s
    acc_soft: float = tunable(1.0, paper=0.0)  # 1: weight 1/(1 + (dev/acc_gate)²); 0: hard gate
    # not in the paper (Valenti's implementation's steady-state bias, as the QKF's); 0: no bias
    bias_rate: float = tunable(0.19602080887244508, paper=0.0, search=SearchRange(1e-3, 10.0, log=True))  # 1/s
    rest_time: float = tunable(0.012180653480196722, paper=0.0, search=SearchRange(0.0, 2.0))  # s; 0: every steady sample

    def __post_init__(self) -> None:
        _check_omega0(self.omega0)
        _check_acc_gate(self.acc_gate)
        _check_acc_lowpass(self.acc_lowpass)
        _check_acc_soft(self.acc_soft)
        if not self.bias_rate >= 0:
            raise ValueError(f"bias_rate must be >= 0, got {self.bias_rate}")
        if not self.rest_time >= 0:
            raise ValueError(f"rest_time must be >= 0, got {self.rest_time}")


@dataclass
class ComplementaryFullParams:
    """Tuning of :class:`ComplementaryFull`.

    omega0: cut-off of the low-pass, rad/s, for all three angles (see the reduced form).
    declination: magnetic declination, rad, positive when magnetic north lies east of true
        north (eq. 44). Default 0: heading against magnetic north. For runs outside the
        service only: the service turns every estimator's output to true north itself
        (``estimator.declination_deg`` or ``[location]``, MAVLink MAG_DECL_DEG), so a declination set
        here as well would count twice.
    acc_gate, acc_lowpass, acc_soft: as for the reduced form (acc_soft default 0: this
        preset was tuned with the hard gate).
    mag_gate: field-disturbance gate (not in the paper): a field sample is not used when
        |‖m‖/m_ref − 1| + |sin δ − sin δ_ref| > mag_gate (δ the dip; references learned from
        accepted samples, ``K.mag_gate_accepts``, as the EKF's). 1e9 (``preset="paper"``): off.
    Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
    are ``preset="paper"``.
    """

    omega0: float = tunable(0.25289896788441085, paper=0.2, search=SearchRange(0.01, 5.0, log=True))  # rad/s
    declination: float = tunable(0.0, paper=0.0)  # rad; a site constant, not tuned
    acc_gate: float = tunable(0.03611278160401323, paper=1e9, search=SearchRange(0.005, 1.0, log=True))
    acc_lowpass: float = tunable(0.050237868208254585, paper=0.0, search=SearchRange(0.0, 0.2))  # s
    mag_gate: float = tunable(0.1512691496420839, paper=1e9, search=SearchRange(0.02, 1.0, log=True))
    acc_soft: float = tunable(0.0, paper=0.0)  # the hard gate: what this preset was tuned with

    def __post_init__(self) -> None:
        _check_omega0(self.omega0)
        _check_acc_gate(self.acc_gate)
        _check_acc_lowpass(self.acc_lowpass)
        _check_acc_soft(self.acc_soft)
        if not self.mag_gate > 0:
            raise ValueError(f"mag_gate must be > 0, got {self.mag_gate}")


_inline = njit(cache=True, inline="always")


@_inline
def _wrap(a):
    """Angle in (−π, π]."""
    return a - 2.0 * math.pi * math.ceil((a - math.pi) / (2.0 * math.pi))


@_inline
def _unwrap_to(measured, reference):
    """The measured angle moved by whole turns to within π of the reference."""
    return reference + _wrap(measured - reference)


@_inline
def _store_euler(s, phi, theta, psi):
    # fold pitch past ±90° back into [−π/2, π/2]: the same attitude, canonical angles
    if theta > 0.5 * math.pi:
        theta = math.pi - theta
        phi += math.pi
        psi += math.pi
    elif theta < -0.5 * math.pi:
        theta = -math.pi - theta
        phi += math.pi
        psi += math.pi
    phi = _wrap(phi)
    psi = _wrap(psi)
    s[PHI], s[THETA], s[PSI] = phi, theta, psi
    K.store_quat(s, quat_from_euler(phi, theta, psi))


@_inline
def _complementary_update(s, x, omega0, declination, acc_gate, acc_lowpass, acc_soft, mag_gate, use_mag, bias_rate, rest_time):
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, use_mag)
    phase = K.initialise_from_sample(s, x, acc_ok, mag_ok)
    if phase == K.STARTED:
        phi, theta, psi = quat_to_euler(K.load_quat(s))
        if mag_ok:
            psi += declination  # eq. 44: the start-up heading is magnetic
        _store_euler(s, phi, theta, psi)
    if phase or not gyro_ok:
        return
    # after a gap: cut-off raised and gate widened while its error is corrected (_kernel)
    omega0 *= K.recovery_gain(s)
    acc_gate *= K.recovery_gain(s)
    phi, theta, psi = s[PHI], s[THETA], s[PSI]
    dt = x[K.DT]
    if bias_rate > 0.0:  # not in the paper: the steady-state bias estimate (imu_tools)
        K.rest_share_bias_update(s, GYR_PREV, REST_SHARE, x, 1.0 - math.exp(-bias_rate * dt), rest_time, dt)
    # the gyro less the bias estimate (0 in the paper)
    wx, wy, wz = x[0] - s[K.BIAS], x[1] - s[K.BIAS + 1], x[2] - s[K.BIAS + 2]

    # eq. 4–5 over one sample: the Euler-angle change of the gyro-propagated attitude
    # (the stored quaternion is always the one of the stored Euler angles)
    q1 = quat_integrate(K.load_quat(s), wx, wy, wz, dt)
    r1, t1, y1 = quat_to_euler(q1)
    phi_p, theta_p, psi_p = phi + _wrap(r1 - phi), t1, psi + _wrap(y1 - psi)
    phi_dot, theta_dot, psi_dot = (phi_p - phi) / dt, (theta_p - theta) / dt, (psi_p - psi) / dt

    # Θ_LF: the slow sensors' attitude, unwrapped against the gyro-propagated estimate; where
    # a sensor is missing (or, for yaw, in the reduced form) that estimate stands in for it
    phi_lf, theta_lf, psi_lf = phi_p, theta_p, psi_p
    fx, fy, fz = x[3], x[4], x[5]
    if acc_ok:
        dev = K.acc_disturbance(s, ACC_LP, x, acc_lowpass)
        # the gate (not the paper's): hard, or a soft weight of the gravity angles
        if acc_soft or dev <= acc_gate:
            phi_lf = _unwrap_to(math.atan2(-fy, -fz), phi_p)  # eq. 29 (specific force)
            theta_lf = math.atan2(fx, math.sqrt(fy * fy + fz * fz))  # eq. 30
            if acc_soft:
                w = 1.0 / (1.0 + (dev / acc_gate) ** 2)
                phi_lf = phi_p + w * (phi_lf - phi_p)
                theta_lf = theta_p + w * (theta_lf - theta_p)
    if mag_ok:
        mx, my, mz = x[6], x[7], x[8]
        nm = math.sqrt(mx * mx + my * my + mz * mz)
        # the field gate (not the paper's): magnitude and dip against earth's, learned
        down = quat_rotate(q1, (mx / nm, my / nm, mz / nm))[2]
        if K.mag_gate_accepts(s, MAG_NORM_REF, nm, down, mag_gate, dt):
            # eq. 43: tilt-compensated magnetic heading, tilt from the gyro-propagated estimate
            sr, cr, st, c_t = math.sin(r1), math.cos(r1), math.sin(t1), math.cos(t1)
            num = -my * cr + mz * sr
            den = mx * c_t + my * sr * st + mz * cr * st
            if num * num + den * den > 0.0:
                psi_lf = _unwrap_to(math.atan2(num, den) + declination, psi_p)  # eq. 44

    # eq. 22 and eq. 13: Θs = Θ̇/ω0 + Θ_LF, low-passed with α from this sample's Δt
    alpha = dt / (1.0 / omega0 + dt)
    phi = alpha * (phi_dot / omega0 + phi_lf) + (1.0 - alpha) * phi
    theta = alpha * (theta_dot / omega0 + theta_lf) + (1.0 - alpha) * theta
    psi = alpha * (psi_dot / omega0 + psi_lf) + (1.0 - alpha) * psi
    _store_euler(s, phi, theta, psi)


_PR = param_index(ComplementaryReducedParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def complementary_reduced_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _complementary_update(s, K.bridge_row(sub, w0, x, j, n), p[_PR.omega0], 0.0, p[_PR.acc_gate], p[_PR.acc_lowpass], p[_PR.acc_soft] != 0.0, 1e9, False, p[_PR.bias_rate], p[_PR.rest_time])
        x = K.end_bridge(s, saved, x, n)
    _complementary_update(s, x, p[_PR.omega0], 0.0, p[_PR.acc_gate], p[_PR.acc_lowpass], p[_PR.acc_soft] != 0.0, 1e9, False, p[_PR.bias_rate], p[_PR.rest_time])


_PF = param_index(ComplementaryFullParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def complementary_full_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _complementary_update(s, K.bridge_row(sub, w0, x, j, n), p[_PF.omega0], p[_PF.declination], p[_PF.acc_gate], p[_PF.acc_lowpass], p[_PF.acc_soft] != 0.0, p[_PF.mag_gate], True, 0.0, 0.0)
        x = K.end_bridge(s, saved, x, n)
    _complementary_update(s, x, p[_PF.omega0], p[_PF.declination], p[_PF.acc_gate], p[_PF.acc_lowpass], p[_PF.acc_soft] != 0.0, p[_PF.mag_gate], True, 0.0, 0.0)


@njit(cache=True)
def complementary_reduced_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        complementary_reduced_step(s, p, rows[i])
        out[i] = s[:4]


@njit(cache=True)
def complementary_full_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        complementary_full_step(s, p, rows[i])
        out[i] = s[:4]


class ComplementaryReduced(Estimator):
    """Euler-angle complementary filter, reduced form: roll/pitch from gravity, yaw from the gyro."""

    name = "complementary_reduced"
    Params = ComplementaryReducedParams
    uses_mag = False
    observes_heading = False
    state_size = STATE_SIZE
    step = staticmethod(complementary_reduced_step)
    batch = staticmethod(complementary_reduced_batch)


class ComplementaryFull(Estimator):
    """Euler-angle complementary filter, full form: adds the magnetometer heading and declination."""

    name = "complementary_full"
    Params = ComplementaryFullParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(complementary_full_step)
    batch = staticmethod(complementary_full_batch)
