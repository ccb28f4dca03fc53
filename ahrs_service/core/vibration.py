"""Vibration levels and accelerometer clipping, as ArduPilot computes them for VIBRATION (message 241).

Follows ArduPilot's ``AP_InertialSensor::calc_vibration_and_clipping`` and
``get_vibration_levels`` (``libraries/AP_InertialSensor/AP_InertialSensor.cpp``, GPL-3.0; the
method is re-implemented here from its description, no code is copied), which every
accelerometer backend calls once per raw sample from
``AP_InertialSensor_Backend::_notify_new_accel_raw_sample`` with the rotated and corrected
specific force and the sample's dt, and which ``GCS_MAVLINK::send_vibration``
(``libraries/GCS_MAVLink/GCS_Common.cpp``) publishes:

* **floor** — each axis low-passed at ``FLOOR_HZ`` (5 Hz, ``AP_INERTIAL_SENSOR_ACCEL_VIBE_FLOOR_FILT_HZ``);
* **vibration** — the squared difference of the sample from that floor, low-passed at
  ``VIBE_HZ`` (2 Hz, ``AP_INERTIAL_SENSOR_ACCEL_VIBE_FILT_HZ``); the level is its square root
  (m/s², an RMS of what is above ~5 Hz);
* **clipping** — a sample with any axis beyond the clip limit counts once. ArduPilot's limit
  is the backend's ``_clip_limit``, by default (16 − 0.5) g; here a sample also counts when the
  driver flagged the accelerometer saturated (``ACC_SATURATED``: its raw counts hit the part's
  full scale, whatever range the part is set to).

The two filters are ArduPilot's first-order ``LowPassFilter`` with a per-sample dt:
``alpha = dt / (dt + 1/(2π·fc))``, ``out += (x − out)·alpha``. One difference, so a start
does not read as vibration: the floor starts at the first sample (not at 0).

PX4 fills the same message differently (``src/modules/mavlink/streams/VIBRATION.hpp``):
vibration_x/y/z are not per-axis levels but the primary IMU's delta-angle coning metric, gyro
and accel high-frequency metrics (filtered length of successive delta differences, from
``vehicle_imu_status``), and clipping_N is the sum over axes of IMU N's per-axis clip counts.
A ground station reading our VIBRATION should read it as ArduPilot's.

The computation is vectorised over rows: :meth:`VibrationMonitor.update` takes one sample row
or a block of them (the rows the estimator is fed: ``[gx, gy, gz, ax, ay, az, mx, my, mz,
dt]``, body FRD, m/s², s) and runs one compiled loop over them, so that a block of rows costs
about what one row does: the call, not the rows, costs (``benchmarks/vibration.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ahrs_service.core.layout import Layout, Slot
from ahrs_service.core.samples import ACC_SATURATED, ACC_VALID, SAMPLE_ROW

FLOOR_HZ = 5.0  # Hz, the floor filter (ArduPilot AP_INERTIAL_SENSOR_ACCEL_VIBE_FLOOR_FILT_HZ)
VIBE_HZ = 2.0  # Hz, the filter of the squared difference (AP_INERTIAL_SENSOR_ACCEL_VIBE_FILT_HZ)
STANDARD_GRAVITY = 9.80665  # m/s²
#: ArduPilot's default clip limit (AP_InertialSensor_Backend::_clip_limit), m/s²
CLIP_LIMIT_MSS = (16.0 - 0.5) * STANDARD_GRAVITY



@dataclass(frozen=True, slots=True)
class VibrationLevels:
    """What VIBRATION carries: levels per body axis (m/s², RMS above ~5 Hz) and the clipping
    count of each accelerometer (this service has one: index 0; the others stay 0)."""

    x: float
    y: float
    z: float
    clipping: tuple[int, int, int]


_FLOOR_RC = 1.0 / (2.0 * math.pi * FLOOR_HZ)  # s, the floor filter's time constant
_VIBE_RC = 1.0 / (2.0 * math.pi * VIBE_HZ)  # s
#: the filter state, one float64 array (one argument for the compiled loop: each argument costs
#: a type check per call, and the service calls it once per sample)
STATE = Layout("vibration state", [
    Slot("floor", 3, "the 5 Hz floor per body axis x, y, z, m/s²"),
    Slot("vibe_sq", 3, "the 2 Hz-filtered squared difference from the floor per axis, (m/s²)²"),
    Slot("seen", 1, "1.0 once a valid sample came (the floor starts at it)"),
    Slot("clip_limit", 1, "a specific force beyond this on any axis is clipping, m/s²"),
    Slot("clipped", 1, "clipped samples since start"),
])
_S = STATE.index  # constants in the compiled loop
_R = SAMPLE_ROW.index  # the sample row's columns: gyr, acc, mag, dt


@numba.njit(cache=True)
def _step(rows, i, f, st):
    """One sample: row ``i`` of ``rows`` with validity ``flags`` ``f``; updates ``st`` in place."""
    limit = st[_S.clip_limit]
    clipped = (f & ACC_SATURATED) != 0  # the part saturated ...
    valid = (f & ACC_VALID) != 0
    for k in range(3):
        a = rows[i, _R.acc + k]
        clipped |= abs(a) > limit  # ... or any axis beyond the limit
        valid &= math.isfinite(a)
    if clipped:
        st[_S.clipped] += 1.0
    dt = rows[i, _R.dt]
    if not valid or not (dt > 0.0 and math.isfinite(dt)):
        return  # no reading to filter
    if st[_S.seen] == 0.0:
        for k in range(3):
            st[_S.floor + k] = rows[i, _R.acc + k]
        st[_S.seen] = 1.0
    alpha_floor = dt / (dt + _FLOOR_RC)  # ArduPilot's LowPassFilter: alpha = dt / (dt + RC)
    alpha_vibe = dt / (dt + _VIBE_RC)
    for k in range(3):
        a = rows[i, _R.acc + k]
        st[_S.floor + k] += (a - st[_S.floor + k]) * alpha_floor  # floor at 5 Hz
        d = a - st[_S.floor + k]
        st[_S.vibe_sq + k] += (d * d - st[_S.vibe_sq + k]) * alpha_vibe  # squared difference at 2 Hz


@numba.njit(cache=True)
def _vibration_block(rows, flags, st):
    """Every row of ``rows`` (n, 10) with ``flags`` (n,), in order."""
    for i in range(rows.shape[0]):
        _step(rows, i, flags[i], st)


@numba.njit(cache=True)
def _vibration_row(row, flag, st):
    """One sample row (10,): the service's per-sample path, without making a (1, 10) view."""
    _step(row.reshape((1, row.shape[0])), 0, flag, st)


