"""Blocks of samples in, attitudes out: calibration, times, validity, magnetometer hold,
estimator over the block.

This is the per-sample work of the service, kept apart from timing and I/O so that tests and
replays drive it directly. A source hands the loop a :class:`~ahrs_service.core.samples.SampleBlock`
(one FIFO burst, or the one sample a polling source read); :meth:`EstimationPipeline.process_block`
calibrates it in one compiled pass, gives each row its time on the sensor's clock, fills the
estimator rows and runs the estimator's batch kernel over them — the kernel that loops the
very ``step`` of the per-sample path, so a block of n rows and n blocks of one row give the
same bits (``tests/test_blocks.py``). :meth:`process` is the same path for one sample.

Sample times: a source whose stamps are already sample instants on the sensor's clock
(``times_on_sensor_clock``: FIFO boards, a flight log) is taken as it is; any other source's
stamps (host read times) go through :class:`~ahrs_service.core.sample_clock.SampleClock` here,
one stamp per row, so its recovered times do not depend on how the rows were blocked. The
row handed to the estimator (its ``dt`` from the recovered times) is exactly what the log
records, beside both times, so replaying the log reproduces the published attitude and never
recovers again.

The stages, in order, each named in :meth:`EstimationPipeline.process_block`: sample times
(the clock recovery below), calibration (:attr:`EstimationPipeline.calibration` applied to the
whole block, :func:`~ahrs_service.core.calibration.apply_calibration_block`), the estimator
rows (validity, magnetometer hold, dt) and the estimator's batch kernel.

Magnetometers run slower than gyroscopes: the last valid field reading is held for
``mag_timeout_s`` (zero-order hold, as the sample rows record it). When no valid reading
arrived for longer than that, the estimator is fed no field (NaN): every estimator then runs
its reduced (gyro + accelerometer) form, and :attr:`EstimationPipeline.reduced` reports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numba import njit

from ahrs_service.calibration.gyro import GyroBiasResult, gyro_bias_at_rest
from ahrs_service.core.calibration import SensorCalibration, apply_calibration, apply_calibration_block
from ahrs_service.core.layout import Layout, Slot
from ahrs_service.core.quaternion import quat_from_euler, quat_mul, quat_to_euler
from ahrs_service.core.sample_clock import SampleClock
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSample, SampleBlock
from ahrs_service.estimators import SAMPLE_ROW, STATE_HEADER
from ahrs_service.estimators.base import Estimator

_R = SAMPLE_ROW.slices
_R0 = SAMPLE_ROW.index  # first column of each part of a row (compile-time constants)
_H = STATE_HEADER.slices
_DT = SAMPLE_ROW.index.dt

G = 9.80665

#: what the row filling carries from one block to the next (one int64 array; times in ns)
FILL_STATE = Layout("row filling state", [
    Slot("started", 1, "1 once the first row was estimated (the start is no longer held back)"),
    Slot("first_t", 1, "time of the first sample seen, ns (valid when have_first)"),
    Slot("have_first", 1, "a sample was seen"),
    Slot("last_t", 1, "time of the last row estimated, ns (valid when have_last)"),
    Slot("have_last", 1, "a row was estimated: the next dt is from last_t"),
    Slot("mag_t", 1, "time of the field reading held, ns (valid when have_mag)"),
    Slot("have_mag", 1, "a field reading is held"),
    Slot("reduced", 1, "1 while no fresh field reading: the reduced form"),
    Slot("switches", 1, "switches between full and reduced form"),
    Slot("recent_head", 1, "next slot of the rest window ring"),
    Slot("recent_count", 1, "rows in the rest window ring"),
])
_S = FILL_STATE.index


def _c(a: np.ndarray) -> np.ndarray:
    # contiguous float64 (a no-op for the usual block): the kernel has one compiled form,
    # the one warm_up loads, so no sample of a flight waits for a compilation
    return np.ascontiguousarray(a, dtype=np.float64)


@njit(cache=True)
def _fill_rows(gyr, acc, mag, flags, t_ns, use_mag, mag_timeout_ns, nominal_dt, st, held_mag, recent, rows):
    """Fills ``rows[start:]`` from calibrated body-frame readings; returns ``start``.

    Per row, as the module docstring says: invalid gyro/accelerometer readings → NaN; the
    field held from the last valid reading (a new one on MAG_NEW, or the first ever) while it
    is at most ``mag_timeout_ns`` old, NaN after (reduced form, counted in ``switches``);
    dt from the previous row's time (the nominal period for the first row). Before the first
    row (``started`` 0) with ``use_mag``, rows are held back until one has a field reading
    or ``mag_timeout_ns`` has passed since the first sample: ``start`` is the first row
    estimated (``len`` when none). Rows with gyro and accelerometer valid enter the rest
    window ring ``recent`` (rows [gyr, acc]).
    """
    n = t_ns.shape[0]
    start = 0
    if st[_S.started] == 0 and use_mag:
        if st[_S.have_first] == 0:
            st[_S.first_t] = t_ns[0]
            st[_S.have_first] = 1
        start = n
        for k in range(n):
            has = (flags[k] & MAG_VALID) != 0 and not (np.isnan(mag[k, 0]) and np.isnan(mag[k, 1]) and np.isnan(mag[k, 2]))
            if has or t_ns[k] - st[_S.first_t] >= mag_timeout_ns:
                start = k
                break
        if start == n:
            return n
    st[_S.started] = 1
    size = recent.shape[0]
    for k in range(start, n):
        f = flags[k]
        g_ok = (f & GYR_VALID) != 0
        a_ok = (f & ACC_VALID) != 0
        for i in range(3):
            rows[k, _R0.gyr + i] = gyr[k, i] if g_ok else np.nan
            rows[k, _R0.acc + i] = acc[k, i] if a_ok else np.nan
        fresh = False
        if use_mag:
            has = (f & MAG_VALID) != 0 and not (np.isnan(mag[k, 0]) and np.isnan(mag[k, 1]) and np.isnan(mag[k, 2]))
            if has and ((f & MAG_NEW) != 0 or st[_S.have_mag] == 0):
                for i in range(3):
                    held_mag[i] = mag[k, i]
                st[_S.mag_t] = t_ns[k]
                st[_S.have_mag] = 1
            fresh = st[_S.have_mag] != 0 and t_ns[k] - st[_S.mag_t] <= mag_timeout_ns
            if fresh == (st[_S.reduced] != 0):
                st[_S.reduced] = 0 if fresh else 1
                st[_S.switches] += 1
        for i in range(3):
            rows[k, _R0.mag + i] = held_mag[i] if fresh else np.nan
        rows[k, _R0.dt] = (t_ns[k] - st[_S.last_t]) * 1e-9 if st[_S.have_last] != 0 else nominal_dt
        st[_S.last_t] = t_ns[k]
        st[_S.have_last] = 1
        if g_ok and a_ok:
            h = st[_S.recent_head]
            for i in range(3):
                recent[h, i] = gyr[k, i]
                recent[h, 3 + i] = acc[k, i]
            st[_S.recent_head] = (h + 1) % size
            st[_S.recent_count] = min(st[_S.recent_count] + 1, size)
    return start


@dataclass(frozen=True, slots=True)
class LatestEstimate:
    """The newest estimated sample, as the streams publish it.

    samples: samples estimated so far (grows with every new one: freshness). t_ns: the
    sample's time, monotonic ns. q: q_earth←body [w, x, y, z] against true north (declination
    applied), NED/FRD. body_rate: (p, q, r) rad/s, bias removed. gyr, acc, mag: calibrated
    body-frame readings, rad/s, m/s², µT (mag None: no reading). mag_new: the field is a fresh
    reading. temperature_c: °C or None. initialised: the estimator's output is trustworthy.
    mag_used: the field is in use (a magnetometer estimator, not in reduced form). reduced:
    the heading is not observed (reduced form, or an estimator without magnetometer).
    estimator_id: identifies the estimator object (a new one after a reload: ODOMETRY's
    reset counter follows it). declination_deg: the declination in ``q``, degrees east.
    """

    samples: int
    t_ns: int
    q: Sequence[float]
    body_rate: Sequence[float]
    gyr: Sequence[float]
    acc: Sequence[float]
    mag: Sequence[float] | None
    mag_new: bool
    temperature_c: float | None
    initialised: bool
    mag_used: bool
    reduced: bool
    estimator_id: int
    declination_deg: float


@dataclass(frozen=True, slots=True)
class LatestAttitude:
    """The newest estimate's attitude alone, what ATTITUDE and ATTITUDE_QUATERNION carry:
    samples (freshness), q (as :class:`LatestEstimate`'s), body_rate rad/s."""

    samples: int
    q: Sequence[float]
    body_rate: Sequence[float]


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
    pipeline: the pipeline that estimated it — where sinks read what the rows do not carry
        (the estimator's name and diagnostics, the newest published attitude).
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
    pipeline: EstimationPipeline | None = None

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
        self._last_block: SampleBlock | None = None  # the last block estimated, calibrated
        self._last_t_ns = 0  # its last row's time, ns
        self._last_sample: ImuSample | None = None  # built from them when asked for
        self._rate_gyr = [0.0, 0.0, 0.0]  # the newest valid gyro row, rad/s (body_rates)
        #: recovers host read times onto the sensor's clock (use_sample_clock), else None
        self.clock: SampleClock | None = None
        self._fill = np.zeros(FILL_STATE.end, dtype=np.int64)  # FILL_STATE slots
        self._held_mag = np.full(3, np.nan)  # the field reading held, µT body FRD
        self.rest_window = max(20, int(round(self.REST_WINDOW_S / nominal_dt)))  # samples
        self._recent = np.zeros((self.rest_window, 6))  # ring of [gyr rad/s, acc m/s²] rows

    @property
    def last_sample(self) -> ImuSample | None:
        """The last row estimated as a calibrated body-frame sample (its time the one fed to
        the estimator); None before the first. Built when asked for (the publishers, at their
        rates), not per block."""
        if self._last_sample is None and self._last_block is not None:
            block = self._last_block
            mag = block.mag[-1]
            temp = float(block.temperature_c[-1])
            self._last_sample = ImuSample(
                self._last_t_ns, block.gyr[-1], block.acc[-1], None if np.isnan(mag).all() else mag,
                int(block.flags[-1]), None if block.raw is None else {k: v[-1].tolist() for k, v in block.raw.items()},
                None if block.truth_q is None else block.truth_q[-1],
                None if math.isnan(temp) else temp,
            )
        return self._last_sample

    @property
    def reduced(self) -> bool:
        """Estimating without a field reading (the reduced form)."""
        return bool(self._fill[_S.reduced])

    @property
    def reduced_switches(self) -> int:
        """Switches between full and reduced form since the start."""
        return int(self._fill[_S.switches])

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
        # the row filling on scratch state (the pipeline's own is untouched)
        _fill_rows(_c(block.gyr), _c(block.acc), _c(block.mag), block.flags, block.t_ns, True, 1, 0.001,
                   np.zeros(FILL_STATE.end, dtype=np.int64), np.full(3, np.nan), np.zeros((2, 6)), np.empty((1, 10)))
        apply_calibration(sample, SensorCalibration().with_gyro_bias_shift(np.full(3, 1e-3)))
        probe.run_rows(np.array([[0.0, 0.0, 0.0, 0.0, 0.0, -G, 20.0, 0.0, 45.0, self.nominal_dt]]))
        # the diagnostics logged with the attitude (the attitude variance, the robust filter's
        # gyro_scale_error): the first /attitude diagnostics must not compile them (0.12-0.27 s;
        # with the simulated motion's kernel, 21-176 samples of a default first start lost)
        probe.diagnostics  # noqa: B018 (a property: evaluated for its kernels)
        quat_to_euler(quat_mul(self._q_decl, (1.0, 0.0, 0.0, 0.0)))

    def use_sample_clock(self, nominal_rate_hz: float) -> None:
        """From now on each row's stamp is a host read time: its sample time is recovered by
        a :class:`~ahrs_service.core.sample_clock.SampleClock` at ``nominal_rate_hz`` (Hz)."""
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
        """Calibrates a block, gives its rows their times, fills the estimator rows
        (:func:`_fill_rows`) and runs the estimator's batch kernel over them.

        Returns the rows estimated, or None when none was: an empty block, or a start held
        back — an estimator that uses the magnetometer starts only with a field reading (so
        it starts with the right heading), waiting at most ``mag_timeout_s`` after the first
        sample for it; the rows before are dropped (neither estimated nor logged).
        """
        n = len(raw)
        if n == 0:
            return None
        # stage 1: each row's time on the sensor's clock
        t_source = raw.t_ns
        t_ns = t_source if self.clock is None else self._recovered(t_source)
        # stage 2: calibration, sensor axes → calibrated body FRD, the whole block in one pass
        block = apply_calibration_block(raw, self.calibration)
        # stage 3: the estimator rows (validity, magnetometer hold, dt); stage 4: the estimator
        rows = np.empty((n, 10))
        start = _fill_rows(_c(block.gyr), _c(block.acc), _c(block.mag), np.ascontiguousarray(block.flags, np.int64),
                           np.ascontiguousarray(t_ns, np.int64), bool(self.use_mag), int(self.mag_timeout_ns),
                           float(self.nominal_dt), self._fill, self._held_mag, self._recent, rows)
        if start == n:
            return None
        if start:
            rows, t_ns, t_source = rows[start:], t_ns[start:], t_source[start:]
        q = self.estimator.run_rows(rows)  # the estimator's step (its paper's equations), row by row
        first = self.samples
        self.samples += n - start
        self.row = rows[-1]
        self._last_block, self._last_t_ns, self._last_sample = block, int(t_ns[-1]), None
        self._hold_rate_gyr(rows)
        if start:
            cut = slice(start, None)
            return EstimatedBlock(
                t_ns, t_source, rows, q, block.flags[cut], block.temperature_c[cut],
                None if block.raw is None else {k: v[cut] for k, v in block.raw.items()},
                None if block.truth_q is None else block.truth_q[cut], first, self.estimator.state.copy(), self)
        return EstimatedBlock(t_ns, t_source, rows, q, block.flags, block.temperature_c, block.raw, block.truth_q,
                              first, self.estimator.state.copy(), self)

    def _recovered(self, t_source: np.ndarray) -> np.ndarray:
        """Each stamp through the sample clock, one sample per stamp (host arrival times)."""
        clock = self.clock
        return np.array([clock.stamp(t, 1)[0] for t in t_source.tolist()], dtype=np.int64)

    # ------------------------------------------------------------------ outputs
    def published_quaternion(self) -> tuple[float, float, float, float]:
        """q_earth←body against true north: the estimate rotated by the declination."""
        q = tuple(self.estimator.state[_H.q].tolist())
        if self.declination_deg == 0.0:
            return q  # type: ignore[return-value]
        return quat_mul(self._q_decl, q)

    def latest_estimate(self) -> LatestEstimate | None:
        """The newest estimated sample for the publishers; None before the first."""
        sample = self.last_sample
        if sample is None:
            return None
        estimator = self.estimator
        return LatestEstimate(
            samples=self.samples,
            t_ns=sample.t_ns,
            q=self.published_quaternion(),
            body_rate=self.body_rates(),
            gyr=sample.gyr,
            acc=sample.acc,
            mag=sample.mag,
            mag_new=bool(sample.flags & MAG_NEW),
            temperature_c=sample.temperature_c,
            initialised=bool(estimator.state[STATE_HEADER.index.initialised]),
            mag_used=self.use_mag and not self.reduced,
            reduced=self.reduced or not self.use_mag,
            estimator_id=id(estimator),
            declination_deg=self.declination_deg,
        )

    def latest_attitude(self) -> LatestAttitude | None:
        """The newest estimate's attitude alone (what ATTITUDE / ATTITUDE_QUATERNION carry);
        None before the first sample."""
        if self.last_sample is None:
            return None
        return LatestAttitude(self.samples, self.published_quaternion(), self.body_rates())

    def diagnostics(self) -> dict:
        """The estimator's diagnostics (rest, rejections, bias trust …) and the form it runs in."""
        return dict(self.estimator.diagnostics, reduced=self.reduced)

    def published_euler(self) -> tuple[float, float, float]:
        return quat_to_euler(self.published_quaternion())

    def _hold_rate_gyr(self, rows: np.ndarray) -> None:
        """Keeps the newest row's gyro reading that the estimator took (finite: valid), for
        :meth:`body_rates`. A row whose gyro was invalid (NaN in the row: non-finite, saturated
        or implausible at the source) keeps the previous one, so no NaN or absurd rate is
        published (without a gyroscope for long the attitude stops being fresh: health)."""
        # the usual block (its last gyro reading valid) on plain floats: one NumPy call, not four
        gx, gy, gz = last = rows[-1, _R.gyr].tolist()
        if math.isfinite(gx) and math.isfinite(gy) and math.isfinite(gz):
            self._rate_gyr = last
            return
        g = rows[:, _R.gyr]
        ok = np.flatnonzero(np.isfinite(g).all(axis=1))
        if ok.size:
            self._rate_gyr = g[ok[-1]].tolist()

    def body_rates(self) -> list[float]:
        """Latest bias-corrected body angular rate (p, q, r), rad/s: of the newest valid gyro
        reading the estimator took (zeros before the first)."""
        # plain floats: cheaper than a NumPy subtraction on three elements, once per publish
        gx, gy, gz = self._rate_gyr
        bx, by, bz = self.estimator.state[_H.bias].tolist()
        return [gx - bx, gy - by, gz - bz]

    # ------------------------------------------------------------------ gyro calibration
    def _recent_rows(self) -> np.ndarray:
        """The rest window's [gyr, acc] rows, oldest first."""
        count, head = int(self._fill[_S.recent_count]), int(self._fill[_S.recent_head])
        if count < self.rest_window:
            return self._recent[:count].copy()
        return np.roll(self._recent, -head, axis=0)

    def recent_gyro_mean(self) -> np.ndarray:
        """Mean calibrated body rate over the rest window, rad/s (NaN when empty)."""
        recent = self._recent_rows()
        if not len(recent):
            return np.full(3, np.nan)
        return recent[:, :3].mean(axis=0)

    def rest_check(self) -> GyroBiasResult:
        """Whether the recent window (``REST_WINDOW_S``) shows the IMU at rest, judged as the
        gyro calibration judges it (its ``at_rest`` and ``reason``); changes nothing."""
        recent = self._recent_rows()
        gyr, acc = recent[:, :3], recent[:, 3:]
        # per-sample accelerometer noise of low-cost parts at high output rates reaches
        # 0.35 m/s² (the simulated ADXL345 at 800 Hz), so over this one-second window even the
        # block means wander by ~0.7° rms: the norm and direction tests allow that, while
        # motion still shows in the gyro spread
        return gyro_bias_at_rest(
            gyr, acc, min_samples=self.rest_window // 2, max_acc_norm_std=0.6, max_acc_direction_deg=2.0
        )

    def calibrate_gyro_bias(self) -> GyroBiasResult:
        """Adds the mean residual rate of the recent window (``REST_WINDOW_S``) to the
        calibration's gyro bias — only when that window shows the IMU at rest."""
        result = self.rest_check()
        if result.at_rest:
            self.calibration = self.calibration.with_gyro_bias_shift(result.bias)
            self._fill[_S.recent_count] = self._fill[_S.recent_head] = 0
        return result
