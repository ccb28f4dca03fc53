"""Error models of MEMS sensors: what turns a true vector into what a part reports.

One :class:`SensorErrorModel` per sensor (gyroscope, accelerometer, magnetometer), in the
sensor's own SI units (rad/s, m/s², µT). :data:`PART_MODELS` holds presets for the parts of
the source papers' boards (GY-80, MinIMU-9 v2) and the common MPU-9250, built from datasheet
figures; ``docs/simulator.md`` lists the numbers and where they come from.

The order in which errors act (the calibration in ``ahrs_service.core.calibration``
undoes the static part in reverse):

    x = soft_iron · true + hard_iron                     (magnetometers; identity/zero else)
    x = (I + misalignment) · diag(scale_factor) · x
    x = x + bias + turn-on bias + drift + temp_coeff · (T − T_ref)
    x = x + white noise, σ = noise_density · √bandwidth
    x = clip(x, ±range)  → flagged saturated
    x = round(x / quantisation) · quantisation
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

DEG = math.pi / 180.0
G0 = 9.80665  # the "g" of datasheets, m/s²
GAUSS = 100.0  # µT per gauss


def _zeros() -> np.ndarray:
    return np.zeros(3)


@dataclass(eq=False)
class SensorErrorModel:
    """Errors of one three-axis sensor, in its SI unit ("unit": rad/s, m/s² or µT).

    noise_density: white noise, unit/√Hz.
    bandwidth_hz: noise bandwidth, Hz; None uses the Nyquist band of the actual sampling
        interval, 1/(2·dt), so the per-sample standard deviation is noise_density·√(rate/2).
    bias: (3,) constant offset, unit.
    bias_sigma: 1σ of a turn-on offset drawn once per seed (per axis), unit.
    bias_random_walk: rate of the bias random walk, unit/√s (bias drifts by
        N(0, bias_random_walk·√dt) per step).
    scale_factor: (3,) per-axis gain, 1 = exact.
    misalignment: (3, 3) small cross-axis coupling added to the identity (diagonal ignored).
    quantisation: step of one LSB, unit; 0 = continuous.
    range: full scale, unit: readings beyond ±range are clipped and flagged; inf = none.
    hard_iron: (3,) µT, and soft_iron: (3, 3), magnetometers only (identity for others).
    temp_coeff: (3,) bias change per °C from ``reference_temp_c``, unit/°C.
    seed: seed of this model's random generator; the same seed gives the same readings.
    """

    noise_density: float = 0.0
    bandwidth_hz: float | None = None
    bias: np.ndarray = field(default_factory=_zeros)
    bias_sigma: float = 0.0
    bias_random_walk: float = 0.0
    scale_factor: np.ndarray = field(default_factory=lambda: np.ones(3))
    misalignment: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    quantisation: float = 0.0
    range: float = math.inf
    hard_iron: np.ndarray = field(default_factory=_zeros)
    soft_iron: np.ndarray = field(default_factory=lambda: np.eye(3))
    temp_coeff: np.ndarray = field(default_factory=_zeros)
    reference_temp_c: float = 25.0
    seed: int = 0

    def __post_init__(self) -> None:
        self.bias = _array(self.bias, (3,), "bias")
        self.scale_factor = _array(self.scale_factor, (3,), "scale_factor")
        self.misalignment = _array(self.misalignment, (3, 3), "misalignment")
        self.hard_iron = _array(self.hard_iron, (3,), "hard_iron")
        self.soft_iron = _array(self.soft_iron, (3, 3), "soft_iron")
        self.temp_coeff = _array(self.temp_coeff, (3,), "temp_coeff")
        for name in ("noise_density", "bias_sigma", "bias_random_walk", "quantisation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
        if not self.range > 0.0:
            raise ValueError(f"range must be > 0 (or inf), got {self.range!r}")
        if self.bandwidth_hz is not None and not (math.isfinite(self.bandwidth_hz) and self.bandwidth_hz > 0):
            raise ValueError(f"bandwidth_hz must be > 0 or None, got {self.bandwidth_hz!r}")
        self.reset()

    def reset(self, seed: int | None = None) -> None:
        """Restarts the random generator (and the drift) from ``seed`` (default: self.seed)."""
        if seed is not None:
            self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        self.turn_on_bias = self._rng.normal(0.0, self.bias_sigma, 3) if self.bias_sigma > 0 else np.zeros(3)
        self.drift = np.zeros(3)
        self.saturated = False
        off = self.misalignment - np.diag(np.diag(self.misalignment))
        # everything linear folded into one matrix, applied once per reading
        self._gain = (np.eye(3) + off) @ np.diag(self.scale_factor) @ self.soft_iron
        self._offset = (np.eye(3) + off) @ np.diag(self.scale_factor) @ self.hard_iron

    @property
    def distortion(self) -> np.ndarray:
        """(3, 3) linear part: measured = distortion · true + offset + bias + noise."""
        return self._gain.copy()

    @property
    def offset(self) -> np.ndarray:
        """(3,) constant offset from the hard iron, after scale and misalignment (unit)."""
        return self._offset.copy()

    @property
    def total_bias(self) -> np.ndarray:
        """Constant plus turn-on plus drifted bias now (unit; without the temperature term)."""
        return self.bias + self.turn_on_bias + self.drift

    def noise_std(self, dt: float) -> float:
        """Standard deviation of the white noise of one reading taken ``dt`` s after the last."""
        bw = self.bandwidth_hz if self.bandwidth_hz is not None else 0.5 / dt
        return self.noise_density * math.sqrt(bw)

    def apply(self, true_value: Any, dt: float, temperature_c: float | None = None,
              noise_dt: float | None = None) -> np.ndarray:
        """The reading of the true vector (3,), ``dt`` s (> 0) after the previous reading.

        Advances the bias random walk by dt and draws fresh noise, over the band of a
        reading every ``noise_dt`` s when given (the sampling part's own period), else every
        dt; sets ``self.saturated`` when any axis was clipped to ±range.
        """
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0 s, got {dt!r}")
        x = self._gain @ np.asarray(true_value, dtype=float) + self._offset
        if self.bias_random_walk > 0.0:
            self.drift += self._rng.normal(0.0, self.bias_random_walk * math.sqrt(dt), 3)
        x += self.bias + self.turn_on_bias + self.drift
        if temperature_c is not None:
            x += self.temp_coeff * (temperature_c - self.reference_temp_c)
        if self.noise_density > 0.0:
            x += self._rng.normal(0.0, self.noise_std(dt if noise_dt is None else noise_dt), 3)
        self.saturated = bool(np.any(np.abs(x) > self.range))
        if self.saturated:
            np.clip(x, -self.range, self.range, out=x)
        if self.quantisation > 0.0:
            x = np.round(x / self.quantisation) * self.quantisation
        return x

    def apply_block(self, true_values: np.ndarray, dts: np.ndarray,
                    temperatures_c: np.ndarray | None = None,
                    noise_dt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`apply` over ``n`` readings in order, vectorised: (readings (n, 3),
        saturated (n,) bool). ``true_values`` (n, 3), ``dts`` (n,) s since each reading's
        previous one, ``temperatures_c`` (n,) or None, ``noise_dt`` as in :meth:`apply`.

        The same model, draw for draw: the random generator gives the drift step and the
        noise of reading 1, then of reading 2, … as ``n`` calls of :meth:`apply` draw them
        (a ziggurat normal is one draw per value whatever the batch size), and the drift is
        the running sum in the same order, so the noise and drift are bit for bit those of
        the per-reading calls; only the linear part (``distortion · true``, one matrix
        product for the block) may differ from them in the last bit. Leaves the state (drift,
        generator, ``saturated``) where the ``n`` calls would."""
        dts = np.asarray(dts, dtype=float)
        n = len(dts)
        if not (dts > 0.0).all():
            raise ValueError(f"dt must be > 0 s, got {dts[~(dts > 0.0)][0]!r}")
        x = np.asarray(true_values, dtype=float) @ self._gain.T
        x += self._offset
        walk, noisy = self.bias_random_walk > 0.0, self.noise_density > 0.0
        z = self._rng.standard_normal((n, 3 * (walk + noisy))) if walk or noisy else None
        if walk:
            # drift_i = drift_{i-1} + step_i, summed in that order (cumsum is sequential)
            drifts = z[:, :3] * (self.bias_random_walk * np.sqrt(dts))[:, None]
            drifts[0] += self.drift
            np.cumsum(drifts, axis=0, out=drifts)
            self.drift = drifts[-1].copy()
        else:
            drifts = self.drift
        x += (self.bias + self.turn_on_bias) + drifts
        if temperatures_c is not None:
            x += self.temp_coeff * (np.asarray(temperatures_c, dtype=float)[:, None] - self.reference_temp_c)
        if noisy:
            if noise_dt is not None or self.bandwidth_hz is not None:
                std = self.noise_std(dts[0] if noise_dt is None else noise_dt)  # one band
            else:  # noise_std(dt) of each reading: the Nyquist band of its own interval
                std = (self.noise_density * np.sqrt(0.5 / dts))[:, None]
            x += z[:, 3 * walk:] * std
        saturated = (np.abs(x) > self.range).any(axis=1)
        if saturated.any():
            np.clip(x, -self.range, self.range, out=x)
        self.saturated = bool(saturated[-1]) if n else self.saturated
        if self.quantisation > 0.0:
            x = np.round(x / self.quantisation) * self.quantisation
        return x, saturated

    def analog(self) -> "SensorErrorModel":
        """A fresh copy without range and quantisation: for simulated register devices that
        digitise (clip and round to their configured full scale) themselves."""
        return dataclasses.replace(self, quantisation=0.0, range=math.inf)

    def with_seed(self, seed: int) -> "SensorErrorModel":
        """A fresh copy of this model with another seed (presets are shared, copy before use)."""
        return dataclasses.replace(self, seed=int(seed))


def _array(v: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.array(v, dtype=float)
    if a.shape != shape or not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite numbers of shape {shape}, got {v!r}")
    return a


# --------------------------------------------------------------------------- part presets
# Figures are datasheet "typical" values; where a datasheet gives a ± spread of the zero
# offset, a third of it is taken as the 1σ turn-on bias. Noise densities quoted as rms over
# a bandwidth are converted with σ = density·√bandwidth. Bias random walks are not given in
# these datasheets: the values below are modest assumptions of the same order as published
# Allan-variance measurements of such consumer parts. See docs/simulator.md.


def _gyro(noise_dps: float, zero_rate_dps: float, lsb_mdps: float, fs_dps: float, tc_dps: float) -> SensorErrorModel:
    return SensorErrorModel(
        noise_density=noise_dps * DEG,
        bias_sigma=zero_rate_dps / 3.0 * DEG,
        bias_random_walk=0.001 * DEG,
        quantisation=lsb_mdps * 1e-3 * DEG,
        range=fs_dps * DEG,
        temp_coeff=np.full(3, tc_dps * DEG),
    )


def _acc(noise_ug: float, zero_g_mg: float, lsb_mg: float, fs_g: float, tc_mg: float) -> SensorErrorModel:
    return SensorErrorModel(
        noise_density=noise_ug * 1e-6 * G0,
        bias_sigma=zero_g_mg / 3.0 * 1e-3 * G0,
        bias_random_walk=1e-4,
        quantisation=lsb_mg * 1e-3 * G0,
        range=fs_g * G0,
        temp_coeff=np.full(3, tc_mg * 1e-3 * G0),
    )


def _mag(noise_ut: float, lsb_ut: float, fs_ut: float) -> SensorErrorModel:
    return SensorErrorModel(noise_density=noise_ut, quantisation=lsb_ut, range=fs_ut)


#: Presets by part name. Every call site should take a copy (``with_seed``) since models
#: carry state (drift, random generator).
PART_MODELS: dict[str, SensorErrorModel] = {
    "ideal": SensorErrorModel(),
    # ST L3G4200D (GY-80), FS ±250 dps: 0.03 dps/√Hz, zero-rate ±10 dps, 8.75 mdps/LSB, ±0.03 dps/°C
    "L3G4200D": _gyro(0.03, 10.0, 8.75, 250.0, 0.03),
    # ST L3GD20 (MinIMU-9 v2), FS ±250 dps: 0.03 dps/√Hz, zero-rate ±10 dps, 8.75 mdps/LSB, ±0.03 dps/°C
    "L3GD20": _gyro(0.03, 10.0, 8.75, 250.0, 0.03),
    # InvenSense MPU-9250 gyro, FS ±250 dps: 0.01 dps/√Hz, ZRO ±5 dps, 131 LSB/dps, ±30 dps over −40…85 °C
    "MPU9250_GYRO": _gyro(0.01, 5.0, 1000.0 / 131.0, 250.0, 30.0 / 125.0),
    # AD ADXL345 (GY-80), ±16 g full resolution: 3.9 mg/LSB; x/y noise ≈ 0.75 LSB rms at
    # 100 Hz ODR (50 Hz band) → 2.9 mg / √50 ≈ 410 µg/√Hz; 0 g offset ±150 mg, ±0.8 mg/°C
    "ADXL345": _acc(410.0, 150.0, 3.9, 16.0, 0.8),
    # ST LSM303DLHC accelerometer, FS ±2 g: 220 µg/√Hz (normal mode), zero-g ±60 mg, 1 mg/LSB, ±0.5 mg/°C
    "LSM303DLHC_ACC": _acc(220.0, 60.0, 1.0, 2.0, 0.5),
    # InvenSense MPU-9250 accelerometer, FS ±2 g: 300 µg/√Hz, zero-g ±60 mg, 16384 LSB/g, ±1.5 mg/°C
    "MPU9250_ACC": _acc(300.0, 60.0, 1000.0 / 16384.0, 2.0, 1.5),
    # Honeywell HMC5883L, gain 1090 LSB/G (±1.3 G): noise floor 2 mG rms at 15 Hz ODR
    # (7.5 Hz band) → 0.2 µT / √7.5 ≈ 0.073 µT/√Hz; 0.092 µT/LSB; range ±130 µT
    "HMC5883L": _mag(0.073, GAUSS / 1090.0, 1.3 * GAUSS),
    # ST LSM303DLHC magnetometer, ±1.3 G: 1100 LSB/G (x/y); no noise figure in the datasheet,
    # taken like the HMC5883L it derives from
    "LSM303DLHC_MAG": _mag(0.073, GAUSS / 1100.0, 1.3 * GAUSS),
    # AKM AK8963 (in the MPU-9250), 16 bit: 0.15 µT/LSB, ±4912 µT; no noise density in the
    # datasheet, ≈0.3 µT rms at 100 Hz ODR assumed → 0.042 µT/√Hz
    "AK8963": _mag(0.042, 0.15, 4912.0),
    # TDK ICM-42688-P gyro (DS-000347 Table 1), FS ±2000 dps (hi-res FIFO): 0.0028 dps/√Hz,
    # ZRO ±0.5 dps, 1/131 dps per LSB (19-bit FIFO data), ±0.005 dps/°C
    "ICM42688P_GYRO": _gyro(0.0028, 0.5, 1000.0 / 131.0, 2000.0, 0.005),
    # TDK ICM-42688-P accelerometer (Table 2), FS ±16 g (hi-res FIFO): 70 µg/√Hz, zero-g
    # ±20 mg, 8192 LSB/g (18-bit FIFO data), ±0.15 mg/°C
    "ICM42688P_ACC": _acc(70.0, 20.0, 1000.0 / 8192.0, 16.0, 0.15),
    # Bosch BMI088 gyro (BST-BMI088-DS001 Table 2), ±2000 dps: 0.014 dps/√Hz, zero-rate ±1 dps,
    # 16.384 LSB/dps, ±0.015 dps/K
    "BMI088_GYRO": _gyro(0.014, 1.0, 1000.0 / 16.384, 2000.0, 0.015),
    # Bosch BMI088 accelerometer (Table 1), ±24 g: 230 µg/√Hz, zero-g ±20 mg, 1365 LSB/g, ±0.2 mg/K
    "BMI088_ACC": _acc(230.0, 20.0, 1000.0 / 1365.33, 24.0, 0.2),
    # TDK ICM-20948 gyro (DS-000189 Table 1), ±2000 dps: 0.015 dps/√Hz, ZRO ±5 dps, 16.4 LSB/dps
    "ICM20948_GYRO": _gyro(0.015, 5.0, 1000.0 / 16.4, 2000.0, 0.05),
    # TDK ICM-20948 accelerometer (Table 2), ±16 g: 230 µg/√Hz, zero-g ±25 mg, 2048 LSB/g
    "ICM20948_ACC": _acc(230.0, 25.0, 1000.0 / 2048.0, 16.0, 0.8),
    # AKM AK09916 (in the ICM-20948): 0.15 µT/LSB, ±4912 µT; noise taken like the AK8963's
    "AK09916": _mag(0.042, 0.15, 4912.0),
}


def part_model(name: str, seed: int = 0) -> SensorErrorModel:
    """A fresh copy of the preset ``name`` with ``seed``; unknown names raise ValueError."""
    try:
        return PART_MODELS[name].with_seed(seed)
    except KeyError:
        raise ValueError(f"unknown sensor part {name!r}; available: {', '.join(PART_MODELS)}") from None


#: the parts on the source papers' boards and on the MPU-9250, as "gyr"/"acc"/"mag" sets
BOARDS: dict[str, dict[str, str]] = {
    "GY-80": {"gyr": "L3G4200D", "acc": "ADXL345", "mag": "HMC5883L"},
    "MinIMU-9v2": {"gyr": "L3GD20", "acc": "LSM303DLHC_ACC", "mag": "LSM303DLHC_MAG"},
    "MPU9250": {"gyr": "MPU9250_GYRO", "acc": "MPU9250_ACC", "mag": "AK8963"},
    "ideal": {"gyr": "ideal", "acc": "ideal", "mag": "ideal"},
}


def board_models(board: str, seed: int = 0) -> dict[str, SensorErrorModel]:
    """Fresh error models for the three sensors of ``board`` (see :data:`BOARDS`), seeds seed, seed+1, seed+2."""
    try:
        parts = BOARDS[board]
    except KeyError:
        raise ValueError(f"unknown board {board!r}; available: {', '.join(BOARDS)}") from None
    return {k: part_model(p, seed + i) for i, (k, p) in enumerate(parts.items())}
