"""Pieces every compiled estimator step shares: the sample row, the state header, validity
checks and start-up from the first usable samples.

A *sample row* is a float64 array ``[gx, gy, gz, ax, ay, az, mx, my, mz, dt]``: gyroscope
rad/s, specific force m/s², magnetic field µT (NaN when there is no magnetometer), and the
time step in seconds since the previous sample. The per-sample service path fills one such
row; batch runs stack them into an (N, 10) array — both go through the same step function.

Every estimator state is a float64 array whose first ``HEADER`` entries (``STATE_HEADER``)
mean the same everywhere, so the service, logs and diagnostics read them without knowing the
estimator. Code outside the kernels reads rows and headers through ``ROW_SLICES`` and
``HEADER_SLICES`` (or the ``Estimator`` properties), never by number.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ahrs_service.core.layout import Layout, Slot
from ahrs_service.core.quaternion import (
    quat_from_gravity_and_field,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotate_inv,
    vec_is_usable,
)
from ahrs_service.core.samples import SAMPLE_ROW

GYR, ACC, MAG, DT = SAMPLE_ROW.index  # first columns, constants in compiled code
ROW = SAMPLE_ROW.end  # row length

#: the state header every estimator's state array starts with
STATE_HEADER = Layout(
    "state header",
    [
        Slot("q", 4, "q_earth←body [w, x, y, z]"),
        Slot("initialised", 1, "1.0 once the attitude was set from gravity (and field)"),
        Slot("acc_skipped", 1, "count of samples whose accelerometer correction was skipped"),
        Slot("mag_skipped", 1, "count of samples whose magnetometer correction was skipped (includes no magnetometer)"),
        Slot("gyr_skipped", 1, "count of samples whose gyro/dt could not be integrated"),
        Slot("bias", 3, "gyro-bias estimate, rad/s, body frame (zero where not estimated)"),
        Slot("acc_age", 1, "time since the last usable accelerometer sample, s (NO_SAMPLE_YET: none yet)"),
        Slot("mag_age", 1, "time since the last usable magnetometer sample, s (NO_SAMPLE_YET: none yet)"),
        Slot("gyr_last", 3, "the last usable gyroscope sample, rad/s (the start of a gap's bridge)"),
        Slot("step_typical", 1, "the typical time step, s, learned from steps that are not gaps (0: none yet)"),
        Slot("gap_run", 1, "count of consecutive gap steps (a lasting change of rate ends a run)"),
        Slot("gaps", 1, "count of gaps bridged"),
        Slot("gap_error", 1, "1σ of the rotation the gaps left unobserved and the corrections have not yet removed, rad"),
        Slot("gap_sigma", 1, "the 1σ attitude_variance reports for it in roll and pitch: it decays with GAP_SIGMA_TIME, rad"),
        Slot("gap_sigma_heading", 1, "the same in heading: it decays with GAP_HEADING_SIGMA_TIME while the field is usable, rad"),
        Slot("gyr_lp", 3, "the gyroscope rate low-passed with RATE_SPREAD_TIME, rad/s"),
        Slot("gyr_spread", 1, "mean square of the rate about gyr_lp, (rad/s)²: how much the rate wanders"),
        Slot("force_lp", 3, "the specific force in the estimated earth frame low-passed over REALIGN_WINDOW, m/s²"),
        Slot("tilt_disagreement", 1, "mean square sine of force_lp's angle from the vertical over DISAGREEMENT_TIME"),
        Slot("realign_force", 3, "sum of the specific force in the estimated earth frame over the realignment window, m/s²"),
        Slot("realign_square", 1, "sum of its squared magnitude, (m/s²)²"),
        Slot("realign_count", 1, "count of samples in the realignment window"),
        Slot("realign_time", 1, "length of the realignment window so far, s"),
        Slot("realignments", 1, "count of tilt realignments after gaps"),
    ],
)
(Q, INITIALISED, ACC_SKIPPED, MAG_SKIPPED, GYR_SKIPPED, BIAS, ACC_AGE, MAG_AGE,
 GYR_LAST, STEP_TYPICAL, GAP_RUN, GAPS, GAP_ERROR, GAP_SIGMA, GAP_SIGMA_HEADING, GYR_LP, GYR_SPREAD, FORCE_LP, TILT_DISAGREEMENT,
 REALIGN_FORCE, REALIGN_SQUARE, REALIGN_COUNT, REALIGN_TIME, REALIGNMENTS) = STATE_HEADER.index  # fmt: skip
HEADER = STATE_HEADER.end  # where an estimator's own slots start
#: acc_age / mag_age before the first usable sample (a state stays finite: logs, checks)
NO_SAMPLE_YET = -1.0

#: slices for Python code outside the kernels: ``state[HEADER_SLICES.bias]``, ``row[ROW_SLICES.mag]``
HEADER_SLICES = STATE_HEADER.slices
ROW_SLICES = SAMPLE_ROW.slices

_jit = njit(cache=True, inline="always")


@_jit
def check_sample(s, x, uses_mag):
    """Validity of the three inputs of one row; counts each skipped correction in the header
    and keeps the age of the newest usable accelerometer and magnetometer sample (the error
    models of ``uncertainty`` grow with it).

    Returns (gyro_ok, acc_ok, mag_ok). gyro_ok also requires a finite dt > 0.
    """
    dt = x[DT]
    gyro_ok = math.isfinite(x[0] + x[1] + x[2]) and dt > 0.0 and dt < 1e3
    acc_ok = vec_is_usable(x[3], x[4], x[5])
    mag_ok = uses_mag and vec_is_usable(x[6], x[7], x[8])
    if not gyro_ok:
        s[GYR_SKIPPED] += 1.0
    if not acc_ok:
        s[ACC_SKIPPED] += 1.0
    if uses_mag and not mag_ok:
        s[MAG_SKIPPED] += 1.0
    if acc_ok:
        s[ACC_AGE] = 0.0
    elif gyro_ok and s[ACC_AGE] >= 0.0:
        s[ACC_AGE] += dt
    if mag_ok:
        s[MAG_AGE] = 0.0
    elif gyro_ok and s[MAG_AGE] >= 0.0:
        s[MAG_AGE] += dt
    if gyro_ok:
        s[GYR_LAST], s[GYR_LAST + 1], s[GYR_LAST + 2] = x[0], x[1], x[2]
        _track_rate_spread(s, x, dt)
        if acc_ok and s[GAP_SIGMA] > 0.0:
            # the accelerometer observes the tilt again: the corrections remove the gap's error
            s[GAP_ERROR] *= math.exp(-dt / GAP_RECOVERY_TIME)
            s[GAP_SIGMA] *= math.exp(-dt / GAP_SIGMA_TIME)
        if mag_ok and s[GAP_SIGMA_HEADING] > 0.0:
            s[GAP_SIGMA_HEADING] *= math.exp(-dt / GAP_HEADING_SIGMA_TIME)
        if acc_ok and s[INITIALISED] != 0.0:
            if s[GAP_ERROR] > GAP_ERROR_REALIGN:
                realign_tilt(s, x)
            else:
                if s[REALIGN_COUNT] != 0.0:
                    _restart_realign_window(s)  # the error shrank below it meanwhile
                _track_tilt_disagreement(s, x, dt)
    return gyro_ok, acc_ok, mag_ok


# ------------------------------------------------------------------------------- sample gaps
# A gap is a time step several typical steps long: samples were lost (FIFO overflow, a host
# stall, a dropped link). What every estimator does across one (docs/gaps.md):
#
# * the rotation during the gap is unobserved; the gyroscope rate is carried across it,
#   interpolated linearly from the last sample before the gap to the first after, in
#   sub-steps no longer than the typical step (at most GAP_MAX_SUBSTEPS), each integrated by
#   the estimator's own step with no accelerometer or magnetometer sample — a prediction
#   without correction, never one huge integration step and nothing learned across the gap;
# * the interpolation's error is about half the change of rate times the gap's length (the
#   rate may have changed anywhere in it), with how much the rate wandered before the gap
#   (``gap_variance``): gap_error, the 1σ of the rotation the gaps left unobserved, grows
#   by it (root sum square), and so do gap_sigma and gap_sigma_heading, which the variances
#   the estimators report add and which decay more slowly (GAP_SIGMA_TIME, and for the
#   heading GAP_HEADING_SIGMA_TIME while the field is usable);
# * while gap_error is large the estimators correct faster (``recovery_gain``) and learn no
#   gyro bias and no rest (``recovering``): an error the gap made is a step, not a drift, and
#   taken for a bias it would turn into one. gap_error decays with GAP_RECOVERY_TIME while
#   the accelerometer is usable;
# * while gap_error is above GAP_ERROR_REALIGN the tilt is realigned (``realign_tilt``): the
#   specific force, averaged in the estimated earth frame over REALIGN_WINDOW, is one tilt
#   measurement, weighed against gap_error as a Kalman update weighs a measurement against
#   its prior (gain P / (P + R)). A gap that hid a large rotation (a shock, an outage) is
#   then corrected in a fraction of a second, not with the estimator's own gain, which is
#   made for errors of a degree; in motion R is large and the realignment does little.

#: a step longer than this many typical steps is a gap
GAP_STEPS = 4.0
#: the weight with which a step that is not a gap moves the typical step
STEP_TYPICAL_WEIGHT = 0.01
#: this many gap steps in a row are a new rate, not lost samples: the typical step follows
GAP_RUN_NEW_RATE = 8
#: the most sub-steps a gap is bridged with (a long outage is bridged with longer sub-steps)
GAP_MAX_SUBSTEPS = 400
#: time constant with which the corrections are taken to remove a gap's error, s
GAP_RECOVERY_TIME = 1.0
#: time constant with which the reported 1σ of a gap's error decays, s: slower than
#: GAP_RECOVERY_TIME, because a filter tuned to trust its gyro corrects a step over seconds and
#: a realignment in motion leaves part of it; an overconfident σ is the dangerous direction
#: for an autopilot fusing it (docs/autopilot.md)
GAP_SIGMA_TIME = 3.0
#: the same for the heading, which only the magnetometer corrects, slowly and gated (the tilt
#: realignment leaves it), s
GAP_HEADING_SIGMA_TIME = 15.0
#: gap_error above which the correction gain is raised in proportion, rad (2°: about the
#: estimators' own error in motion, which their usual gain is made for)
GAP_ERROR_BOOST = 2.0 * math.pi / 180.0
#: time constant of the rate's low-pass whose spread measures how the rate wanders, s
RATE_SPREAD_TIME = 0.5
#: the largest factor on a correction gain after a gap (x-io Fusion's start-up gain is 10×
#: its default: the same idea, an error of unknown size corrected fast, then the usual gain)
GAP_GAIN_MAX = 10.0
#: below this gap_error the estimator learns bias and rest again, rad (2°, GAP_ERROR_BOOST:
#: an error below the estimators' own error in motion is noise to them; above it, a step that
#: a bias learned meanwhile would keep)
GAP_ERROR_LEARN = GAP_ERROR_BOOST
#: above this gap_error the tilt is realigned from the averaged specific force, rad
GAP_ERROR_REALIGN = GAP_ERROR_BOOST
#: length of the window whose mean specific force is one tilt measurement, s
REALIGN_WINDOW = 0.25
#: the least 1σ of that measurement's tilt before its own spread is counted, rad: the
#: horizontal acceleration it cannot tell from a tilt (5°: about 0.9 m/s² held over the window)
REALIGN_TILT_NOISE = 5.0 * math.pi / 180.0
#: time over which the window mean's disagreement with the estimated vertical before a gap is
#: averaged (the motion's sustained accelerations: a turn, a circle), s
DISAGREEMENT_TIME = 5.0


@_jit
def _track_rate_spread(s, x, dt):
    """Keeps gyr_lp and gyr_spread: how far the rate wanders within RATE_SPREAD_TIME (what a
    gap cannot observe). Until the attitude is initialised the low-pass follows the rate."""
    if s[INITIALISED] == 0.0:
        s[GYR_LP], s[GYR_LP + 1], s[GYR_LP + 2] = x[0], x[1], x[2]
        return
    k = min(1.0, dt / RATE_SPREAD_TIME)
    spread = 0.0
    for i in range(3):
        d = x[i] - s[GYR_LP + i]
        spread += d * d
        s[GYR_LP + i] += k * d
    s[GYR_SPREAD] += k * (spread - s[GYR_SPREAD])


@_jit
def gap_substeps(s, x):
    """How many sub-steps bridge the gap before row ``x`` (0: no gap); keeps the typical step.

    A gap's bridge needs a rate before it, so the first steps of a run are never gaps. Returns
    n ≥ 2 for a gap: n − 1 bridging rows (``bridge_row``) and the row itself, each covering
    dt / n; adds the gap's unobserved rotation to ``gap_error``.
    """
    dt = x[DT]
    if not (dt > 0.0 and dt < 1e3 and math.isfinite(x[0] + x[1] + x[2])):
        return 0
    typical = s[STEP_TYPICAL]
    if typical <= 0.0:
        s[STEP_TYPICAL] = dt
        return 0
    if dt <= GAP_STEPS * typical or s[INITIALISED] == 0.0:
        s[GAP_RUN] = 0.0
        s[STEP_TYPICAL] += STEP_TYPICAL_WEIGHT * (dt - typical)
        return 0
    s[GAP_RUN] += 1.0
    if s[GAP_RUN] >= GAP_RUN_NEW_RATE:
        s[STEP_TYPICAL] = dt  # the rate changed: these steps are the sensor's new period
        s[GAP_RUN] = 0.0
        return 0
    s[GAPS] += 1.0
    variance = gap_variance(s, x, dt)
    s[GAP_ERROR] = math.sqrt(s[GAP_ERROR] ** 2 + variance)
    s[GAP_SIGMA] = math.sqrt(s[GAP_SIGMA] ** 2 + variance)
    s[GAP_SIGMA_HEADING] = math.sqrt(s[GAP_SIGMA_HEADING] ** 2 + variance)
    return max(2, min(GAP_MAX_SUBSTEPS, int(dt / typical + 0.5)))


@_jit
def gap_variance(s, x, gap):
    """Variance (rad²) of the rotation a gap of ``gap`` s before row ``x`` leaves unobserved.

    Two parts, root sum square: the rate interpolated across the gap may be wrong by up to
    half its change (0.5·|Δω|·gap: the change may have happened anywhere in it), and the rate
    wanders within the gap as it did before it: its spread σ about its low-pass, over a gap
    shorter than RATE_SPREAD_TIME mostly a smooth change the interpolation follows
    (σ·gap²/(2·RATE_SPREAD_TIME)), over a longer one up to σ·gap/2.
    """
    d0, d1, d2 = x[0] - s[GYR_LAST], x[1] - s[GYR_LAST + 1], x[2] - s[GYR_LAST + 2]
    step_change = 0.5 * math.sqrt(d0 * d0 + d1 * d1 + d2 * d2) * gap
    wander = 0.5 * math.sqrt(s[GYR_SPREAD]) * gap * min(1.0, gap / RATE_SPREAD_TIME)
    return step_change * step_change + wander * wander


@_jit
def begin_bridge(s):
    """(rate before the gap, the counters to restore, a scratch row) for ``bridge_row``."""
    return (s[GYR_LAST], s[GYR_LAST + 1], s[GYR_LAST + 2]), (s[ACC_SKIPPED], s[MAG_SKIPPED]), np.empty(ROW)


@_jit
def bridge_row(sub, w0, x, j, n):
    """The j-th of the n − 1 rows that bridge a gap before ``x``: the rate interpolated from
    ``w0`` (the last sample's) to ``x``'s, no accelerometer or magnetometer, dt = x's dt / n."""
    f = j / n
    for k in range(3):
        sub[k] = w0[k] + f * (x[k] - w0[k])
        sub[ACC + k] = math.nan
        sub[MAG + k] = math.nan
    sub[DT] = x[DT] / n
    return sub


@_jit
def end_bridge(s, saved, x, n):
    """The row after its gap's bridge: ``x`` covering the last sub-step. The bridging rows'
    missing accelerometer and magnetometer samples were not the sensor's: they are not counted
    as skipped corrections."""
    s[ACC_SKIPPED], s[MAG_SKIPPED] = saved
    last = x.copy()
    last[DT] = x[DT] / n
    return last


@_jit
def recovery_gain(s):
    """The factor (≥ 1) on a correction gain while a gap's error is being corrected."""
    return min(GAP_GAIN_MAX, max(1.0, s[GAP_ERROR] / GAP_ERROR_BOOST))


@_jit
def _track_tilt_disagreement(s, x, dt):
    """Keeps force_lp and tilt_disagreement while no gap's error is being corrected: how far
    the specific force averaged as the realignment averages it lies from the vertical the
    estimator holds. In motion that is the horizontal acceleration a realignment would take
    for a tilt (a circle, a coordinated turn): its measurement noise in this motion."""
    fe = quat_rotate(load_quat(s), (x[3], x[4], x[5]))
    k = min(1.0, dt / REALIGN_WINDOW)
    for i in range(3):
        s[FORCE_LP + i] += k * (fe[i] - s[FORCE_LP + i])
    hx, hy, vz = s[FORCE_LP], s[FORCE_LP + 1], s[FORCE_LP + 2]
    n2 = hx * hx + hy * hy + vz * vz
    if n2 > 0.0:
        s[TILT_DISAGREEMENT] += min(1.0, dt / DISAGREEMENT_TIME) * ((hx * hx + hy * hy) / n2 - s[TILT_DISAGREEMENT])


@_jit
def _restart_realign_window(s):
    for i in range(REALIGN_FORCE, REALIGN_TIME + 1):
        s[i] = 0.0


@_jit
def realign_tilt(s, x):
    """Adds a usable accelerometer sample to the realignment window; at the window's end
    turns the estimate towards the tilt it measured, by the Kalman gain P / (P + R).

    P = gap_error²; R = the larger of REALIGN_TILT_NOISE² and tilt_disagreement (how far such
    a mean lay from the estimated vertical before the gap) + the window's spread about its
    mean over n g² (vibration) + |‖f̄‖²/g² − 1| (an acceleration it did not average out). The
    turn is about a horizontal axis in the earth frame, so the heading stays; gap_error
    becomes the update's posterior √(P R / (P + R)).
    """
    fe = quat_rotate(load_quat(s), (x[3], x[4], x[5]))
    for i in range(3):
        s[REALIGN_FORCE + i] += fe[i]
    s[REALIGN_SQUARE] += fe[0] * fe[0] + fe[1] * fe[1] + fe[2] * fe[2]
    s[REALIGN_COUNT] += 1.0
    s[REALIGN_TIME] += x[DT]
    if s[REALIGN_TIME] < REALIGN_WINDOW:
        return
    n = s[REALIGN_COUNT]
    mx, my, mz = s[REALIGN_FORCE] / n, s[REALIGN_FORCE + 1] / n, s[REALIGN_FORCE + 2] / n
    norm = math.sqrt(mx * mx + my * my + mz * mz)
    spread = max(0.0, s[REALIGN_SQUARE] / n - norm * norm)
    _restart_realign_window(s)
    if not norm > 0.0:
        return
    r = (max(REALIGN_TILT_NOISE**2, s[TILT_DISAGREEMENT]) + spread / (n * GRAVITY * GRAVITY)
         + abs(norm * norm / (GRAVITY * GRAVITY) - 1.0))
    p = s[GAP_ERROR] ** 2
    gain = p / (p + r)
    # the specific force at rest points up, -z in NED: turn its measured direction onto it
    ux, uy, uz = mx / norm, my / norm, mz / norm
    ax, ay = -uy, ux  # u × (0, 0, -1)
    sine = math.sqrt(ax * ax + ay * ay)
    if sine > 1e-12:
        angle = gain * math.atan2(sine, -uz) / sine
        store_quat(s, quat_normalize(quat_mul(quat_from_rotvec(ax * angle, ay * angle, 0.0), load_quat(s))))
    s[GAP_ERROR] = math.sqrt(p * r / (p + r))
    s[REALIGNMENTS] += 1.0


@_jit
def recovering(s):
    """Whether a gap's error is still large: bias and rest are not learned meanwhile."""
    return s[GAP_ERROR] > GAP_ERROR_LEARN


GRAVITY = 9.81  # m/s², the nominal specific force at rest of the accelerometer gates


@_jit
def acc_disturbance(s, i, x, tau):
    """How far the specific force is from gravity alone, |‖f̄‖/g − 1|, for a usable sample.

    ``tau`` (s) 0: f̄ = f, this sample's own. Above 0: f̄ is f low-passed with time constant
    ``tau`` in the body frame, turned with the gyro each sample so a rotation does not shrink it
    (3 slots from ``s[i]``, zero before the first sample): vibration averages out of f̄, a
    sustained acceleration does not.
    """
    fx, fy, fz = x[3], x[4], x[5]
    if tau > 0.0:
        dt = x[DT]
        lx, ly, lz = s[i], s[i + 1], s[i + 2]
        if lx == 0.0 and ly == 0.0 and lz == 0.0:
            lx, ly, lz = fx, fy, fz
        elif dt > 0.0 and math.isfinite(x[0] + x[1] + x[2]):
            lx, ly, lz = quat_rotate_inv(quat_from_rotvec(x[0] * dt, x[1] * dt, x[2] * dt), (lx, ly, lz))
            k = 1.0 - math.exp(-dt / tau)
            lx += k * (fx - lx)
            ly += k * (fy - ly)
            lz += k * (fz - lz)
        s[i], s[i + 1], s[i + 2] = lx, ly, lz
        fx, fy, fz = lx, ly, lz
    return abs(math.sqrt(fx * fx + fy * fy + fz * fz) / GRAVITY - 1.0)


RUNNING, WAITING, STARTED = 0, 1, 2  # initialise_from_sample results


@_jit
def initialise_from_sample(s, x, acc_ok, mag_ok):
    """Sets the attitude from the first usable accelerometer (and magnetometer) sample.

    Returns RUNNING (0) once initialised, WAITING while no usable accelerometer sample has
    come, STARTED when this sample initialised the state. Any non-zero result means "do not
    update with this sample": until the start the estimate stays at identity, for every
    estimator alike (none converges from identity when it can start from the sensors).
    """
    if s[INITIALISED] != 0.0:
        return RUNNING
    if not acc_ok:
        return WAITING
    q = quat_from_gravity_and_field(x[3], x[4], x[5], x[6], x[7], x[8], mag_ok)
    s[Q], s[Q + 1], s[Q + 2], s[Q + 3] = q
    s[INITIALISED] = 1.0
    return STARTED


@_jit
def store_quat(s, q):
    s[Q], s[Q + 1], s[Q + 2], s[Q + 3] = q


@_jit
def load_quat(s):
    return (s[Q], s[Q + 1], s[Q + 2], s[Q + 3])


# ------------------------------------------------------------------ magnetic-disturbance gate
# Not in any source paper (the project's addition, docs/tuning.md): a magnet near the sensor
# changes the measured field's magnitude and its dip below the horizon, which earth's field
# keeps. A filter that uses the gate keeps two slots, MAG_REFERENCE_SLOTS, in its own layout:
# a reference magnitude and dip learned from the field samples the gate accepted (never from
# outside the filter), and passes their first index to mag_gate_accepts.

#: the gate's two state slots, for an estimator's own Layout (``*K.MAG_REFERENCE_SLOTS``)
MAG_REFERENCE_SLOTS = (
    Slot("mag_norm_ref", 1, "reference field magnitude, µT (0 until the first field sample)"),
    Slot("mag_dip_ref", 1, "reference sine of the field's dip below the horizon"),
)
#: time constant with which the field reference follows accepted samples, s
MAG_REF_TAU = 10.0


@_jit
def mag_gate_accepts(s, ref, norm, dip_sine, gate, dt):
    """Whether a field sample looks like earth's field; learns the reference from it if so.

    ``ref`` is the index of the gate's slots (MAG_REFERENCE_SLOTS) in ``s``; ``norm`` the
    sample's magnitude (µT); ``dip_sine`` the down component of the unit field seen in the
    earth frame by the filter's estimate; ``gate`` the largest |‖m‖/m_ref − 1| + |sin δ −
    sin δ_ref| accepted (1e9: every sample). The first sample sets the reference; accepted
    samples move it with time constant MAG_REF_TAU, so it follows slow changes of the field
    (and of a magnet fixed to the sensor) but not a magnet passing by.
    """
    if s[ref] == 0.0:
        s[ref], s[ref + 1] = norm, dip_sine
    if abs(norm / s[ref] - 1.0) + abs(dip_sine - s[ref + 1]) > gate:
        return False
    k = min(1.0, dt / MAG_REF_TAU)
    s[ref] += k * (norm - s[ref])
    s[ref + 1] += k * (dip_sine - s[ref + 1])
    return True


# ------------------------------------------------------------- gyro bias from steady states
# The bias estimate of R.G. Valenti's own implementation of his filter (the
# ``imu_complementary_filter`` of ROS ``imu_tools``, BSD, CCNY Robotics Lab 2015:
# ``checkState``/``updateBiases``), for the filters without a bias model of their own: while the
# sensor is in a steady state the bias follows the gyro by a low-pass filter. A filter that
# uses it keeps REST_BIAS_SLOTS in its own layout, the bias itself in the header's BIAS slots.

#: the previous gyro sample, for an estimator's own Layout (``*K.REST_BIAS_SLOTS``)
REST_BIAS_SLOTS = (Slot("gyr_prev", 3, "the previous sample's gyroscope reading, rad/s (steady-state test)"),)
#: steady-state thresholds of imu_tools: specific-force magnitude off g (m/s²), each gyro axis's
#: change from the previous sample and its distance from the bias estimate (rad/s)
STEADY_ACC = 0.1
STEADY_GYRO_DELTA = 0.01
STEADY_GYRO = 0.2


@_jit
def steady_state(s, prev, x):
    """imu_tools' steady-state test of one sample; keeps ω for the next test.

    ``prev`` is the index of REST_BIAS_SLOTS in ``s``.
    """
    na = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    steady = math.isfinite(na) and abs(na - GRAVITY) <= STEADY_ACC
    for i in range(3):
        if abs(x[i] - s[prev + i]) > STEADY_GYRO_DELTA or abs(x[i] - s[BIAS + i]) > STEADY_GYRO:
            steady = False
    for i in range(3):
        s[prev + i] = x[i]
    return steady


@_jit
def rest_bias_update(s, prev, x, gain):
    """b ← b + gain (ω − b) when the sample is a steady state; keeps ω for the next test.

    ``prev`` is the index of REST_BIAS_SLOTS in ``s``; ``gain`` the fraction per sample.
    """
    if steady_state(s, prev, x) and not recovering(s):
        for i in range(3):
            s[BIAS + i] += gain * (x[i] - s[BIAS + i])


#: the share of steady samples of rest_share_bias_update, for an estimator's own Layout
REST_SHARE_SLOTS = (Slot("rest_share", 1, "low-passed share of steady-state samples (0–1)"),)
#: the share of recent samples that must be steady states for the sensor to count as resting
REST_SHARE_MIN = 0.5


@_jit
def rest_share_bias_update(s, prev, share, x, gain, tau, dt):
    """rest_bias_update, but a steady sample updates the bias only while most recent samples
    were steady states: the share of steady samples low-passed with time constant ``tau`` (s)
    is at least REST_SHARE_MIN. Per sample the test also passes during motion, in short runs,
    and each such sample moves the bias towards a rate of the motion; at rest most samples
    pass it, so a majority keeps rest learning and drops those runs (figures:
    docs/estimators-paper1-3.md, "Why the defaults: measured figures"). ``tau`` 0:
    rest_bias_update itself.

    ``share`` is the index of REST_SHARE_SLOTS in ``s``.
    """
    steady = steady_state(s, prev, x)
    if tau > 0.0:
        s[share] += (1.0 - math.exp(-dt / tau)) * ((1.0 if steady else 0.0) - s[share])
        if s[share] < REST_SHARE_MIN:
            steady = False
    if steady and not recovering(s):
        for i in range(3):
            s[BIAS + i] += gain * (x[i] - s[BIAS + i])
