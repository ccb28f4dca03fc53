"""A simulated IMU board: a trajectory seen through three sensor error models.

The simulated I2C devices, the simulated CAN node and :class:`~.source.SimulatedSource` all
read their values from :meth:`SimulatedImu.physics` at their own output data rate, with
``t`` in seconds on the simulation clock (:attr:`SimulatedImu.clock`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ahrs_service.drivers.calibration import SensorCalibration
from ahrs_service.drivers.sim.clock import ManualClock, MonotonicClock
from ahrs_service.drivers.sim.motion import MotionState, Trajectory
from ahrs_service.drivers.sim.sensor_model import SensorErrorModel

__all__ = ["ManualClock", "MonotonicClock", "SimulatedImu", "SENSORS"]

SENSORS = ("gyr", "acc", "mag")
_TRUTH_FIELD = {"gyr": "omega_body", "acc": "specific_force_body", "mag": "mag_body"}


class SimulatedImu:
    """The sensors of one board following ``trajectory``.

    models: error models by sensor, keys among "gyr", "acc", "mag"; missing ones are ideal.
        The IMU works on fresh copies (``self.models``): the given objects are not changed.
    clock: the simulation clock (``MonotonicClock`` by default); devices read ``clock.now()``.
    seed: seeds the models' copies with seed, seed+1, seed+2 (gyr, acc, mag) so one number
        makes a whole run reproducible; None keeps the models' own seeds.
    mounting: (3, 3) rotation from sensor axes to body FRD (v_body = M v_sensor), as in
        ``SensorCalibration.mounting``; the sensors see Mᵀ·(body truth). Default identity.
    temperature_c: die temperature in °C, a number or a callable of t (s).
    nominal_rate_hz: sampling rate assumed for the noise of the very first reading (no
        previous reading to measure dt from).
    """

    def __init__(
        self,
        trajectory: Trajectory,
        models: Mapping[str, SensorErrorModel] | None = None,
        clock: Any = None,
        seed: int | None = 0,
        *,
        mounting: Any = None,
        temperature_c: float | Callable[[float], float] = 25.0,
        nominal_rate_hz: float = 100.0,
    ) -> None:
        models = dict(models or {})
        unknown = set(models) - set(SENSORS)
        if unknown:
            raise ValueError(f"models: unknown sensor key(s) {sorted(unknown)}; use {SENSORS}")
        self.trajectory = trajectory
        # own copies: presets (PART_MODELS) can be passed directly and are never mutated,
        # and one model object given for two sensors does not share a random stream
        self.models: dict[str, SensorErrorModel] = {}
        for i, k in enumerate(SENSORS):
            given = models.get(k)
            if given is None:
                given = SensorErrorModel()
            self.models[k] = given.with_seed(given.seed if seed is None else seed + i)
        self.clock = clock if clock is not None else MonotonicClock()
        if mounting is None:
            self._mt = None
        else:
            m = np.array(mounting, dtype=float)
            if m.shape != (3, 3) or not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
                raise ValueError("mounting must be a (3, 3) rotation matrix (sensor axes to body FRD)")
            self._mt = m.T.copy()
        self._temperature = temperature_c
        if not nominal_rate_hz > 0:
            raise ValueError(f"nominal_rate_hz must be > 0, got {nominal_rate_hz!r}")
        self._nominal_dt = 1.0 / nominal_rate_hz
        self._last_t: float | None = None
        self._last: dict[str, Any] | None = None

    def temperature(self, t: float) -> float:
        """Die temperature in °C at time t."""
        return float(self._temperature(t)) if callable(self._temperature) else float(self._temperature)

    def truth(self, t: float) -> MotionState:
        """The true motion at time t, without sensor errors (body frame)."""
        return self.trajectory.state(t)

    def physics(self, t: float, period: float | None = None) -> dict[str, Any]:
        """The board's readings at simulation time ``t`` (s).

        Returns {"gyr": rad/s, "acc": m/s² specific force, "mag": µT} as (3,) arrays in the
        sensor's axes with the error models applied, "saturated": {sensor: bool},
        "temperature_c" and "truth" (the :class:`MotionState`, body frame). The same ``t`` as
        the previous call gives the same result (two devices of one board read one instant);
        noise and drift advance once per distinct t. ``period``: the sampling period (s) of
        the part asking; its readings' white noise is drawn over that part's band (bias drift
        still advances by the time since the previous call), not over the gap since another
        part's reading, which is tiny where two parts' sample grids almost coincide.
        """
        t = float(t)
        if self._last is not None and t == self._last_t:
            return self._last
        truth = self.trajectory.state(t)
        dt = self._nominal_dt
        if self._last_t is not None and t > self._last_t:
            dt = t - self._last_t
        temp = self.temperature(t)
        out: dict[str, Any] = {"saturated": {}}
        for k in SENSORS:
            v = getattr(truth, _TRUTH_FIELD[k])
            if self._mt is not None:
                v = self._mt @ v
            model = self.models[k]
            out[k] = model.apply(v, dt, temp, noise_dt=period)
            out["saturated"][k] = model.saturated
        out["temperature_c"] = temp
        out["truth"] = truth
        self._last_t, self._last = t, out
        return out

    def ideal_calibration(self) -> SensorCalibration:
        """The calibration a perfect procedure would find now, for this board's models and mounting.

        Undoes the static errors: gyro and accelerometer offsets (constant + turn-on + drift
        so far, at the reference temperature), accelerometer scale/misalignment, hard and
        soft iron, and the mounting. Noise, quantisation, later drift and temperature effects
        remain; so does a gyro scale error (the calibration has no term for it).
        """
        def offset(k: str) -> np.ndarray:
            m = self.models[k]
            return m.offset + m.total_bias

        return SensorCalibration(
            gyro_bias=offset("gyr"),
            acc_bias=offset("acc"),
            acc_scale=np.linalg.inv(self.models["acc"].distortion),
            mag_hard_iron=offset("mag"),
            mag_soft_iron=np.linalg.inv(self.models["mag"].distortion),
            mounting=np.eye(3) if self._mt is None else self._mt.T,
        )

    def now(self) -> float:
        """The simulation clock's time in s."""
        return self.clock.now()

    @property
    def finished(self) -> bool:
        """True once the clock has passed the end of a finite, non-looping trajectory."""
        tr = self.trajectory
        return not tr.looping and math.isfinite(tr.duration) and self.clock.now() > tr.duration
