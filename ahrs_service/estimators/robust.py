"""The robust real-time attitude estimator ("robust"): GIMLET.

GIMLET — *Gyro-consistent Inertial-frame filter with Magnetic Learning of hard iron and
Extended rejection* — is a causal, one-sample-at-a-time estimator built on VQF (D. Laidig,
T. Seel, "VQF: Highly accurate IMU orientation estimation with bias estimation and magnetic
disturbance rejection", Information Fusion 91, 2023, doi: 10.1016/j.inffus.2022.10.014).

Credit: this module's start-up, rest detection, inclination correction (with its q_w guard)
and gyro-bias Kalman filter (covariance in (0.01 °/s)², its noise scaling) follow VQF's
reference implementation (github.com/dlaidig/vqf, vqf/cpp/vqf.cpp, MIT, © 2021 Daniel
Laidig; notice in THIRD_PARTY_NOTICES), in places statement by statement, re-expressed for
NED/FRD. The project's own: the output lead and the magnetic features marked so in
``robust_mag``. The attitude is factored as (VQF eq. 3)

    q_E←S = q_δ ⊗ q_a ⊗ q_g

* q_g (I←S): strapdown integration of the bias-corrected gyroscope into an almost-inertial
  frame I (VQF eq. 4);
* q_a (E6←I): inclination correction. The accelerometer is rotated into I and low-pass
  filtered there (2nd-order, τ_acc), so linear accelerations that average out over a few
  seconds (tapping, translation) cannot tilt the estimate; q_a turns the filtered vector onto
  the vertical (VQF eq. 7–10). τ_acc follows the tilt rate (the project's own, see
  ``_accel_time_constant``): longer while the sensor tilts slowly, as a vehicle in flight
  does, so that sustained accelerations average out;
* q_δ (E←E6): rotation about the vertical by the heading offset δ, a first-order filter of
  the magnetometer's heading disagreement (τ_mag, VQF eq. 11–12) gated by the magnetic
  rejection features below.

Gyro bias: a 3-state Kalman filter updated at rest (rest detection from the deviations of
gyro and accelerometer from their low-passed values) and in motion (the inclination
correction rate tells the bias on the horizontal axes), VQF section 3.3.

Magnetic rejection features (documented in docs/robust-estimator.md):

* **norm/dip gate** — the field's norm and dip, learned while undisturbed, must match;
* **gyro consistency** — an undisturbed field is constant in the gyro frame I after the
  hard-iron offset is removed; a field that changes there while the gyroscope says the body
  did not turn accordingly (vibrating phone, passing magnet) is rejected;
* **hard-iron learning** — a body-fixed offset h (an attached magnet) obeys
  R_g(t)(m(t) − h) = const, so differences of block means of R_g m are linear in h:
  Δ(R̄_g m) = Δ(R̄_g) h. A recursive least squares with forgetting estimates h while rotation
  makes it observable; the corrected field m − h feeds the heading once its norm and dip
  match the learned reference again;
* **offset change detection** — a block jump no rotation explains restarts the least
  squares and vetoes the field until the new offset is known (magnet attached or removed);
* **start-up confirmation** — the switch-on field sets the initial heading but corrects it
  only once it stayed steady while turning (VQF's magNewFirstTime);
* **rejection timeout** and **new-field acceptance** as in VQF.

Attitude uncertainty (``attitude_variance``): the step keeps a record of the gyro drift its
corrections have not yet removed, of the sustained acceleration the accelerometer shows (the
vector mean of its horizontal part) and of the disturbance of the fields it used
(``_drift_of_the_error_model``, ``_inclination_and_bias``, ``robust_mag.heading``); ``uncertainty.ObservedErrorModel``
turns it into variances (docs/autopilot.md, "Attitude covariance").

The published attitude is carried forward by ``output_lead`` (latency compensation, see
``RobustParams``); the filter state is not.

A row whose magnetometer is NaN carries no new field: the heading update is skipped and the
time since the last field sample is kept, so a magnetometer slower than the gyroscope works.

Modules: this one (start-up, rest detection, inclination, bias, the step and the class),
``robust_layout`` (parameters and state slots), ``robust_mag`` (the magnetic features),
``robust_blocks`` (filters and small linear algebra). The state array starts with the common
header of ``_kernel`` (q, flags, counters, gyro bias); ``robust_layout.STATE`` declares the
rest by name and size (``s[ST.gq]``, ``p[P.tau_acc]``). Earth frame NED, body frame FRD or the sensor's own axes; units rad/s, m/s², µT, s.
"""

