"""A simulated IMU board: a trajectory seen through three sensor error models.

The simulated I2C devices, the simulated CAN node and :class:`~.source.SimulatedSource` all
read their values from :meth:`SimulatedImu.physics` at their own output data rate, with
``t`` in seconds on the simulation clock (:attr:`SimulatedImu.clock`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ahrs_service.core.calibration import SensorCalibration
from ahrs_service.drivers.sim.clock import ManualClock, MonotonicClock
from ahrs_service.drivers.sim.motion import MotionState, Trajectory
from ahrs_service.drivers.sim.sensor_model import SensorErrorModel

__all__ = ["ManualClock", "MonotonicClock", "SimulatedImu", "SENSORS"]

SENSORS = ("gyr", "acc", "mag")
_TRUTH_FIELD = {"gyr": "omega_body", "acc": "specific_force_body", "mag": "mag_body"}


@dataclass
class PhysicsBlock:
    """The board's readings at ``n`` times, row ``i`` at ``t[i]`` (s): what ``n`` calls of
    :meth:`SimulatedImu.physics` return, as arrays. gyr rad/s, acc m/s², mag µT: (n, 3) in the
    sensor's axes; temperature_c (n,); saturated: {sensor: (n,) bool}; truth: the true state
    (body frame) at each time."""

    t: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    temperature_c: np.ndarray
    saturated: dict[str, np.ndarray]
    truth: list[MotionState]

    def __len__(self) -> int:
        return len(self.t)

    def reading(self, i: int) -> dict[str, Any]:
        """Row ``i`` as the dict :meth:`SimulatedImu.physics` returns."""
        return {"gyr": self.gyr[i], "acc": self.acc[i], "mag": self.mag[i],
                "saturated": {k: bool(v[i]) for k, v in self.saturated.items()},
                "temperature_c": float(self.temperature_c[i]), "truth": self.truth[i]}


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
        # the motion's compiled helpers (quat_rotate_inv) loaded, or compiled at a first
        # start, now: not inside a simulated part's first FIFO read, while its FIFO fills
        trajectory.state(0.0)

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

    def physics_block(self, t: Any, period: float | None = None) -> PhysicsBlock:
        """:meth:`physics` at the ascending times ``t`` (n,) s, in one call: the readings of
        a part's FIFO burst. The same model, draw for draw (see
        :meth:`SensorErrorModel.apply_block`): each reading's dt is the time since the one
        before it (the first: since the previous call), its noise drawn over ``period``'s
        band, bias drift advanced as by ``n`` calls. The results are those of ``n`` calls of
        :meth:`physics` bit for bit, except that a mounting or a distortion matrix, applied
        as one product over the block, may differ in the last bit. The true motion is
        computed per time, as there: over a burst of ~10 times numpy's cost per array
        operation outweighs vectorising it. Times that repeat the previous call's or are not
        strictly ascending are served by :meth:`physics` one by one (a repeated time returns
        the same reading)."""
        t = np.array(t, dtype=float).reshape(-1)
        n = len(t)
        if n == 0 or (n > 1 and not (t[1:] > t[:-1]).all()) \
                or (self._last is not None and t[0] == self._last_t):
            return self._stacked([self.physics(x, period) for x in t.tolist()], t)
        dts = np.empty(n)
        dts[0] = t[0] - self._last_t if self._last_t is not None and t[0] > self._last_t else self._nominal_dt
        np.subtract(t[1:], t[:-1], out=dts[1:])
        truth = [self.trajectory.state(x) for x in t.tolist()]
        temps = np.array([self.temperature(x) for x in t.tolist()]) if callable(self._temperature) \
            else np.full(n, float(self._temperature))
        out: dict[str, np.ndarray] = {}
        saturated: dict[str, np.ndarray] = {}
        for k in SENSORS:
            v = np.array([getattr(state, _TRUTH_FIELD[k]) for state in truth])
            if self._mt is not None:
                v = v @ self._mt.T
            out[k], saturated[k] = self.models[k].apply_block(v, dts, temps, noise_dt=period)
        block = PhysicsBlock(t, out["gyr"], out["acc"], out["mag"], temps, saturated, truth)
        self._last_t, self._last = float(t[-1]), block.reading(n - 1)
        return block

    @staticmethod
    def _stacked(readings: list[dict[str, Any]], t: np.ndarray) -> PhysicsBlock:
        """A block of readings :meth:`physics` returned one by one."""
        n = len(readings)
        return PhysicsBlock(
            t, *(np.array([r[k] for r in readings], dtype=float).reshape(n, 3) for k in SENSORS),
            np.array([r["temperature_c"] for r in readings], dtype=float),
            {k: np.array([r["saturated"][k] for r in readings], dtype=bool) for k in SENSORS},
            [r["truth"] for r in readings])

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
