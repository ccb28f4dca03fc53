"""Offline (non-causal) attitude for recordings: a forward-backward smoother over any estimator.

A causal estimator gives, at each sample, the best attitude from the samples *up to* it. When
a whole recording is at hand (a replayed flight log, a BROAD trial) the best attitude after
the fact may also use the samples after it. This module gets that from the causal estimators
themselves, without touching their kernels:

1. **forward pass** — the estimator as it runs live (``estimators.run``);
2. **backward pass** — a fresh instance of the same estimator over the time-reversed
   recording with the gyroscope negated (:func:`reverse_rows`). Its output, put back into
   forward order, estimates the attitude at each sample *from the samples after it*;
3. **fusion** — per sample, a weighted quaternion average of the two (:func:`fuse`), each
   pass weighted by how long it has been running at that sample (:func:`forward_share`).

>>> from ahrs_service.estimators import offline
>>> q = offline.smooth("robust", gyr, acc, mag, rate_hz=285.714)          # doctest: +SKIP

The output has the meaning of ``estimators.run``'s: (N, 4) q_earth←body [w, x, y, z], earth
NED, body FRD, one row per sample.

Why the backward pass needs no conversion
-----------------------------------------
Every estimator integrates q_k = q_{k−1} ⊗ exp(ω_k dt_k / 2), where gyro sample k is the body
rate over (t_{k−1}, t_k] and dt_k = t_k − t_{k−1}. Undoing that step gives
q_{k−1} = q_k ⊗ exp(−ω_k dt_k / 2): the same integrator, fed the *negated* rate, walks the same
q_earth←body(t) backwards in time. Gravity and the magnetic field are earth-fixed, so the
accelerometer and magnetometer rows keep their meaning unchanged. The backward attitude is
therefore the same quantity as the forward one (no frame change, no conjugate). The only care
is the pairing: the backward step that arrives at sample k must use the gyro and dt of sample
k + 1 (the interval it crosses), together with the accelerometer and magnetometer of sample
k. Reversing whole rows instead would pair each rate with the wrong interval and make the
backward pass lag one sample behind the forward one; ``tests/test_offline.py`` checks on an
exact simulated trajectory that the backward pass, paired as here, tracks the truth as closely
as the forward pass does.

So the two passes have the same timing: there is no half-sample lead of the backward pass to
cancel a half-sample lag of the forward one. (With whole rows reversed there would be, if the
gyro delivered the rate *at* t_k rather than over the interval before it: each pass would then
be half a sample off, in opposite directions. The estimators, the simulator and the tests all
take the interval reading, and on BROAD the exact pairing scores clearly better than whole
rows reversed; figures: docs/evaluation.md, "Offline mode".) What does cancel is the lag of
each filter's *corrections*, see "Why it helps".

Each pass has its own start-up: it begins from the first usable accelerometer (and
magnetometer) sample *in its own direction*, learns its gyro bias and settles its corrections
from there. NaN rows and a missing magnetometer are handled by the estimator itself, in both
passes alike, exactly as in a causal run.

The fusion weights
------------------
At sample k let t_f be the time since the forward pass started (its first usable
accelerometer sample) and t_b the time until the backward pass's start (the last one). Each
pass gets the weight w = 1 − exp(−t / τ) with τ = ``blend_time_s`` (default
:data:`DEFAULT_BLEND_TIME_S`, 10 s), and the forward pass's share of the average is
w_f / (w_f + w_b). So at the start of a recording the estimate is the backward pass's (which
has had the whole recording to converge), at the end the forward pass's, and everywhere more
than a few τ from both ends the two weigh equally.

The default is about three times the accelerometer time constant of ``robust`` and VQF
(3 s), so a pass counts fully once it has settled from an ordinary start. From a bad start (a
recording that begins in motion) estimators with disturbance rejection take much longer:
``robust`` and ``ekf`` are still far off after one τ where Madgwick has long settled
(``tests/test_offline.py``'s simulation). Raise τ for such recordings: a longer τ lowers the
offline error's peak in the first seconds, at a small cost where the passes are good. On
BROAD, whose trials begin and end at rest outside the scored samples, τ hardly matters.
Figures: docs/evaluation.md, "Offline mode".

The average is a normalised linear interpolation (nlerp) of the two quaternions after putting
them in the same hemisphere (q and −q are one attitude). It departs from slerp by a term of
third order in the angle between the passes: under 0.005° for passes 20° apart, 0.13° for
60°. Near the ends, where the passes may differ by more, one weight is close to 0 or 1, where
nlerp is exact.

Heading without a magnetometer
------------------------------
An estimator that does not observe heading (no magnetometer, or a reduced form) integrates
yaw from the gyro, starting from 0 at its own first sample: the backward pass's yaw is then
the forward one's plus a constant (both integrate the same gyro, bias included). Averaging
the two would slide the heading reference from one pass's to the other's along the recording,
so the backward pass is first turned about the vertical by the weighted circular mean of that
offset (:func:`align_heading`), estimated where both passes have converged. The result keeps
the forward pass's heading reference, as the causal estimator does. The inclination is not
affected: a rotation about the earth's vertical changes heading only.

Why it helps
------------
* **Start-up**: at the beginning of a recording the causal estimate has not converged yet
  (initial attitude from one perhaps disturbed sample, gyro bias not yet learned); the
  backward pass arrives there converged, with the bias learned over the whole recording.
  Symmetrically at the end.
* **Disturbances from both sides**: a disturbance (linear acceleration, a magnet) that drags
  a filter off leaves an error that decays *after* it in the forward pass and *before* it in
  the backward pass; the average halves it, and where one pass had rejected the disturbed
  samples and drifted on the gyro, the other pass's drift runs in the opposite direction.
* **Zero phase**: averaging a causal low-pass correction with its time-reversed twin gives a
  symmetric (zero-phase) correction kernel, so slowly varying accelerometer and
  magnetometer errors are smoothed without the causal filter's lag behind them.

It cannot remove what both passes share: a lag of the sensor itself (its own filters) is seen
by both. On BROAD every estimate lags the optical reference by about half a sample (see the
``robust`` estimator's ``output_lead``), the backward pass's and the offline one's as well:
scored against the reference taken half a sample earlier, each of them would be clearly
better (figures: docs/evaluation.md, "Offline mode"). And the two passes are two different
estimates: a filter tuned on forward runs of a data set may do worse backwards on it (see
docs/evaluation.md, "Offline mode").

Cost: two estimator runs and an O(N) fusion in NumPy, about three times the causal batch run
(``ahrs-service evaluate --offline`` prints the figure per column; measured figures:
docs/evaluation.md, "Offline mode").
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable, Mapping

import numpy as np

from ahrs_service import estimators
from ahrs_service.core.quaternion import quat_conj_array, quat_mul_array, vecs_are_usable
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import stack_rows, time_steps

#: Default time constant (s) of the fusion weights w = 1 − exp(−t / τ).
DEFAULT_BLEND_TIME_S = 10.0

#: A pass runner: (N, 10) sample rows (see ``_kernel``) → (N, 4) q_earth←body, one fresh run.
RowRunner = Callable[[np.ndarray], np.ndarray]


@dataclass
class OfflineResult:
    """Both passes and their fusion; every array in forward time order, one row per sample.

    q: (N, 4) the offline estimate, q_earth←body [w, x, y, z] (NED).
    forward: (N, 4) the causal pass, exactly what ``estimators.run`` returns.
    backward: (N, 4) the backward pass (after heading alignment, when applied).
    forward_share: (N,) the forward pass's weight in ``q``, from 0 (backward only) to 1.
    heading_offset_rad: the constant rotation about the vertical applied to the backward
        pass (rad), or None when heading is observed and nothing was aligned.
    """

    q: np.ndarray
    forward: np.ndarray
    backward: np.ndarray
    forward_share: np.ndarray
    heading_offset_rad: float | None = None


# ------------------------------------------------------------------------------ public entry


def smooth(name: str, gyr: Any, acc: Any, mag: Any = None, **options: Any) -> np.ndarray:
    """Offline attitude of a whole recording: (N, 4) q_earth←body [w, x, y, z], NED.

    ``options`` as for :func:`smooth_passes`; this is its ``.q``.
    """
    return smooth_passes(name, gyr, acc, mag, **options).q


def smooth_passes(
    name: str,
    gyr: Any,
    acc: Any,
    mag: Any = None,
    *,
    rate_hz: float | None = None,
    timestamps: Any = None,
    dt: Any = None,
    params: Mapping[str, float] | None = None,
    blend_time_s: float = DEFAULT_BLEND_TIME_S,
) -> OfflineResult:
    """Offline attitude of a whole recording, with both passes and the weights (:class:`OfflineResult`).

    Inputs as for ``estimators.run``: gyr rad/s, acc m/s² (specific force), mag µT or None,
    each (N, 3) in the sensor's axes, NaN rows allowed. Time steps come from ``dt`` (s, scalar
    or (N,)) when given, else from ``timestamps`` (s) or ``rate_hz``. ``params`` are the
    estimator's tuning parameters (unknown names raise ``ValueError``); ``blend_time_s`` the
    time constant (s) of the fusion weights. See the module notes for the method.
    """
    params = dict(params or {})
    estimators.create(name, **params)  # unknown or bad parameters raise before any work
    n = np.shape(gyr)[0]
    steps = np.asarray(dt, dtype=np.float64) if dt is not None else time_steps(n, rate_hz, timestamps)
    rows = stack_rows(gyr, acc, mag, steps)

    def run_rows(r: np.ndarray) -> np.ndarray:
        return estimators.create(name, **params).run_rows(r)

    return smooth_rows(run_rows, rows, blend_time_s=blend_time_s, align=not heading_observed(name, rows))


def smooth_rows(
    run_rows: RowRunner,
    rows: np.ndarray,
    *,
    blend_time_s: float = DEFAULT_BLEND_TIME_S,
    align: bool = False,
) -> OfflineResult:
    """Forward-backward smoothing of any causal estimator given as a row runner.

    ``run_rows(rows)`` must run a *fresh* estimator over (N, 10) sample rows and return its
    (N, 4) q_earth←body (NED); it is called twice, on ``rows`` and on :func:`reverse_rows`.
    ``align``: turn the backward pass's heading onto the forward pass's (for estimators or runs
    that do not observe heading, see :func:`heading_observed`).
    """
    blend_time_s = blend_time(blend_time_s)
    rows = np.asarray(rows, dtype=np.float64)
    q_forward = np.asarray(run_rows(rows), dtype=np.float64)
    q_backward = np.asarray(run_rows(reverse_rows(rows)), dtype=np.float64)[::-1]
    return combine(q_forward, q_backward, rows, blend_time_s=blend_time_s, align=align)


def combine(
    q_forward: np.ndarray,
    q_backward: np.ndarray,
    rows: np.ndarray,
    *,
    blend_time_s: float = DEFAULT_BLEND_TIME_S,
    align: bool = False,
) -> OfflineResult:
    """Fuses a forward pass and a backward pass (already back in forward order) of ``rows``.

    For callers that run the passes themselves (a log replay applying recorded parameter
    changes, say); :func:`smooth_rows` is this plus the two runs.
    """
    blend_time_s = blend_time(blend_time_s)
    q_forward = np.asarray(q_forward, dtype=np.float64)
    q_backward = np.asarray(q_backward, dtype=np.float64)
    rows = np.asarray(rows, dtype=np.float64)
    if q_forward.shape != q_backward.shape or q_forward.shape != (rows.shape[0], 4):
        raise ValueError(
            f"passes {q_forward.shape} and {q_backward.shape} must both be ({rows.shape[0]}, 4) like the rows"
        )
    t_fwd, t_bwd = pass_times(rows)
    w_fwd, w_bwd = _weight(t_fwd, blend_time_s), _weight(t_bwd, blend_time_s)
    offset = None
    if align:
        q_backward, offset = align_heading(q_forward, q_backward, w_fwd * w_bwd)
    share = forward_share(w_fwd, w_bwd)
    return OfflineResult(fuse(q_forward, q_backward, share), q_forward, q_backward, share, offset)


# ------------------------------------------------------------------------------ the pieces


def reverse_rows(rows: np.ndarray) -> np.ndarray:
    """The backward pass's input: (N, 10) sample rows in reverse time order, gyro negated.

    Backward row j holds the accelerometer and magnetometer of sample k = N−1−j, and the
    negated gyro and the dt of sample k + 1: the step from sample k + 1 back to sample k
    crosses the interval (t_k, t_{k+1}] that sample k + 1's rate and dt describe, so it is the
    exact inverse of the forward step k → k + 1. The first backward row (sample N−1) only
    starts the estimator, whose gyro and dt are not integrated (start-up rule in ``_kernel``);
    it keeps sample N−1's own.
    """
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != K.ROW:
        raise ValueError(f"rows must have shape (N, {K.ROW}), got {rows.shape}")
    out = rows[::-1].copy()
    g = slice(K.GYR, K.GYR + 3)
    out[:, g] = -out[:, g]
    if rows.shape[0] > 1:
        out[1:, g] = -rows[:0:-1, g]  # samples N−1, N−2, …, 1
        out[1:, K.DT] = rows[:0:-1, K.DT]
    return out


def pass_times(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) time (s) each pass has been running at each sample: (forward, backward).

    A pass starts at its first usable accelerometer sample in its own direction (the
    estimators' start-up rule); before that, and at it, its time is 0. Time adds up the
    valid time steps only (a row whose dt the estimators would skip adds nothing).
    """
    rows = np.asarray(rows, dtype=np.float64)
    n = rows.shape[0]
    if n == 0:
        return np.zeros(0), np.zeros(0)
    dt = rows[:, K.DT]
    valid_dt = np.where(np.isfinite(dt) & (dt > 0.0) & (dt < 1e3), dt, 0.0)
    t = np.cumsum(valid_dt)
    usable = vecs_are_usable(rows[:, K.ACC : K.ACC + 3])
    if not usable.any():
        return np.zeros(n), np.zeros(n)
    first, last = int(np.argmax(usable)), n - 1 - int(np.argmax(usable[::-1]))
    return np.maximum(t - t[first], 0.0), np.maximum(t[last] - t, 0.0)