from __future__ import annotations

import math
from typing import ClassVar

import numpy as np
from numba import njit

from ahrs_service.core.quaternion import quat_conj, quat_integrate, quat_mul, quat_normalize, quat_rotate
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators import robust_blocks as B
from ahrs_service.estimators.base import Estimator, sample_age
from ahrs_service.estimators.robust_layout import DEG, N_PARAMS, ST, STATE, STATE_SIZE, P, RobustParams
from ahrs_service.estimators.robust_mag import hard_iron_and_consistency, heading
from ahrs_service.estimators.uncertainty import (
    SUSTAINED_ACCELERATION_TAU,
    AttitudeVariance,
    ObservedErrorModel,
    ObservedErrorState,
)

_jit = njit(cache=True, inline="always")

#: unit of the bias covariance (robust_layout: bias_p in (0.01 °/s)²): σ_b = √p · BIAS_P_UNIT rad/s
BIAS_P_UNIT = 0.01 * DEG


@_jit
def _accel_time_constant(s, p):
    """τ of the accelerometer low-pass in I for the recent tilt rate, s (the project's own).

    The gyro frame I drifts in inclination by the residual bias plus the gyro's scale and
    misalignment error times the rate at which the sensor tilts (|ω| about the horizontal
    axes): r = b + ε |ω̄_h|. A low-pass of time constant τ leaves a drift error ≈ r τ and an
    acceleration error that falls with τ; their sum is smallest for τ ∝ 1/√r, hence
    τ = tau_acc_max / √(1 + |ω̄_h| / tilt_rate_ref), with tilt_rate_ref = b/ε, never below
    tau_acc. Rounded to 0.05 s so the coefficient cache holds between changes; the filters
    keep their delay states across a change, which shifts their output by Δb0 times the input
    (transposed direct form II): b0 ≈ 3·10⁻⁷ for τ = 3 s at 400 Hz, a 0.05 s step changes it by
    about 10⁻⁸, so gravity's 9.8 m/s² jumps by about 10⁻⁷ m/s².
    """
    ref = p[P.tilt_rate_ref] * DEG
    if ref <= 0.0:
        return p[P.tau_acc]
    tau = max(p[P.tau_acc], p[P.tau_acc_max] / math.sqrt(1.0 + s[ST.tilt_rate] / ref))
    return math.floor(tau * 20.0 + 0.5) / 20.0


@_jit
def _update_coefficients(s, p, dt, tau_acc):
    """Recomputes the cached low-pass coefficients when dt or a time constant changed;
    ``tau_acc`` is the accelerometer time constant in force (``_accel_time_constant``)."""
    if B.cache_is_stale(
        s,
        (ST.coef_dt, ST.coef_tau_acc, ST.coef_tau_rest, ST.coef_tau_acc_rest),
        (dt, tau_acc, p[P.rest_filter_tau], p[P.tau_acc_rest]),
    ):
        B.butter2_coefficients(s, ST.ca, dt, tau_acc)
        B.butter2_coefficients(s, ST.cr, dt, p[P.rest_filter_tau])
        B.butter2_coefficients(s, ST.car, dt, p[P.tau_acc_rest])


@_jit
def _start(s, x):
    """First usable sample: q_g from gravity (and field), q_a = 1, δ = 0, filters at steady state."""
    s[ST.gq], s[ST.gq + 1], s[ST.gq + 2], s[ST.gq + 3] = s[0], s[1], s[2], s[3]
    s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3] = 1.0, 0.0, 0.0, 0.0
    s[ST.delta] = 0.0
    s[ST.delta_c], s[ST.delta_s] = 1.0, 0.0
    a_i = quat_rotate(K.load_quat(s), (x[3], x[4], x[5]))
    r = B.quat_to_matrix(K.load_quat(s))
    for k in range(3):
        B.butter2_reset(s, ST.ca, ST.acc_lp, 3, k, a_i[k])
        B.butter2_reset(s, ST.cr, ST.rest_gyr, 3, k, x[k])
        B.butter2_reset(s, ST.cr, ST.rest_acc, 3, k, x[3 + k])
        s[ST.gyr_lp + k] = x[k]
    for k in range(9):
        B.butter2_reset(s, ST.ca, ST.r_lp, 9, k, r[k])
    for k in range(2):
        B.butter2_reset(s, ST.ca, ST.bias_lp, 2, k, 0.0)
    s[ST.mag_n] = 0.0
    s[ST.mag_t] = 0.0
    s[ST.hi_prev_ok] = 0.0


