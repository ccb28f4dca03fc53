"""Blocks of samples in, attitudes out: calibration, times, validity, magnetometer hold,
estimator over the block.

This is the per-sample work of the service, kept apart from timing and I/O so that tests and
replays drive it directly. A source hands the loop a :class:`~ahrs_service.drivers.base.SampleBlock`
(one FIFO burst, or the one sample a polling source read); :meth:`EstimationPipeline.process_block`
calibrates it in one compiled pass, gives each row its time on the sensor's clock, fills the
estimator rows and runs the estimator's batch kernel over them — the kernel that loops the
very ``step`` of the per-sample path, so a block of n rows and n blocks of one row give the
same bits (``tests/test_blocks.py``). :meth:`process` is the same path for one sample.

Sample times: a source whose stamps are already sample instants on the sensor's clock
(``times_on_sensor_clock``: FIFO boards, a flight log) is taken as it is; any other source's
stamps (host read times) go through :class:`~ahrs_service.sample_clock.SampleClock` here,
one stamp per row, so its recovered times do not depend on how the rows were blocked. The
row handed to the estimator (its ``dt`` from the recovered times) is exactly what the log
records, beside both times, so replaying the log reproduces the published attitude and never
recovers again.

Magnetometers run slower than gyroscopes: the last valid field reading is held for
``mag_timeout_s`` (zero-order hold, as the sample rows record it). When no valid reading
arrived for longer than that, the estimator is fed no field (NaN): every estimator then runs
its reduced (gyro + accelerometer) form, and :attr:`EstimationPipeline.reduced` reports it.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ahrs_service.calibration.gyro import GyroBiasResult, gyro_bias_at_rest
from ahrs_service.drivers.base import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSample, SampleBlock
from ahrs_service.drivers.calibration import SensorCalibration, apply_calibration, apply_calibration_block
from ahrs_service.estimators import SAMPLE_ROW, STATE_HEADER
from ahrs_service.estimators.base import Estimator
from ahrs_service.quaternion import quat_from_euler, quat_mul, quat_to_euler
from ahrs_service.sample_clock import SampleClock

_R = SAMPLE_ROW.slices
_H = STATE_HEADER.slices
_DT = SAMPLE_ROW.index.dt

G = 9.80665
_NO_FIELD = np.full(3, np.nan)


@dataclass(slots=True)
class EstimatedBlock:
    """The rows of one block the estimator ran over, for the log and the publishers.

    t_ns: (n,) int64 each sample's time on the sensor's clock (recovered), monotonic ns — the
        times the ``dt`` column was computed from. t_source_ns: (n,) int64 the source's own
        stamps (host read times for a polling source; equal to ``t_ns`` for a source whose
        stamps are already on the sensor's clock). rows: (n, 10) float64 the sample rows
        exactly as fed to the estimator (calibrated body FRD: rad/s, m/s², µT (NaN: none),
        dt s). q: (n, 4) q_earth←body [w, x, y, z] after each row (magnetic north, as the
        estimator holds it). flags: (n,) validity bits. temperature_c: (n,) °C, NaN unknown.
        raw: the driver's counts per row, or None. truth_q: (n, 4) or None. first_index: the
        number of row 0 since the pipeline started (what /params ``sample_index`` counts).
        state: the estimator's state after the last row (a copy).
    """

    t_ns: np.ndarray
    t_source_ns: np.ndarray
    rows: np.ndarray
    q: np.ndarray
    flags: np.ndarray
    temperature_c: np.ndarray
    raw: dict[str, np.ndarray] | None
    truth_q: np.ndarray | None
    first_index: int
    state: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)


class EstimationPipeline:
    """Turns source blocks into estimator steps.

    ``declination_deg`` rotates the published heading from magnetic to true north (first
    paper eq. 44) for every estimator alike; the estimator itself stays on magnetic north so
    the recorded estimate replays unchanged. Stamps are taken as sample instants unless
    :meth:`use_sample_clock` is called (sources that stamp with the host's read time).
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
        self.row = np.full(10, np.nan)  # the last row fed to the estimator
        self.samples = 0
        self.last_sample: ImuSample | None = None  # the last row's calibrated sample
        self.reduced = False
        self.reduced_switches = 0
        #: recovers host read times onto the sensor's clock (use_sample_clock), else None
        self.clock: SampleClock | None = None
        self._last_t_ns: int | None = None
        self._first_t_ns: int | None = None
        self._mag = np.full(3, np.nan)
        self._mag_t_ns: int | None = None
        self.rest_window = max(20, int(round(self.REST_WINDOW_S / nominal_dt)))  # samples
        self._recent_gyr: deque[np.ndarray] = deque(maxlen=self.rest_window)
        self._recent_acc: deque[np.ndarray] = deque(maxlen=self.rest_window)

    def warm_up(self) -> None:
        """Compiles, or loads from numba's cache, every kernel of the block path.

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
        block = SampleBlock.from_samples([sample])
        # the identity calibration skips the compiled path: a live calibration must not be
        # the first call of it, nor the first publish the first quaternion product
        apply_calibration_block(block, SensorCalibration().with_gyro_bias_shift(np.full(3, 1e-3)))
        apply_calibration(sample, SensorCalibration().with_gyro_bias_shift(np.full(3, 1e-3)))
        probe.run_rows(np.array([[0.0, 0.0, 0.0, 0.0, 0.0, -G, 20.0, 0.0, 45.0, self.nominal_dt]]))
        quat_to_euler(quat_mul(self._q_decl, (1.0, 0.0, 0.0, 0.0)))

    def use_sample_clock(self, nominal_rate_hz: float) -> None:
        """From now on each row's stamp is a host read time: its sample time is recovered by
        a :class:`~ahrs_service.sample_clock.SampleClock` at ``nominal_rate_hz`` (Hz)."""
        self.clock = SampleClock(nominal_rate_hz)

    def set_declination(self, degrees: float) -> None:
        self.declination_deg = float(degrees)
        self._q_decl = quat_from_euler(0.0, 0.0, math.radians(degrees))

    # ------------------------------------------------------------------ samples in
    def process(self, raw_sample: ImuSample) -> ImuSample | None:
        """One sample through :meth:`process_block` (a block of one row). Returns the
        calibrated body-frame sample, or None while the start is held back."""
        done = self.process_block(SampleBlock.from_samples([raw_sample]))
        return None if done is None else self.last_sample

    def process_block(self, raw: SampleBlock) -> EstimatedBlock | None:
        """Calibrates a block, gives its rows their times, fills the estimator rows and runs
        the estimator over them (its batch kernel).

        Returns the rows estimated, or None when none was: an empty block, or a start held
        back — an estimator that uses the magnetometer starts only with a field reading (so
        it starts with the right heading), waiting at most ``mag_timeout_s`` after the first
        sample for it; the rows before are dropped (neither estimated nor logged).
        """
        n = len(raw)
        if n == 0:
            return None
        t_source = np.asarray(raw.t_ns, dtype=np.int64)
        t_ns = t_source if self.clock is None else self._recovered(t_source)
        block = apply_calibration_block(raw, self.calibration)
        flags = np.asarray(block.flags, dtype=np.int64)
        mag_ok = ((flags & MAG_VALID) != 0) & ~np.isnan(block.mag).all(axis=1)
        start = 0
        if self.samples == 0 and self.use_mag:
            start = self._first_estimated_row(t_ns, mag_ok)
            if start == n:
                return None
        if start:
            t_ns, t_source, flags, mag_ok = t_ns[start:], t_source[start:], flags[start:], mag_ok[start:]
        m = n - start
        rows = np.empty((m, 10))
        rows[:, _R.gyr] = block.gyr[start:]
        rows[:, _R.acc] = block.acc[start:]
        rows[(flags & GYR_VALID) == 0, _R.gyr] = np.nan
        rows[(flags & ACC_VALID) == 0, _R.acc] = np.nan
        rows[:, _R.mag] = self._fields(block.mag[start:], flags, mag_ok, t_ns)
        # dt from consecutive times; the first row after the start: the nominal period
        dt = rows[:, _DT]
        dt[1:] = np.diff(t_ns) * 1e-9
        dt[0] = self.nominal_dt if self._last_t_ns is None else (int(t_ns[0]) - self._last_t_ns) * 1e-9
        self._last_t_ns = int(t_ns[-1])
        q = self.estimator.run_rows(rows)  # eq. numbers: the estimator's step, row by row
        first = self.samples
        self.samples += m
        self.row = rows[-1]
        self.last_sample = ImuSample(
            int(t_ns[-1]), block.gyr[-1].copy(), block.acc[-1].copy(), None if np.isnan(block.mag[-1]).all() else block.mag[-1].copy(),
            int(flags[-1]), None if block.raw is None else {k: v[-1].tolist() for k, v in block.raw.items()},
            None if block.truth_q is None else block.truth_q[-1].copy(),
            None if math.isnan(float(block.temperature_c[-1])) else float(block.temperature_c[-1]),
        )
        both = ((flags & GYR_VALID) != 0) & ((flags & ACC_VALID) != 0)
        if both.any():  # the rest window: rows whose gyro and accelerometer are both valid
            kept = rows[both][-self.rest_window:]
            self._recent_gyr.extend(kept[:, _R.gyr])
            self._recent_acc.extend(kept[:, _R.acc])
        return EstimatedBlock(
            t_ns=t_ns, t_source_ns=t_source, rows=rows, q=q, flags=flags,
            temperature_c=np.asarray(block.temperature_c[start:], dtype=float),
            raw=None if block.raw is None else {k: v[start:] for k, v in block.raw.items()},
            truth_q=None if block.truth_q is None else block.truth_q[start:],
            first_index=first, state=self.estimator.state.copy(),
        )

    def _recovered(self, t_source: np.ndarray) -> np.ndarray:
        """Each stamp through the sample clock, one sample per stamp (host read times)."""
        clock = self.clock
        return np.array([clock.stamp(t, 1)[0] for t in t_source.tolist()], dtype=np.int64)

    def _first_estimated_row(self, t_ns: np.ndarray, mag_ok: np.ndarray) -> int:
        """The first row the start may begin at: one with a field reading, or the first at
        ``mag_timeout_s`` after the first sample seen; ``len`` when none of this block."""
        if self._first_t_ns is None:
            self._first_t_ns = int(t_ns[0])
        ready = mag_ok | (t_ns - self._first_t_ns >= self.mag_timeout_ns)
        return int(np.argmax(ready)) if ready.any() else len(t_ns)

    def _fields(self, mag: np.ndarray, flags: np.ndarray, mag_ok: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
        """The field column of each row: the last valid reading held for ``mag_timeout_s``
        (a new one where ``MAG_NEW``, or the first valid one ever), NaN once it is older."""
        m = len(t_ns)
        if not self.use_mag:
            return np.broadcast_to(_NO_FIELD, (m, 3))
        take = mag_ok & ((flags & MAG_NEW) != 0)
        if self._mag_t_ns is None and mag_ok.any():
            take[int(np.argmax(mag_ok))] = True  # the first valid reading starts the hold
        held = np.maximum.accumulate(np.where(take, np.arange(m), -1))  # row of the reading held
        out = np.where((held >= 0)[:, None], mag[np.maximum(held, 0)], self._mag)
        held_t = np.where(held >= 0, t_ns[np.maximum(held, 0)], -1 if self._mag_t_ns is None else self._mag_t_ns)
        fresh = ((held >= 0) | (self._mag_t_ns is not None)) & (t_ns - held_t <= self.mag_timeout_ns)
        if take.any():
            last = int(np.flatnonzero(take)[-1])
            self._mag, self._mag_t_ns = mag[last].astype(float), int(t_ns[last])
        reduced = ~fresh
        self.reduced_switches += int(reduced[0] != self.reduced) + int(np.count_nonzero(reduced[1:] != reduced[:-1]))
        self.reduced = bool(reduced[-1])
        out[reduced] = np.nan
        return out

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