def blend_time(value: float | None) -> float:
    """The fusion time constant to use (s): ``value``, or :data:`DEFAULT_BLEND_TIME_S` for None.
    ValueError unless it is a positive finite number of seconds (the command lines' check too)."""
    if value is None:
        return DEFAULT_BLEND_TIME_S
    if not (value > 0.0 and math.isfinite(value)):
        raise ValueError(f"blend_time_s (--offline-blend) must be a positive number of seconds, got {value}")
    return float(value)


def _weight(t: np.ndarray, blend_time_s: float) -> np.ndarray:
    return -np.expm1(-np.asarray(t, dtype=np.float64) / blend_time_s)  # 1 − exp(−t/τ), exact near 0


def forward_share(w_forward: np.ndarray, w_backward: np.ndarray) -> np.ndarray:
    """(N,) share w_f / (w_f + w_b) of the forward pass; 1 (the causal estimate) where both are 0."""
    total = w_forward + w_backward
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total > 0.0, w_forward / np.where(total > 0.0, total, 1.0), 1.0)


def fuse(q_forward: np.ndarray, q_backward: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(N, 4) normalised weighted average share·q_f + (1 − share)·q_b, hemisphere-aligned.

    Where one pass is not finite the other is taken as it is.
    """
    qf = np.asarray(q_forward, dtype=np.float64)
    qb = np.asarray(q_backward, dtype=np.float64)
    a = np.asarray(share, dtype=np.float64)[:, None]
    sign = np.where(np.sum(qf * qb, axis=1, keepdims=True) < 0.0, -1.0, 1.0)
    q = a * qf + (1.0 - a) * sign * qb
    ok_f, ok_b = np.isfinite(qf).all(axis=1), np.isfinite(qb).all(axis=1)
    q = np.where((ok_f & ~ok_b)[:, None], qf, q)
    q = np.where((ok_b & ~ok_f)[:, None], qb, q)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    # a zero norm needs q_f = −q_b with share ½, i.e. two passes 360° apart: cannot happen for
    # unit inputs after the hemisphere flip, but never divide by it
    return q / np.where(norm > 0.0, norm, 1.0)


def heading_offset(q_forward: np.ndarray, q_backward: np.ndarray, weight: np.ndarray) -> float | None:
    """Weighted circular mean (rad) of the rotation about the vertical from q_b to q_f.

    Per sample, the earth-frame difference e = q_f ⊗ q_b⁻¹ is split into a rotation about
    the vertical (NED z) and the rest; its vertical part is 2·atan2(e_z, e_w). None when no
    sample has a positive weight and two finite passes.
    """
    e = quat_mul_array(q_forward, quat_conj_array(q_backward))
    w = np.asarray(weight, dtype=np.float64)
    ok = np.isfinite(e).all(axis=1) & np.isfinite(w) & (w > 0.0)
    if not ok.any():
        return None
    angle = 2.0 * np.arctan2(e[ok, 3], e[ok, 0])  # q and −q give angles 2π apart: same sin/cos
    return math.atan2(float(np.sum(w[ok] * np.sin(angle))), float(np.sum(w[ok] * np.cos(angle))))


def align_heading(
    q_forward: np.ndarray, q_backward: np.ndarray, weight: np.ndarray
) -> tuple[np.ndarray, float | None]:
    """The backward pass turned about the vertical onto the forward pass's heading reference.

    Returns (q_backward aligned, the offset in rad or None when it could not be estimated and
    nothing was changed). ``weight`` (N,) says where the offset is measured (both converged).
    """
    delta = heading_offset(q_forward, q_backward, weight)
    if delta is None:
        return np.asarray(q_backward, dtype=np.float64), None
    turn = np.array([math.cos(delta / 2.0), 0.0, 0.0, math.sin(delta / 2.0)])
    return quat_mul_array(turn, q_backward), delta


def heading_observed(name: str, rows: np.ndarray) -> bool:
    """Whether estimator ``name`` observes heading over ``rows``: it can (a full form that
    uses the magnetometer) and some magnetometer row is usable."""
    cls = estimators.get(name)
    if not (cls.observes_heading and cls.uses_mag):
        return False
    return bool(vecs_are_usable(np.asarray(rows, dtype=np.float64)[:, K.MAG : K.MAG + 3]).any())


__all__ = [
    "DEFAULT_BLEND_TIME_S",
    "OfflineResult",
    "align_heading",
    "blend_time",
    "combine",
    "forward_share",
    "fuse",
    "heading_observed",
    "heading_offset",
    "pass_times",
    "reverse_rows",
    "smooth",
    "smooth_passes",
    "smooth_rows",
]
