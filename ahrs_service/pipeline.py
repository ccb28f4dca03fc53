"""One sample in, one attitude out: calibration, validity, magnetometer hold, estimator step.

This is the per-sample work of the service, kept apart from timing and I/O so that tests and
replays drive it directly. The row handed to the estimator is exactly what the log records,
so replaying the log reproduces the published attitude.

Magnetometers run slower than gyroscopes: the last valid field reading is held for
``mag_timeout_s`` (zero-order hold, as the sample rows record it). When no valid reading
arrived for longer than that, the estimator is fed no field (NaN): every estimator then runs
its reduced (gyro + accelerometer) form, and :attr:`EstimationPipeline.reduced` reports it.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from ahrs_service.calibration.gyro import GyroBiasResult, gyro_bias_at_rest
from ahrs_service.drivers.base import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSample
from ahrs_service.drivers.calibration import SensorCalibration, apply_calibration
from ahrs_service.estimators import SAMPLE_ROW, STATE_HEADER
from ahrs_service.estimators.base import Estimator
from ahrs_service.quaternion import quat_from_euler, quat_mul, quat_to_euler

_R = SAMPLE_ROW.slices
_H = STATE_HEADER.slices
_DT = SAMPLE_ROW.index.dt

G = 9.80665
_NO_FIELD = np.full(3, np.nan)


class EstimationPipeline:
    """Turns source samples into estimator steps.

    ``declination_deg`` rotates the published heading from magnetic to true north (first
    paper eq. 44) for every estimator alike; the estimator itself stays on magnetic north so
    the recorded estimate replays unchanged.
    """

    REST_WINDOW_S = 1.0  # recent samples kept for the rest check and gyro calibration, s

    def __init__(
        self,
        estimator: Estimator,
        calibration: SensorCalibration | None = None,
        *,
        mag_timeout_s: float = 0.5,
        use_mag: bool = True,
        declination_deg: float = 0.0,
        nominal_dt: float = 0.005,
    ) -> None:
        self.estimator = estimator
        self.calibration = calibration or SensorCalibration()
        self.mag_timeout_ns = int(mag_timeout_s * 1e9)
        self.use_mag = use_mag and estimator.uses_mag
        self.nominal_dt = nominal_dt
        self.set_declination(declination_deg)
        self.row = np.full(10, np.nan)
        self.samples = 0
        self.last_sample: ImuSample | None = None
        self.reduced = False
        self.reduced_switches = 0
        self._last_t_ns: int | None = None
        self._first_t_ns: int | None = None
        self._mag = np.full(3, np.nan)
        self._mag_t_ns: int | None = None
        self.rest_window = max(20, int(round(self.REST_WINDOW_S / nominal_dt)))  # samples
        self._recent_gyr: deque[np.ndarray] = deque(maxlen=self.rest_window)
        self._recent_acc: deque[np.ndarray] = deque(maxlen=self.rest_window)

    def warm_up(self) -> None:
        """Compiles, or loads from numba's cache, every kernel of the per-sample path.

        Called before the loop starts: the first start on a machine compiles the estimator
        (tens of seconds once), and that must not happen on the first sample of a flight.
        """
        probe = type(self.estimator)(**self.estimator.get_params())
        sample = ImuSample(
            t_ns=0,
            gyr=np.zeros(3),
            acc=np.array([0.0, 0.0, -G]),
            mag=np.array([20.0, 0.0, 45.0]),
            flags=GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW,
        )
        apply_calibration(sample, self.calibration)
        # the identity calibration skips the compiled path: a live calibration must not be
        # the first call of it, nor the first publish the first quaternion product
        apply_calibration(sample, SensorCalibration().with_gyro_bias_shift(np.full(3, 1e-3)))
        probe.update_row(np.array([0.0, 0.0, 0.0, 0.0, 0.0, -G, 20.0, 0.0, 45.0, self.nominal_dt]))
        quat_to_euler(quat_mul(self._q_decl, (1.0, 0.0, 0.0, 0.0)))

    def set_declination(self, degrees: float) -> None:
        self.declination_deg = float(degrees)
        self._q_decl = quat_from_euler(0.0, 0.0, math.radians(degrees))

    def process(self, raw_sample: ImuSample) -> ImuSample | None:
        """Calibrates one sample, fills the estimator row and steps the estimator.

        Returns the calibrated body-frame sample (what the log records beside the row), or
        None while the start is held back: an estimator that uses the magnetometer starts
        only with a field reading (so it starts with the right heading), waiting at most
        ``mag_timeout_s`` after the first sample for it.
        """
        sample = apply_calibration(raw_sample, self.calibration)
        t_ns = sample.t_ns
        if self.samples == 0 and self.use_mag and not (sample.mag is not None and sample.flags & MAG_VALID):
            if self._first_t_ns is None:
                self._first_t_ns = t_ns
            if t_ns - self._first_t_ns < self.mag_timeout_ns:
                return None
        row = self.row
        dt = self.nominal_dt if self._last_t_ns is None else (t_ns - self._last_t_ns) * 1e-9
        self._last_t_ns = t_ns
        flags = sample.flags
        row[_R.gyr] = sample.gyr if flags & GYR_VALID else np.nan
        row[_R.acc] = sample.acc if flags & ACC_VALID else np.nan
        row[_R.mag] = self._field_for(sample, t_ns)
        row[_DT] = dt
        self.estimator.update_row(row)
        self.samples += 1
        self.last_sample = sample
        if flags & GYR_VALID and flags & ACC_VALID:
            self._recent_gyr.append(sample.gyr)
            self._recent_acc.append(sample.acc)
        return sample

    def _field_for(self, sample: ImuSample, t_ns: int) -> np.ndarray:
        if not self.use_mag:
            return _NO_FIELD
        if sample.mag is not None and sample.flags & MAG_VALID and (sample.flags & MAG_NEW or self._mag_t_ns is None):
            self._mag = np.asarray(sample.mag, dtype=float)
            self._mag_t_ns = t_ns
        fresh = self._mag_t_ns is not None and t_ns - self._mag_t_ns <= self.mag_timeout_ns
        if fresh == self.reduced:
            self.reduced = not fresh
            self.reduced_switches += 1
        return self._mag if fresh else _NO_FIELD

    # ------------------------------------------------------------------ outputs
    def published_quaternion(self) -> tuple[float, float, float, float]:
        """q_earth←body against true north: the estimate rotated by the declination."""
        q = tuple(self.estimator.state[_H.q].tolist())
        if self.declination_deg == 0.0:
            return q  # type: ignore[return-value]
        return quat_mul(self._q_decl, q)

    def published_euler(self) -> tuple[float, float, float]:
        return quat_to_euler(self.published_quaternion())

    def body_rates(self) -> list[float]:
        """Latest bias-corrected body angular rate (p, q, r), rad/s."""
        if self.last_sample is None:
            return [0.0, 0.0, 0.0]
        # plain floats: cheaper than a NumPy subtraction on three elements, once per publish
        gx, gy, gz = np.asarray(self.last_sample.gyr).tolist()
        bx, by, bz = self.estimator.state[_H.bias].tolist()
        return [gx - bx, gy - by, gz - bz]

    # ------------------------------------------------------------------ gyro calibration
    def recent_gyro_mean(self) -> np.ndarray:
        """Mean calibrated body rate over the rest window, rad/s (NaN when empty)."""
        if not self._recent_gyr:
            return np.full(3, np.nan)
        return np.array(self._recent_gyr).mean(axis=0)

    def calibrate_gyro_bias(self) -> GyroBiasResult:
        """Adds the mean residual rate of the recent window (``REST_WINDOW_S``) to the
        calibration's gyro bias — only when that window shows the IMU at rest."""
        gyr = np.array(self._recent_gyr) if self._recent_gyr else np.empty((0, 3))
        acc = np.array(self._recent_acc) if self._recent_acc else np.empty((0, 3))
        # per-sample accelerometer noise of low-cost parts at high output rates reaches
        # 0.35 m/s² (the simulated ADXL345 at 800 Hz), so over this one-second window even the
        # block means wander by ~0.7° rms: the norm and direction tests allow that, while
        # motion still shows in the gyro spread
        result = gyro_bias_at_rest(
            gyr, acc, min_samples=self.rest_window // 2, max_acc_norm_std=0.6, max_acc_direction_deg=2.0
        )
        if result.at_rest:
            self.calibration = self.calibration.with_gyro_bias_shift(result.bias)
            self._recent_gyr.clear()
            self._recent_acc.clear()
        return result