@_jit
def _rest_detection(s, p, x, dt):
    """VQF's rest detection: gyro and accelerometer stay near their low-passed values."""
    dev_g = 0.0
    dev_a = 0.0
    lp2 = 0.0
    for k in range(3):
        g = B.butter2_step(s, ST.cr, ST.rest_gyr, 3, k, x[k])
        s[ST.gyr_lp + k] = g
        a = B.butter2_step(s, ST.cr, ST.rest_acc, 3, k, x[3 + k])
        dev_g += (x[k] - g) ** 2
        dev_a += (x[3 + k] - a) ** 2
        lp2 += g * g
    th_g = p[P.rest_th_gyr] * DEG
    clip = p[P.bias_clip] * DEG
    if dev_g >= th_g * th_g or lp2 > clip * clip or dev_a >= p[P.rest_th_acc] ** 2:
        s[ST.rest_t] = 0.0
        s[ST.rest] = 0.0
    else:
        s[ST.rest_t] += dt
        if s[ST.rest_t] >= p[P.rest_min_t]:
            s[ST.rest] = 1.0


@_jit
def _inclination_and_bias(s, p, x, dt, qg, rg):
    """Accelerometer low-pass in I, inclination correction of q_a, gyro-bias Kalman update.

    ``rg`` is R(q_g) as a row-major 9-tuple. Returns q_a ⊗ q_g with the corrected q_a.
    """
    ax, ay, az = x[3], x[4], x[5]
    a_i = (
        rg[0] * ax + rg[1] * ay + rg[2] * az,
        rg[3] * ax + rg[4] * ay + rg[5] * az,
        rg[6] * ax + rg[7] * ay + rg[8] * az,
    )
    ca = ST.car if s[ST.rest] != 0.0 else ST.ca  # at rest nothing needs rejecting: converge faster
    lp0 = B.butter2_step(s, ca, ST.acc_lp, 3, 0, a_i[0])
    lp1 = B.butter2_step(s, ca, ST.acc_lp, 3, 1, a_i[1])
    lp2 = B.butter2_step(s, ca, ST.acc_lp, 3, 2, a_i[2])
    qa = (s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3])
    # error model (attitude_variance): the vector mean of the unit specific force's horizontal
    # part in E6 over SUSTAINED_ACCELERATION_TAU, the sustained acceleration the low-pass takes
    # for gravity in part (a quadrotor's turns); jerks and vibration average out
    f_e = quat_rotate(qa, a_i)
    nf = math.sqrt(f_e[0] ** 2 + f_e[1] ** 2 + f_e[2] ** 2)
    if nf > 0.0:
        k_s = min(1.0, dt / SUSTAINED_ACCELERATION_TAU)
        s[ST.acc_sustained] += k_s * (f_e[0] / nf - s[ST.acc_sustained])
        s[ST.acc_sustained + 1] += k_s * (f_e[1] / nf - s[ST.acc_sustained + 1])
    a_e = quat_rotate(qa, (lp0, lp1, lp2))
    n = math.sqrt(a_e[0] ** 2 + a_e[1] ** 2 + a_e[2] ** 2)
    # down direction u = −f/|f| must become NED z: rotate u onto (0, 0, 1) (VQF eq. 9–10).
    # A zero (or NaN) filtered vector has no direction: no correction, and no early return
    # either (it would cost a reference-count pair per sample, see the note on the step below)
    if n > 0.0:
        ux, uy, uz = -a_e[0] / n, -a_e[1] / n, -a_e[2] / n
    else:
        ux, uy, uz = 0.0, 0.0, 1.0
    qw = math.sqrt(max(0.0, 0.5 * (uz + 1.0)))
    if qw > 1e-6:
        corr = (qw, 0.5 * uy / qw, -0.5 * ux / qw, 0.0)
    else:
        corr = (0.0, 1.0, 0.0, 0.0)
    qa = quat_normalize(quat_mul(corr, qa))
    s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3] = qa

    # ---- gyro bias (VQF section 3.3): P in (0.01 °/s)², bias in rad/s
    clip = p[P.bias_clip] * DEG
    q6 = quat_mul(qa, qg)
    r = B.quat_to_matrix(q6)  # R(q_a ⊗ q_g), E6←S
    b0, b1, b2 = s[K.BIAS], s[K.BIAS + 1], s[K.BIAS + 2]
    rb0 = r[0] * b0 + r[1] * b1 + r[2] * b2
    rb1 = r[3] * b0 + r[4] * b1 + r[5] * b2
    rl = (
        B.butter2_step(s, ST.ca, ST.r_lp, 9, 0, r[0]), B.butter2_step(s, ST.ca, ST.r_lp, 9, 1, r[1]),
        B.butter2_step(s, ST.ca, ST.r_lp, 9, 2, r[2]), B.butter2_step(s, ST.ca, ST.r_lp, 9, 3, r[3]),
        B.butter2_step(s, ST.ca, ST.r_lp, 9, 4, r[4]), B.butter2_step(s, ST.ca, ST.r_lp, 9, 5, r[5]),
        B.butter2_step(s, ST.ca, ST.r_lp, 9, 6, r[6]), B.butter2_step(s, ST.ca, ST.r_lp, 9, 7, r[7]),
        B.butter2_step(s, ST.ca, ST.r_lp, 9, 8, r[8]),
    )  # fmt: skip
    blp0 = B.butter2_step(s, ST.ca, ST.bias_lp, 2, 0, rb0)
    blp1 = B.butter2_step(s, ST.ca, ST.bias_lp, 2, 1, rb1)
    # tilt rate: the bias-corrected rate about the two horizontal axes of E6, low-passed over
    # tau_acc_max (drift turned in within the filter's longest memory still needs correcting)
    wx, wy, wz = x[0] - b0, x[1] - b1, x[2] - b2
    wh = math.sqrt((r[0] * wx + r[1] * wy + r[2] * wz) ** 2 + (r[3] * wx + r[4] * wy + r[5] * wz) ** 2)
    s[ST.tilt_rate] += dt / (p[P.tau_acc_max] + dt) * (wh - s[ST.tilt_rate])

    # process noise: the variance grows by (0.1 °/s)² per forgetting time, up to its initial value
    v = 100.0 * dt / p[P.bias_forgetting_time]
    p0 = (p[P.bias_sigma_init] * 100.0) ** 2
    for k in range(3):
        if s[ST.bias_p + 4 * k] < p0:
            s[ST.bias_p + 4 * k] += v
    if K.recovering(s):
        pass  # a gap's error is a step, not a bias: nothing learned until it is corrected
    elif s[ST.rest] != 0.0 and p[P.bias_sigma_rest] > 0.0:
        # at rest the low-passed gyro is the bias itself: H = I
        pr = (p[P.bias_sigma_rest] * 100.0) ** 2
        w = pr * pr / v + pr
        e = (
            min(clip, max(-clip, s[ST.gyr_lp] - b0)),
            min(clip, max(-clip, s[ST.gyr_lp + 1] - b1)),
            min(clip, max(-clip, s[ST.gyr_lp + 2] - b2)),
        )
        B.bias_kalman_update(s, ST.bias_p, K.BIAS, ST.scratch, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), e, (w, w, w), 3)
    elif p[P.bias_sigma_motion] > 0.0:
        # in motion the horizontal correction rate −r/dt is what the bias error turned the
        # estimate by: R b_true ≈ −r/dt + LP(R b̂) on the two horizontal rows
        pm = (p[P.bias_sigma_motion] * 100.0) ** 2
        w = pm * pm / v + pm
        e = (
            min(clip, max(-clip, -uy / dt + blp0 - (rl[0] * b0 + rl[1] * b1 + rl[2] * b2))),
            min(clip, max(-clip, ux / dt + blp1 - (rl[3] * b0 + rl[4] * b1 + rl[5] * b2))),
            0.0,
        )
        B.bias_kalman_update(s, ST.bias_p, K.BIAS, ST.scratch, rl, e, (w, w, w), 2)
    for k in range(3):
        s[K.BIAS + k] = min(clip, max(-clip, s[K.BIAS + k]))
    return q6