class VibrationMonitor:
    """Vibration levels and clipping count of one accelerometer, fed with sample rows.

    clip_limit_mss: a specific force beyond this on any axis counts as clipping (m/s²).
    """

    def __init__(self, clip_limit_mss: float = CLIP_LIMIT_MSS) -> None:
        self.clip_limit_mss = float(clip_limit_mss)
        self._st = np.zeros(STATE.end)
        self._st[_S.clip_limit] = self.clip_limit_mss

    @property
    def floor(self) -> np.ndarray:
        """(3,) m/s², the 5 Hz floor per body axis (a copy)."""
        return self._st[STATE.slices.floor].copy()

    @property
    def clipping(self) -> int:
        """Clipped samples since start."""
        return int(self._st[_S.clipped])

    def update(self, rows: np.ndarray, flags: np.ndarray | int) -> None:
        """Feeds sample rows (10,) or (n, 10) as fed to the estimator, with their validity
        ``flags`` (an int for one row, else (n,))."""
        if rows.ndim == 1:
            _vibration_row(rows, int(flags), self._st)
        else:
            _vibration_block(rows, np.asarray(flags, dtype=np.int64), self._st)

    @staticmethod
    def warm_up() -> None:
        """Compiles (or loads from numba's cache) both entries, so the loop's first sample
        does not pay for it; the state of no monitor is touched."""
        scratch = VibrationMonitor()
        scratch.update(np.zeros(10), 0)
        scratch.update(np.zeros((2, 10)), np.zeros(2, dtype=np.int64))

    def levels(self) -> VibrationLevels:
        """The levels now (ArduPilot's get_vibration_levels: the square root of each axis)."""
        x, y, z = np.sqrt(np.maximum(self._st[STATE.slices.vibe_sq], 0.0)).tolist()
        return VibrationLevels(x, y, z, (self.clipping, 0, 0))

