"""Calibration while the service runs (MAV_CMD_PREFLIGHT_CALIBRATION).

The service hands every *uncalibrated* sample of its source (sensor axes, before
``apply_calibration``) to :meth:`LiveCalibrator.add`, which only copies it into arrays
preallocated by :meth:`LiveCalibrator.start` — cheap enough for 1 kHz. When the collection
time is over (:attr:`LiveCalibrator.done`) the collected data is fitted with the calibration
in force, giving the fit and the updated calibration.

The fit (a least-squares ellipsoid or six-position solution, tens of milliseconds) must not
run on a real-time loop, so the service uses :meth:`LiveCalibrator.finish_async`: it hands
the collected arrays to a daemon thread named "live-calibration" and returns a
:class:`concurrent.futures.Future` at once; the loop keeps estimating with the old
calibration, checks ``future.done()`` and applies the result on its own thread, between two
samples::

    cal, fit = LiveCalibrator(), None
    text = cal.start("mag")                   # MAV_CMD_PREFLIGHT_CALIBRATION param2 = 1
    ...                                       # → COMMAND_ACK ACCEPTED, STATUSTEXT text
    for each raw sample:                      # before apply_calibration
        if cal.add(raw_sample):               # True once: the collection is done
            fit = cal.finish_async(pipeline.calibration)   # state "fitting"; returns at once
    about once a second:  STATUSTEXT cal.status_text()
    if fit is not None and fit.done():        # on the loop thread
        result = fit.result()                 # re-raises an exception of the fit
        if result.accepted:
            pipeline.calibration = result.apply_to(pipeline.calibration)
        STATUSTEXT result.text                # severity INFO if result.accepted else WARNING
        if result.accepted:
            save_calibration(config_path, pipeline.calibration)   # when persisting

:meth:`LiveCalibrator.finish` does the same fit synchronously and returns the result
(scripts, tests). Either way the calibrator gives its collection buffers to the fit and
drops them (the next :meth:`~LiveCalibrator.start` allocates new ones), so the fit works on
data nothing changes any more, without a copy on the loop thread.

Only one collection or fit runs at a time: :meth:`LiveCalibrator.start` refuses while a fit
started by :meth:`~LiveCalibrator.finish_async` is running. The object is not thread-safe
(use it from the thread that reads the source); the fit thread never touches it. The
mounting and the other sensors' terms of the calibration are kept; only the calibrated
sensor's terms are replaced — :meth:`LiveCalibrationResult.apply_to` puts them on the
calibration in force when the result arrives, which may have changed during the fit (a gyro
calibration, a reload).
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import threading
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from ahrs_service.calibration.accelerometer import AXIS_LABELS, fit_accelerometer
from ahrs_service.calibration.gyro import gyro_bias_at_rest
from ahrs_service.calibration.magnetometer import fit_magnetometer, sphere_coverage
from ahrs_service.core.calibration import SensorCalibration
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_VALID, ImuSample

__all__ = ["KINDS", "DEFAULT_DURATION_S", "FIT_THREAD_NAME", "LiveCalibrationResult", "LiveCalibrator"]

KINDS = ("gyro", "mag", "accel")
#: collection time per kind, s: 2 s still for the gyro; a minute of turning for the
#: magnetometer; six poses of ~5 s plus moves for the accelerometer
DEFAULT_DURATION_S = {"gyro": 2.0, "mag": 60.0, "accel": 90.0}
MAX_DURATION_S = 600.0
STATUSTEXT_LEN = 50  # MAVLink STATUSTEXT.text is 50 characters

_FITS: dict[str, Callable[..., Any]] = {"gyro": gyro_bias_at_rest, "mag": fit_magnetometer, "accel": fit_accelerometer}
#: the SensorCalibration fields each kind of calibration replaces
_TERMS = {"gyro": ("gyro_bias",), "mag": ("mag_hard_iron", "mag_soft_iron"), "accel": ("acc_bias", "acc_scale")}
#: name of the thread :meth:`LiveCalibrator.finish_async` fits on
FIT_THREAD_NAME = "live-calibration"


@dataclass(frozen=True)
class LiveCalibrationResult:
    """Outcome of :meth:`LiveCalibrator.finish`.

    kind: "gyro" | "mag" | "accel". accepted: whether ``calibration`` holds new terms.
    reason: "ok" or why refused. calibration: the updated calibration (the ``current`` one
    unchanged when refused). fit: the fitting function's result (GyroBiasResult,
    MagCalibrationResult or AccCalibrationResult), or None when there were no samples.
    samples: readings collected. text: one line of at most 50 characters for STATUSTEXT.
    """

    kind: str
    accepted: bool
    reason: str
    calibration: SensorCalibration
    fit: Any
    samples: int
    text: str

    def apply_to(self, calibration: SensorCalibration) -> SensorCalibration:
        """``calibration`` with the calibrated sensor's terms replaced by this result's, or
        ``calibration`` itself when refused. Use it on the calibration in force when the
        result is applied: after an asynchronous fit that may differ from the one the fit
        started with, and its other terms must be kept."""
        if not self.accepted:
            return calibration
        return dataclasses.replace(calibration, **{t: getattr(self.calibration, t) for t in _TERMS[self.kind]})


@dataclass(frozen=True)
class _Collected:
    """The samples of one finished collection, handed from the calibrator to the fit.

    t_ns: (n,) sample timestamps, ns. gyr: (n, 3) rad/s, acc: (n, 3) m/s², mag: (n, 3) µT
    (NaN rows where there was no valid reading); all sensor axes, uncalibrated. The arrays
    are views of buffers the calibrator has dropped: nothing writes to them any more.
    """

    kind: str
    options: dict[str, Any]
    t_ns: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t_ns.shape[0])


def _fit(data: _Collected, current: SensorCalibration) -> LiveCalibrationResult:
    """Fits one collection (see :meth:`LiveCalibrator.finish`); touches no calibrator state,
    so it may run on any thread."""
    kind, n, options = data.kind, data.n, data.options
    if n == 0:
        reason = "no valid magnetometer readings" if kind == "mag" else "no valid samples"
        return LiveCalibrationResult(kind, False, reason, current, None, 0, _short(f"{kind} cal refused: {reason}"))
    # the fit functions are looked up here, not in _FITS, so a test can replace them
    if kind == "gyro":
        mag = data.mag if np.isfinite(data.mag).any() else None
        fit = gyro_bias_at_rest(data.gyr, data.acc, mag, **options)
        accepted = bool(fit.at_rest)
        values = (fit.bias,)
        ok_text = f"gyro cal done: bias {np.linalg.norm(fit.bias):.4f} rad/s"
    elif kind == "mag":
        fit = fit_magnetometer(data.mag, **options)
        accepted = bool(fit.accepted)
        values = (fit.hard_iron, fit.soft_iron)
        ok_text = f"mag cal done: res {100 * fit.residual_rel:.1f}% cov {100 * fit.coverage:.0f}%"
    else:
        span_s = (data.t_ns[n - 1] - data.t_ns[0]) * 1e-9
        rate = (n - 1) / span_s if span_s > 0 else 1.0
        fit = fit_accelerometer(data.acc, data.gyr, sample_rate_hz=rate, **options)
        accepted = bool(fit.accepted)
        values = (fit.bias, fit.scale)
        ok_text = f"accel cal done: res {fit.residual_rms:.3f} m/s2"
    new = dataclasses.replace(current, **dict(zip(_TERMS[kind], values, strict=True))) if accepted else current
    text = ok_text if accepted else f"{kind} cal refused: {fit.reason}"
    return LiveCalibrationResult(kind, accepted, fit.reason, new, fit, n, _short(text))


def _short(text: str) -> str:
    return text if len(text) <= STATUSTEXT_LEN else text[: STATUSTEXT_LEN - 1] + "…"


class LiveCalibrator:
    """Collects raw samples for one calibration and fits it (see the module docstring).

    max_rate_hz: the highest sample rate the source can deliver; with ``duration_s`` it sizes
    the buffers (samples beyond them end the collection early rather than allocate).
    """

    def __init__(self, max_rate_hz: float = 1000.0) -> None:
        if not (math.isfinite(max_rate_hz) and max_rate_hz > 0):
            raise ValueError(f"max_rate_hz must be a positive number, got {max_rate_hz!r}")
        self.max_rate_hz = float(max_rate_hz)
        self.kind: str | None = None
        self.duration_s = 0.0
        self._options: dict[str, Any] = {}
        self._n = 0
        self._t0: int | None = None
        self._t_last = 0
        self._full = False
        self._poses: set[str] = set()
        self._empty_buffers()
        # the fit started by finish_async, while it runs (kind, future)
        self._fit: tuple[str, Future[LiveCalibrationResult]] | None = None

    def _empty_buffers(self) -> None:
        self._t_ns = np.zeros(0, dtype=np.int64)
        self._gyr = np.zeros((0, 3))
        self._acc = np.zeros((0, 3))
        self._mag = np.zeros((0, 3))

    # ------------------------------------------------------------------ control
    @property
    def state(self) -> str:
        """"idle" (nothing started), "collecting", "done" (waiting for :meth:`finish` or
        :meth:`finish_async`), or "fitting" (the fit of :meth:`finish_async` runs)."""
        if self.kind is None:
            return "fitting" if self.fitting else "idle"
        return "done" if self.done else "collecting"

    @property
    def active(self) -> bool:
        """True between :meth:`start` and :meth:`finish`/:meth:`finish_async`/:meth:`cancel`
        (collecting or done; not while fitting: :meth:`add` has nothing to do then)."""
        return self.kind is not None

    @property
    def fitting(self) -> bool:
        """True while the fit started by :meth:`finish_async` runs."""
        if self._fit is not None and self._fit[1].done():
            self._fit = None
        return self._fit is not None

    def start(self, kind: str, duration_s: float | None = None, **options: Any) -> str:
        """Begins collecting for ``kind`` ("gyro" | "mag" | "accel") during ``duration_s`` s of
        sample time (default :data:`DEFAULT_DURATION_S`); ``options`` go to the fit function
        (e.g. ``field_strength=49.8`` for "mag", ``max_gyro_std=0.03`` for "gyro").

        Returns the instruction for the operator (STATUSTEXT). Raises ValueError for an
        unknown kind, a bad duration or an unknown option, RuntimeError while another
        collection is running (call :meth:`cancel` first) or a fit started by
        :meth:`finish_async` has not ended.
        """
        if kind not in KINDS:
            raise ValueError(f"calibration kind must be one of {', '.join(KINDS)}, got {kind!r}")
        if self.kind is not None:
            raise RuntimeError(f"a {self.kind} calibration is already running")
        if self.fitting:
            assert self._fit is not None
            raise RuntimeError(f"the {self._fit[0]} calibration is still being fitted")
        d = DEFAULT_DURATION_S[kind] if duration_s is None else float(duration_s)
        if not (math.isfinite(d) and 0 < d <= MAX_DURATION_S):
            raise ValueError(f"duration_s must be within (0, {MAX_DURATION_S:g}] s, got {duration_s!r}")
        accepted = set(inspect.signature(_FITS[kind]).parameters) - {"gyr", "acc", "mag", "sample_rate_hz"}
        unknown = sorted(set(options) - accepted)
        if unknown:
            raise ValueError(f"unknown {kind} calibration option(s) {unknown}; accepted: {sorted(accepted)}")
        capacity = int(math.ceil(d * self.max_rate_hz * 1.1)) + 16  # 10 % margin for clock jitter
        self._t_ns = np.zeros(capacity, dtype=np.int64)
        self._gyr = np.zeros((capacity, 3))
        self._acc = np.zeros((capacity, 3))
        self._mag = np.full((capacity, 3), np.nan)
        self.kind, self.duration_s, self._options = kind, d, dict(options)
        self._n, self._t0, self._full = 0, None, False
        self._poses = set()
        return _short({
            "gyro": f"gyro cal: keep still for {d:g} s",
            "mag": f"mag cal: rotate through all axes for {d:g} s",
            "accel": f"accel cal: hold 6 faces still, {d:g} s",
        }[kind])

    def cancel(self) -> None:
        """Drops the collection (no result). A fit already handed to a thread by
        :meth:`finish_async` is not affected: its future still completes."""
        self.kind = None
        self._n = 0
        self._empty_buffers()

    # ------------------------------------------------------------------ per sample
    def add(self, sample: ImuSample) -> bool:
        """Stores one raw sample (sensor axes, uncalibrated). Returns :attr:`done`.

        Ignored when idle or done. "gyro"/"accel" keep samples whose gyro and accelerometer
        are valid (the magnetometer too when valid); "mag" keeps each new valid magnetometer
        reading once (sources repeat a held reading between magnetometer updates).
        """
        if self.kind is None or self._full:
            return self.kind is not None
        t = sample.t_ns
        if self._t0 is None:
            self._t0 = t
        elif t - self._t0 >= self.duration_s * 1e9:
            self._full = True
            return True
        self._t_last = t
        n = self._n
        flags = sample.flags
        mag = sample.mag
        if self.kind == "mag":
            if mag is None or not flags & MAG_VALID:
                return False
            if n and self._mag[n - 1, 0] == mag[0] and self._mag[n - 1, 1] == mag[1] and self._mag[n - 1, 2] == mag[2]:
                return False  # a held reading, not a new one
            self._mag[n] = mag
        else:
            if not (flags & GYR_VALID and flags & ACC_VALID):
                return False
            self._gyr[n] = sample.gyr
            self._acc[n] = sample.acc
            if mag is not None and flags & MAG_VALID:
                self._mag[n] = mag
        self._t_ns[n] = t
        self._n = n + 1
        if self._n == self._t_ns.shape[0]:
            self._full = True  # faster than max_rate_hz: stop rather than grow
        return self._full

    @property
    def done(self) -> bool:
        """True when the collection time is over (or the buffers are full)."""
        return self._full

    @property
    def samples(self) -> int:
        return self._n

    @property
    def progress(self) -> float:
        """Fraction 0…1 of the collection time elapsed (sample time)."""
        if self.kind is None or self._t0 is None:
            return 0.0
        if self._full:
            return 1.0
        return min(1.0, (self._t_last - self._t0) / (self.duration_s * 1e9))

    def status_text(self) -> str:
        """One line (≤ 50 characters) on the collection, for a periodic STATUSTEXT (~1 Hz).

        For "mag" it estimates the coverage so far (directions around the running mean); for
        "accel" it checks whether the last half second was a still pose and lists the poses
        seen. Costs O(samples collected) for "mag": call it about once a second, not per sample.
        """
        if self.kind is None:
            if self.fitting:
                assert self._fit is not None
                return f"{self._fit[0]} cal: fitting"
            return "calibration: idle"
        pct = f"{100 * self.progress:.0f}%"
        n = self._n
        if self.kind == "mag":
            cov = sphere_coverage(self._mag[:n] - self._mag[:n].mean(axis=0)) if n > 1 else 0.0
            return _short(f"mag cal {pct}: {100 * cov:.0f}% of directions")
        if self.kind == "accel":
            self._note_pose()
            seen = " ".join(lb for lb in AXIS_LABELS if lb in self._poses)
            return _short(f"accel cal {pct}: {len(self._poses)}/6 {seen}")
        return _short(f"gyro cal {pct}: keep still")

    def _note_pose(self) -> None:
        n = self._n
        if n < 10:
            return
        rate = (n - 1) / max(1e-9, (self._t_ns[n - 1] - self._t_ns[0]) * 1e-9)
        k = min(n, max(10, int(0.5 * rate)))
        acc = self._acc[n - k:n]
        if acc.std(axis=0).max() < 0.2 and self._gyr[n - k:n].std(axis=0).max() < 0.03:
            m = acc.mean(axis=0)
            u = m / np.linalg.norm(m)
            axis = int(np.argmax(np.abs(u)))
            if abs(u[axis]) > math.cos(math.radians(25.0)):
                self._poses.add(AXIS_LABELS[2 * axis + (0 if u[axis] > 0 else 1)])

    # ------------------------------------------------------------------ result
    def _take(self) -> _Collected:
        """Ends the collection and hands its data over: the calibrator is idle afterwards and
        drops its buffers (``start`` allocates new ones), so the returned views are never
        written again — a snapshot without copying megabytes on the loop thread."""
        if self.kind is None:
            raise RuntimeError("no calibration is running")
        n = self._n
        data = _Collected(self.kind, self._options, self._t_ns[:n], self._gyr[:n], self._acc[:n], self._mag[:n])
        self.kind, self._n, self._options, self._t0, self._full = None, 0, {}, None, False
        self._empty_buffers()
        return data

    def finish(self, current: SensorCalibration) -> LiveCalibrationResult:
        """Fits the collected data (also before :attr:`done`: with what there is) and returns
        the result; the calibrator is idle afterwards. ``current``: the calibration in force,
        whose mounting and other terms the new calibration keeps. RuntimeError when idle.
        Runs the fit on the calling thread (tens of milliseconds for "mag" and "accel").
        """
        return _fit(self._take(), current)

    def finish_async(self, current: SensorCalibration) -> Future[LiveCalibrationResult]:
        """Like :meth:`finish`, but fits on a new daemon thread named :data:`FIT_THREAD_NAME`
        and returns at once with a :class:`concurrent.futures.Future` of the result.

        The data is handed to the fit before this returns; until the fit ends the state is
        "fitting", :meth:`add` ignores samples and :meth:`start` raises RuntimeError. An
        exception in the fit is set on the future (``future.result()`` re-raises it) and the
        calibrator is idle again all the same. The thread is a daemon: a process that exits
        while it runs does not wait for it (the result is lost). RuntimeError when idle, or
        when the thread cannot be started (the collection is dropped then).
        """
        data = self._take()
        future: Future[LiveCalibrationResult] = Future()
        future.set_running_or_notify_cancel()  # no cancelling: the thread cannot be stopped

        def work() -> None:
            try:
                future.set_result(_fit(data, current))
            except BaseException as exc:  # noqa: BLE001 - every failure must complete the future
                future.set_exception(exc)

        # "fitting" before the thread can run: whoever the fit signals sees the state it is in
        self._fit = (data.kind, future)
        try:
            threading.Thread(target=work, name=FIT_THREAD_NAME, daemon=True).start()
        except BaseException:
            self._fit = None
            raise
        return future