@_jit
def _drift_of_the_error_model(s, p, dt, acc_ok, wx, wy, wz, q6):
    """The gyro drift the corrections have not yet removed (``attitude_variance``).

    Inclination: the gyro frame drifts in tilt by r = σ_b + ε |ω̄_h| (residual bias σ_b from
    the bias covariance, scale and misalignment error ε = bias_sigma_motion / tilt_rate_ref
    times the tilt rate: the figures ``_accel_time_constant`` is built on); the low-pass
    removes a share dt/τ_acc of it per accelerometer sample, so u_tilt settles at r τ_acc
    while the accelerometer corrects and grows by r t without it.
    Heading: the residual bias turns it by σ_b per second (u_yaw), the scale error by ε times
    the angle turned about the vertical (u_turn, signed: turning back undoes it); each used
    field sample removes its gain's share k of both (``robust_mag.heading``), so they grow
    while the field is rejected or missing. A ramp is not noise: drifts add as σ, not variance."""
    sb2 = max(s[ST.bias_p], s[ST.bias_p + 4], s[ST.bias_p + 8])
    sigma_b = math.sqrt(max(sb2, 0.0)) * BIAS_P_UNIT
    s[ST.u_tilt] += (sigma_b + gyro_scale_error(p) * s[ST.tilt_rate]) * dt
    if acc_ok:
        s[ST.u_tilt] *= 1.0 - min(1.0, dt / s[ST.coef_tau_acc])
    s[ST.u_yaw] += sigma_b * dt
    # the body rate's component about the vertical of E6: R(q6) row 3 · ω
    q0, q1, q2, q3 = q6
    s[ST.u_turn] += (2.0 * (q1 * q3 - q0 * q2) * wx + 2.0 * (q2 * q3 + q0 * q1) * wy + (q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3) * wz) * dt


