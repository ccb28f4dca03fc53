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

from numba import njit

from ahrs_service.core.layout import Layout, Slot
from ahrs_service.core.quaternion import quat_from_gravity_and_field, quat_from_rotvec, quat_rotate_inv, vec_is_usable
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
    ],
)
Q, INITIALISED, ACC_SKIPPED, MAG_SKIPPED, GYR_SKIPPED, BIAS, ACC_AGE, MAG_AGE = STATE_HEADER.index
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
    return gyro_ok, acc_ok, mag_ok


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
    if steady_state(s, prev, x):
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
    if steady:
        for i in range(3):
            s[BIAS + i] += gain * (x[i] - s[BIAS + i])
