"""The estimator base class: parameters, explicit state and one compiled step function.

Each estimator is one small class (``madgwick.Madgwick`` …) with

* ``Params`` — a dataclass: every tuning parameter, its unit and default, documented;
* ``step`` — a numba-compiled function ``step(state, params, row)`` that advances the state
  by one sample row (see ``_kernel``) and reads like the paper's equations;
* ``batch`` — the same step looped over an (N, 10) array, compiled, for ``run`` and replay.

The per-sample path (``update``) and the batch path (``run``) call the same ``step``, so a
replay reproduces what the service published.

Each estimator module writes its own four-line ``batch`` loop on purpose: numba caches only
functions defined at module level, and a generic loop that takes the step as an argument (or
a closure over it) is compiled anew at every start — seconds of start-up for the service.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, ClassVar

import numpy as np
from numba import njit

from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.uncertainty import AttitudeVariance, ErrorModel

_H = K.HEADER_SLICES
_R = K.ROW_SLICES


class Estimator:
    """Base of all attitude estimators.

    Subclasses set ``name``, ``Params``, ``uses_mag``, ``observes_heading``, ``state_size``,
    ``step`` and ``batch``, and may override ``initial_state`` (covariances and the like).
    The estimate is q_earth←body, [w, x, y, z], earth NED, body FRD.

    ``attitude_variance()`` reports the uncertainty of the current attitude: from the
    ``error_model`` here, overridden by the estimators that keep a covariance (see
    ``uncertainty``).
    """

    name: ClassVar[str]
    Params: ClassVar[type]
    uses_mag: ClassVar[bool] = False
    observes_heading: ClassVar[bool] = False
    state_size: ClassVar[int] = K.HEADER
    step: ClassVar[Any]
    batch: ClassVar[Any]
    #: attitude error model of the estimators without a covariance of their own (``uncertainty``)
    error_model: ClassVar[ErrorModel] = ErrorModel()

    def __init__(self, **params: float) -> None:
        self.params = _make_params(self.Params, params, self.name)
        self._p = self._pack(self.params)
        self._row = np.full(K.ROW, np.nan)
        self.state = self.initial_state()
        # the hot path avoids attribute and slice work: a bound kernel and a fixed view of q
        self._step = type(self).step
        self._q = self.state[_H.q]

    # ---------------------------------------------------------------- parameters
    def _pack(self, params: Any) -> np.ndarray:
        return np.array([float(v) for v in dataclasses.astuple(params)], dtype=np.float64)

    @classmethod
    def param_names(cls) -> list[str]:
        return [f.name for f in dataclasses.fields(cls.Params)]

    def get_params(self) -> dict[str, float]:
        return dataclasses.asdict(self.params)

    def set_params(self, **changes: float) -> None:
        """Changes tuning parameters live; the state is kept. Unknown names raise ValueError."""
        new = _make_params(self.Params, {**self.get_params(), **changes}, self.name)
        self.params = new
        self._p[:] = self._pack(new)

    # ---------------------------------------------------------------- state
    def initial_state(self) -> np.ndarray:
        """State before the first sample: identity attitude, not initialised, zero counters."""
        s = np.zeros(self.state_size)
        s[K.Q] = 1.0
        s[K.ACC_AGE] = s[K.MAG_AGE] = K.NO_SAMPLE_YET
        return s

    def reset(self) -> None:
        """Back to the state before the first sample (in place: views of the state stay valid)."""
        self.state[:] = self.initial_state()

    @property
    def quaternion(self) -> np.ndarray:
        """Current q_earth←body [w, x, y, z] (a copy)."""
        return self.state[_H.q].copy()

    @property
    def gyro_bias(self) -> np.ndarray:
        """Current gyro-bias estimate, rad/s, body frame (zeros where not estimated)."""
        return self.state[_H.bias].copy()

    def attitude_variance(self) -> AttitudeVariance:
        """Variances of the current roll, pitch and yaw (ZYX Euler angles), rad²; NaN where
        unknown (before initialisation; yaw of the estimators that do not observe heading, or
        before the first usable field sample): the estimator's own model
        (``_model_variance``) plus, in each angle, the variance of the rotation sample gaps
        left unobserved that the corrections may not yet have removed (the header's
        ``gap_sigma`` and ``gap_sigma_heading``, docs/gaps.md)."""
        tilt, heading = float(self.state[K.GAP_SIGMA]), float(self.state[K.GAP_SIGMA_HEADING])
        return self._model_variance().plus(tilt * tilt, heading * heading)

    def _model_variance(self) -> AttitudeVariance:
        """The estimator's own variance model. This default is the ``error_model`` over the
        ages of the newest usable accelerometer and magnetometer samples; estimators with a
        covariance override it."""
        s = self.state
        if not s[K.INITIALISED]:
            return AttitudeVariance.unknown()
        return self.error_model.variance(
            sample_age(s[K.ACC_AGE]), sample_age(s[K.MAG_AGE]), self.observes_heading and self.uses_mag
        )

    @property
    def diagnostics(self) -> dict[str, float]:
        s = self.state
        return {
            "initialised": bool(s[K.INITIALISED]),
            "acc_skipped": int(s[K.ACC_SKIPPED]),
            "mag_skipped": int(s[K.MAG_SKIPPED]),
            "gyr_skipped": int(s[K.GYR_SKIPPED]),
            # sample gaps bridged, and the 1σ of the rotation they may have left uncorrected, as
            # attitude_variance() adds it (docs/gaps.md)
            "gaps": int(s[K.GAPS]),
            "gap_error_deg": math.degrees(float(s[K.GAP_SIGMA])),
            "realignments": int(s[K.REALIGNMENTS]),
            # logged with the attitude at log.diagnostics_hz (logs/schemas.py ATTITUDE)
            "attitude_variance": self.attitude_variance().as_dict(),
        }

    # ---------------------------------------------------------------- stepping
    def update(self, gyr: Any, acc: Any, mag: Any = None, *, dt: float) -> np.ndarray:
        """Advances by one sample taken ``dt`` seconds after the previous one.

        gyr rad/s, acc m/s² (specific force), mag µT or None, all in the sensor's axes.
        Returns the new q_earth←body (a view into the state; copy it to keep it).
        """
        row = self._row
        row[_R.gyr] = gyr
        row[_R.acc] = acc
        if mag is None:
            row[_R.mag] = np.nan
        else:
            row[_R.mag] = mag
        row[K.DT] = dt
        return self.update_row(row)

    def update_row(self, row: np.ndarray) -> np.ndarray:
        """Fast path for the service: ``row`` is a filled float64 sample row (see ``_kernel``).

        Returns the new q_earth←body (a view into the state; copy it to keep it).
        """
        self._step(self.state, self._p, row)
        return self._q

    def run(self, gyr: Any, acc: Any, mag: Any = None, *, dt: Any) -> np.ndarray:
        """Runs over N samples from the current state; returns (N, 4) quaternions.

        ``dt`` is a scalar or an (N,) array of time steps in seconds.
        """
        return self.run_rows(stack_rows(gyr, acc, mag, dt))

    def run_rows(self, rows: np.ndarray) -> np.ndarray:
        """Runs over (N, 10) filled sample rows (see ``_kernel``) from the current state;
        returns (N, 4) quaternions. For callers that hold rows already (replay, offline)."""
        rows = np.ascontiguousarray(rows, dtype=np.float64)
        if rows.ndim != 2 or rows.shape[1] != K.ROW:
            raise ValueError(f"rows must have shape (N, {K.ROW}), got {rows.shape}")
        out = np.empty((rows.shape[0], 4))
        self.batch(self.state, self._p, rows, out)
        return out


def sample_age(age: float) -> float:
    """A header ``acc_age`` / ``mag_age`` in s, ``inf`` before the first usable sample."""
    return math.inf if age < 0.0 else float(age)


def stack_rows(gyr: Any, acc: Any, mag: Any, dt: Any) -> np.ndarray:
    """(N, 10) sample rows from (N, 3) gyr/acc/mag arrays (mag may be None) and dt."""
    gyr = np.asarray(gyr, dtype=np.float64)
    acc = np.asarray(acc, dtype=np.float64)
    if gyr.ndim != 2 or gyr.shape[1] != 3:
        raise ValueError(f"gyr must have shape (N, 3), got {gyr.shape}")
    if acc.shape != gyr.shape:
        raise ValueError(f"acc must have the shape of gyr {gyr.shape}, got {acc.shape}")
    n = gyr.shape[0]
    if mag is None:
        mag = np.full((n, 3), np.nan)
    else:
        mag = np.asarray(mag, dtype=np.float64)
        if mag.shape != gyr.shape:
            raise ValueError(f"mag must have the shape of gyr {gyr.shape}, got {mag.shape}")
    rows = np.empty((n, K.ROW))
    _fill_rows(rows, gyr, acc, mag, np.broadcast_to(np.asarray(dt, dtype=np.float64), (n,)))
    return rows


@njit(cache=True)
def _fill_rows(rows, gyr, acc, mag, dt):
    # one pass row by row: a third of the time of four strided column copies
    for i in range(rows.shape[0]):
        for k in range(3):
            rows[i, K.GYR + k] = gyr[i, k]
            rows[i, K.ACC + k] = acc[i, k]
            rows[i, K.MAG + k] = mag[i, k]
        rows[i, K.DT] = dt[i]


def time_steps(
    n: int, rate_hz: float | None = None, timestamps: Any = None, *, recover_clock: bool = True
) -> np.ndarray:
    """Per-sample time steps (s) from timestamps (s, monotonic) or a nominal rate.

    The first sample's dt is the nominal period (the median step when only timestamps are
    given). Timestamps win over the rate when both are given. With ``recover_clock`` (the
    default) the stamps first go through ``sample_clock.recover_times`` (causal; exactly
    uniform stamps pass unchanged; ``rate_hz``, when given, is the nominal rate): host stamps
    jitter, and integrating each jittered step as true costs accuracy (docs/timing.md).
    Implausible stamps raise ValueError (``check_timestamps``).
    """
    if timestamps is not None:
        t = np.asarray(timestamps, dtype=np.float64)
        if t.shape != (n,):
            raise ValueError(f"timestamps must have shape ({n},), got {t.shape}")
        check_timestamps(t, allow_equal=recover_clock)
        if recover_clock and n > 1:
            from ahrs_service.core.sample_clock import recover_times

            t = recover_times(t, nominal_rate_hz=rate_hz)
        dt = np.empty(n)
        if n == 0:
            return dt
        dt[1:] = np.diff(t)
        if rate_hz is not None:
            dt[0] = 1.0 / float(rate_hz)
        else:
            dt[0] = float(np.median(dt[1:])) if n > 1 else 0.0
        return dt
    if rate_hz is None:
        raise ValueError("give rate_hz or timestamps: estimators need each sample's time step")
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    return np.full(n, 1.0 / float(rate_hz))


#: Steps longer than this (s) are not an IMU's sampling: the stamps are in another unit.
MAX_STEP_S = 1.0


def check_timestamps(t: np.ndarray, *, allow_equal: bool = False) -> None:
    """ValueError naming the problem when ``t`` (s) cannot be an IMU's sample times: NaN or
    infinite stamps, stamps that go backwards (or repeat, unless ``allow_equal``: a burst of
    samples read at once, which clock recovery spreads out, but not all of them), or a median
    step between distinct stamps over a second (milliseconds, microseconds or nanoseconds given
    where seconds are expected, bursts included)."""
    if t.size == 0:
        return
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(
            f"timestamps: {int(bad.sum())} NaN or infinite value(s), first at sample {i}; "
            "expected finite sample times in seconds"
        )
    if t.size < 2:
        return
    steps = np.diff(t)
    back = steps < 0 if allow_equal else steps <= 0
    if back.any():
        i = int(np.argmax(back))
        what = "negative" if allow_equal else "zero or negative"
        order = "non-decreasing" if allow_equal else "strictly increasing"
        raise ValueError(
            f"timestamps: not increasing at sample {i + 1} ({float(t[i]):.9g} s then {float(t[i + 1]):.9g} s), "
            f"{int(back.sum())} step(s) {what}; expected {order} sample times in seconds"
        )
    # the unit from the steps between distinct stamps: with bursts (a FIFO read's samples share
    # one host stamp) most steps are 0, and their median said nothing about the unit
    moving = steps[steps > 0]
    if moving.size == 0:
        raise ValueError(
            f"timestamps: all {t.size} are equal ({float(t[0]):.9g} s): no time passes; "
            "expected sample times in seconds"
        )
    median = float(np.median(moving))
    if median > MAX_STEP_S:
        guess = "nanoseconds" if median > 1e5 else ("microseconds" if median > 100 else "milliseconds")
        raise ValueError(
            f"timestamps: median step {median:g} is over {MAX_STEP_S:g} s; these look like "
            f"{guess}, expected seconds (divide by {1e9 if guess == 'nanoseconds' else 1e6 if guess == 'microseconds' else 1e3:g})"
        )


def _make_params(params_cls: type, values: dict[str, Any], name: str) -> Any:
    known = {f.name for f in dataclasses.fields(params_cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {', '.join(unknown)} for estimator {name!r}; "
            f"accepted: {', '.join(sorted(known)) or '(none)'}"
        )
    clean = {}
    for key, value in values.items():
        # a number, not a string or a boolean that float() would also take ("1.5", True):
        # a recorded or typed value of the wrong kind is refused, never silently converted
        if isinstance(value, (str, bytes, bool, np.bool_)):
            raise ValueError(f"parameter {key!r} of estimator {name!r} must be a number, got {value!r}")
        try:
            clean[key] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"parameter {key!r} of estimator {name!r} must be a number, got {value!r}") from None
        if not np.isfinite(clean[key]):
            raise ValueError(f"parameter {key!r} of estimator {name!r} must be finite, got {value!r}")
    return params_cls(**clean)