@_jit
def gyro_scale_error(p):
    """ε, the gyro's scale and misalignment error (no unit): bias_sigma_motion / tilt_rate_ref
    (0.1 °/s over 20 °/s = 0.5 %, see ``RobustParams.tilt_rate_ref``); 0 when the adaptation is off."""
    return p[P.bias_sigma_motion] / p[P.tilt_rate_ref] if p[P.tilt_rate_ref] > 0.0 else 0.0


# error_model="numpy": divisions by zero give inf/NaN instead of raising (every division is
# guarded). No "nnan"/"reassoc" fast-math: the NaN checks of bad samples must hold.
_step_jit = njit(cache=True, error_model="numpy", fastmath={"contract", "arcp", "afn"})

# The step is laid out for speed. numba counts references to arrays: each time an inlined
# helper receives one, an atomic increment and decrement, which its pruning removes only where
# the control flow is simple (no early return, no array used on one branch only). Left in,
# they took much of the step's time (docs/robust-estimator.md, "Speed"). So the helpers get
# the parameters and the row as tuples of floats and only the state as an array, and the
# batch loop, which holds the state for all its rows, calls two compiled functions, start-up
# and update, each with a single exit.


@_step_jit
def _first_sample(s, params, x, gyro_ok, acc_ok, mag_ok):
    """Until the start: waits for a usable accelerometer sample, then starts the filters."""
    if K.initialise_from_sample(s, x, acc_ok, mag_ok) != K.STARTED:
        return
    p = B.load_tuple(params, N_PARAMS)
    dt0 = x[K.DT] if gyro_ok else 0.01
    # until the tilt rate is measured, assume the fast tilting that tau_acc is meant for
    ref = p[P.tilt_rate_ref] * DEG
    s[ST.tilt_rate] = ref * ((p[P.tau_acc_max] / p[P.tau_acc]) ** 2 - 1.0) if p[P.tau_acc_max] > p[P.tau_acc] else 0.0
    _update_coefficients(s, p, dt0, p[P.tau_acc])
    _start(s, x)
    if mag_ok:
        s[ST.mag_dt] = dt0
        heading(s, p, x, (s[0], s[1], s[2], s[3]))  # q_a = 1: q_a ⊗ q_g = q_g = q


