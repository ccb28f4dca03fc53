"""Vibration levels and accelerometer clipping, as ArduPilot computes them for VIBRATION (#241).

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
dt]``, body FRD, m/s², s) and runs one compiled loop over them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from ahrs_service.drivers.base import ACC_SATURATED, ACC_VALID

FLOOR_HZ = 5.0  # Hz, the floor filter (ArduPilot AP_INERTIAL_SENSOR_ACCEL_VIBE_FLOOR_FILT_HZ)
VIBE_HZ = 2.0  # Hz, the filter of the squared difference (AP_INERTIAL_SENSOR_ACCEL_VIBE_FILT_HZ)
STANDARD_GRAVITY = 9.80665  # m/s²
#: ArduPilot's default clip limit (AP_InertialSensor_Backend::_clip_limit), m/s²
CLIP_LIMIT_MSS = (16.0 - 0.5) * STANDARD_GRAVITY

_ACC = slice(3, 6)  # the accelerometer's columns in a sample row
_DT = 9  # the dt column, s


@dataclass(frozen=True, slots=True)
class VibrationLevels:
    """What VIBRATION carries: levels per body axis (m/s², RMS above ~5 Hz) and the clipping
    count of each accelerometer (this service has one: index 0; the others stay 0)."""

    x: float
    y: float
    z: float
    clipping: tuple[int, int, int]


@numba.njit(cache=True)
def _vibration_kernel(rows, flags, floor, vibe_sq, seen, clip_limit, floor_rc, vibe_rc):
    """One pass over ``rows`` (n, 10) with ``flags`` (n,): updates ``floor`` (3,), ``vibe_sq``
    (3,) and ``seen`` (1,) in place; returns the number of clipped samples."""
    clipped = 0
    for i in range(rows.shape[0]):
        f = flags[i]
        ax, ay, az, dt = rows[i, 3], rows[i, 4], rows[i, 5], rows[i, 9]
        if abs(ax) > clip_limit or abs(ay) > clip_limit or abs(az) > clip_limit or (f & 16) != 0:
            clipped += 1  # any axis beyond the limit, or the part saturated (ACC_SATURATED)
        if (f & 2) == 0 or not (math.isfinite(ax) and math.isfinite(ay) and math.isfinite(az)):
            continue  # no valid reading (ACC_VALID unset): nothing to filter
        if not (dt > 0.0 and math.isfinite(dt)):
            continue
        if seen[0] == 0:
            floor[0], floor[1], floor[2] = ax, ay, az
            seen[0] = 1
        # floor: low-pass at FLOOR_HZ, alpha = dt / (dt + RC)
        a = dt / (dt + floor_rc)
        floor[0] += (ax - floor[0]) * a
        floor[1] += (ay - floor[1]) * a
        floor[2] += (az - floor[2]) * a
        # squared difference from the floor, low-passed at VIBE_HZ
        b = dt / (dt + vibe_rc)
        dx, dy, dz = ax - floor[0], ay - floor[1], az - floor[2]
        vibe_sq[0] += (dx * dx - vibe_sq[0]) * b
        vibe_sq[1] += (dy * dy - vibe_sq[1]) * b
        vibe_sq[2] += (dz * dz - vibe_sq[2]) * b
    return clipped


assert ACC_VALID == 2 and ACC_SATURATED == 16  # the kernel's literal bits


class VibrationMonitor:
    """Vibration levels and clipping count of one accelerometer, fed with sample rows.

    clip_limit_mss: a specific force beyond this on any axis counts as clipping (m/s²).
    """

    def __init__(self, clip_limit_mss: float = CLIP_LIMIT_MSS) -> None:
        self.clip_limit_mss = float(clip_limit_mss)
        self.floor = np.zeros(3)  # m/s², the 5 Hz floor per body axis
        self.vibe_sq = np.zeros(3)  # (m/s²)², the 2 Hz-filtered squared difference
        self.clipping = 0  # clipped samples since start
        self._seen = np.zeros(1, dtype=np.int64)
        self._floor_rc = 1.0 / (2.0 * math.pi * FLOOR_HZ)
        self._vibe_rc = 1.0 / (2.0 * math.pi * VIBE_HZ)
        self._one_flag = np.zeros(1, dtype=np.int64)

    def update(self, rows: np.ndarray, flags: np.ndarray | int) -> None:
        """Feeds sample rows (10,) or (n, 10) as fed to the estimator, with their validity
        ``flags`` (an int for one row, else (n,))."""
        if rows.ndim == 1:
            self._one_flag[0] = flags
            rows, flags = rows.reshape(1, -1), self._one_flag
        else:
            flags = np.asarray(flags, dtype=np.int64)
        self.clipping += _vibration_kernel(rows, flags, self.floor, self.vibe_sq, self._seen,
                                           self.clip_limit_mss, self._floor_rc, self._vibe_rc)

    def levels(self) -> VibrationLevels:
        """The levels now (ArduPilot's get_vibration_levels: the square root of each axis)."""
        x, y, z = np.sqrt(np.maximum(self.vibe_sq, 0.0)).tolist()
        return VibrationLevels(x, y, z, (int(self.clipping), 0, 0))

