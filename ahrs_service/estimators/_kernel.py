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

from ahrs_service.estimators.layout import Layout, Slot
from ahrs_service.quaternion import quat_from_gravity_and_field, vec_is_usable

#: the sample row: one sample's three sensors and its time step
SAMPLE_ROW = Layout(
    "sample row",
    [
        Slot("gyr", 3, "gyroscope, rad/s, sensor axes"),
        Slot("acc", 3, "specific force, m/s², sensor axes"),
        Slot("mag", 3, "magnetic field, µT, sensor axes (NaN: no new field)"),
        Slot("dt", 1, "time since the previous sample, s"),
    ],
)
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