@_step_jit
def _update(s, params, x, acc_ok, mag_ok):
    """One sample with a usable gyroscope after the start (VQF eq. 3: q = q_δ ⊗ q_a ⊗ q_g)."""
    p = B.load_tuple(params, N_PARAMS)
    dt = x[K.DT]
    _update_coefficients(s, p, dt, _accel_time_constant(s, p))
    s[ST.mag_dt] += dt
    s[ST.hi_t] += dt
    # strapdown integration of the bias-corrected rate (VQF eq. 4)
    wx, wy, wz = x[0] - s[K.BIAS], x[1] - s[K.BIAS + 1], x[2] - s[K.BIAS + 2]
    qg = quat_integrate((s[ST.gq], s[ST.gq + 1], s[ST.gq + 2], s[ST.gq + 3]), wx, wy, wz, dt)
    s[ST.gq], s[ST.gq + 1], s[ST.gq + 2], s[ST.gq + 3] = qg
    # R(q_g) once: it rotates the accelerometer into I and feeds the hard-iron block means
    rg = B.quat_to_matrix(qg)
    if acc_ok:
        _rest_detection(s, p, x, dt)
        q6 = _inclination_and_bias(s, p, x, dt, qg, rg)
    else:
        q6 = quat_mul((s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3]), qg)
    _drift_of_the_error_model(s, p, dt, acc_ok, wx, wy, wz, q6)
    if mag_ok:
        hard_iron_and_consistency(s, p, x, dt, rg)
        heading(s, p, x, q6)
    q = quat_mul((s[ST.delta_c], 0.0, 0.0, s[ST.delta_s]), q6)
    lead = 0.5 * p[P.output_lead]
    if lead > 0.0:
        # q ⊗ exp(ω̂ t_lead / 2) to first order: the lead angle is a few mrad, the neglected
        # terms (angle³/24) far below a microradian. |q ⊗ v| = |v| for a unit q, so scaling
        # by 1/|v| normalises exactly
        vx, vy, vz = wx * lead, wy * lead, wz * lead
        inv = 1.0 / math.sqrt(1.0 + vx * vx + vy * vy + vz * vz)
        q = quat_mul(q, (inv, vx * inv, vy * inv, vz * inv))
    K.store_quat(s, q)


@_step_jit
def _bridge_gap(s, params, x, n):
    """Carries the rate across a gap before row ``x`` in n − 1 sub-steps without
    accelerometer or field (``_kernel``, "sample gaps"); no rest is carried across it.
    Returns ``x`` covering the last sub-step."""
    w0 = (s[K.GYR_LAST], s[K.GYR_LAST + 1], s[K.GYR_LAST + 2])
    skipped = (s[K.ACC_SKIPPED], s[K.MAG_SKIPPED])
    dt = x[K.DT] / n
    nan = math.nan
    for j in range(1, n):
        f = j / n
        sub = (w0[0] + f * (x[0] - w0[0]), w0[1] + f * (x[1] - w0[1]), w0[2] + f * (x[2] - w0[2]),
               nan, nan, nan, nan, nan, nan, dt)  # fmt: skip
        K.check_sample(s, sub, True)
        _update(s, params, sub, False, False)
    s[K.ACC_SKIPPED], s[K.MAG_SKIPPED] = skipped
    s[ST.rest_t] = 0.0
    s[ST.rest] = 0.0
    return (x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7], x[8], dt)


@_step_jit
def _take_realignment(s, q_before):
    """Moves a tilt realignment after a gap (``_kernel.realign_tilt``, which turned the
    header's q by r in the earth frame) into q_a: r ⊗ q_δ ⊗ q_a ⊗ q_g = q_δ ⊗ q_a' ⊗ q_g with
    q_a' = q_δ⁻¹ ⊗ r ⊗ q_δ ⊗ q_a. q_a is made each sample from the accelerometer's low-pass
    in I (VQF eq. 9–10), so the low-pass's states turn with it, by q_a'⁻¹ ⊗ q_a: the
    filtered specific force stays as vertical under q_a' as it was under q_a."""
    r = quat_mul(K.load_quat(s), quat_conj(q_before))
    d = (s[ST.delta_c], 0.0, 0.0, s[ST.delta_s])
    qa = (s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3])
    qa_new = quat_normalize(quat_mul(quat_conj(d), quat_mul(r, quat_mul(d, qa))))
    c = quat_mul(quat_conj(qa_new), qa)
    for j in range(2):  # the two delay states of the three channels (butter2_step)
        i = ST.acc_lp + 3 * j
        s[i], s[i + 1], s[i + 2] = quat_rotate(c, (s[i], s[i + 1], s[i + 2]))
    s[ST.aq], s[ST.aq + 1], s[ST.aq + 2], s[ST.aq + 3] = qa_new


@_step_jit
def robust_batch(s, params, rows, out):
    """Advances over the sample rows (N, 10); each row's published q goes to ``out`` (N, 4),
    unless ``out`` is None (``robust_step``)."""
    for i in range(rows.shape[0]):
        # the row's values, not the view rows[i], which would cost a reference-count pair
        x = (rows[i, 0], rows[i, 1], rows[i, 2], rows[i, 3], rows[i, 4],
             rows[i, 5], rows[i, 6], rows[i, 7], rows[i, 8], rows[i, K.DT])  # fmt: skip
        n = K.gap_substeps(s, x)
        if n:
            x = _bridge_gap(s, params, x, n)
        q_before, realignments = K.load_quat(s), s[K.REALIGNMENTS]
        gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
        if s[K.REALIGNMENTS] != realignments:
            _take_realignment(s, q_before)
        if s[K.INITIALISED] == 0.0:
            _first_sample(s, params, x, gyro_ok, acc_ok, mag_ok)
        elif gyro_ok:
            _update(s, params, x, acc_ok, mag_ok)
        if out is not None:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = s[0], s[1], s[2], s[3]


@_step_jit
def robust_step(s, params, row):
    """Advances the robust estimator by one sample row (see ``_kernel``): the batch over
    this one row, so that the per-sample and the batch path run the same code."""
    robust_batch(s, params, row[np.newaxis, :], None)


class RobustEstimator(Estimator):
    """GIMLET, the project's robust estimator: VQF-structured inclination and bias, heading
    with norm/dip, gyro-consistency and hard-iron-learning magnetic rejection."""

    name = "robust"
    Params = RobustParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(robust_step)
    batch = staticmethod(robust_batch)

    def initial_state(self) -> np.ndarray:
        s = super().initial_state()
        p0 = (self.params.bias_sigma_init * 100.0) ** 2
        s[ST.bias_p] = s[ST.bias_p + 4] = s[ST.bias_p + 8] = p0  # diagonal of the 3 × 3 covariance
        s[ST.coef_dt] = -1.0  # forces the first coefficient computation
        s[ST.gain_dt] = -1.0  # and the first gain computation
        return s

    @property
    def diagnostics(self) -> dict[str, float]:
        s = self.state
        return {
            **super().diagnostics,
            "rest": bool(s[ST.rest]),
            "mag_disturbed": bool(s[ST.mag_dist]),
            # False until the start-up field stayed steady while turning (mag_new_first_time):
            # mag_disturbed meanwhile is that confirmation, not a field found disturbed
            "mag_confirmed": bool(s[ST.mag_confirmed]),
            "mag_used": int(s[ST.mag_used]),
            "mag_ref_norm_ut": float(s[ST.mag_ref_norm]),
            "mag_ref_dip_deg": float(np.degrees(s[ST.mag_ref_dip])),
            "hard_iron_ut": s[STATE.slices.hi_h].copy(),
            "hard_iron_trusted": bool(s[ST.hi_ok]),
            # residual / tolerance of the gyro-consistency test (< 1: consistent), no unit
            "consistency_ratio": float(np.sqrt(max(s[ST.cons], 0.0))),
        }

    #: the error model of ``attitude_variance`` (``uncertainty.ObservedErrorModel``)
    #: scales: the largest either data set needs (inclination: BROAD or DIDO, which binds;
    #: heading: BROAD), docs/autopilot.md "Attitude covariance"; well below 1: the drift terms
    #: are worst cases (the scale error's drift partly cancels when the motion turns back) and
    #: the filter follows only part of the sustained acceleration
    observed_error_model: ClassVar[ObservedErrorModel] = ObservedErrorModel(tilt_scale=0.089, heading_scale=0.12)

    def _model_variance(self) -> AttitudeVariance:
        """Roll, pitch, yaw variances, rad²: ``ObservedErrorModel`` over the filter's own record
        of what it has not corrected (``_drift_of_the_error_model``, docs/autopilot.md)."""
        s = self.state
        if not s[K.INITIALISED]:
            return AttitudeVariance.unknown()
        return self.observed_error_model.variance(
            ObservedErrorState(
                tilt_drift=float(s[ST.u_tilt]),
                yaw_drift=float(s[ST.u_yaw]) + float(gyro_scale_error(self._p)) * abs(float(s[ST.u_turn])),
                field_mean_square=float(s[ST.u_field]),
                field_norm=float(s[ST.mag_ref_norm]),
                field_dip=float(s[ST.mag_ref_dip]),
                has_field=bool(np.isfinite(sample_age(s[K.MAG_AGE]))),
                sustained_acceleration=float(s[ST.acc_sustained] ** 2 + s[ST.acc_sustained + 1] ** 2),
            )
        )
