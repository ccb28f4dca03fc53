"""Is the estimate still consistent with the accelerometer? A divergence monitor for any estimator.

An attitude estimate predicts the direction of gravity in the body. The accelerometer measures
the specific force f (body FRD, m/s²), which is gravity's reaction plus the vehicle's own
acceleration: rotated into the *estimated* earth frame (NED, q_earth←body [w, x, y, z],
docs/design.md), a correct estimate gives R(q)·f = (0, 0, −g) + a, a the vehicle's
acceleration in the earth frame. Its mean over a window of T seconds is
(0, 0, −g) + Δv/T: a vehicle that does not keep speeding up in one direction averages its
acceleration out, while a tilt error δ of the estimate turns the whole mean δ away from the
vertical. That is the monitor's innovation, as an EKF's accelerometer or velocity innovation
is the autopilots' (ArduPilot EKF3's innovation test ratio, PX4 ekf2's innovation gates): a
measure of how far the measurements are from what the estimate predicts, against a gate that
grows with how much the measurements are expected to scatter.

Two tests, each a *test ratio* (above 1: fails):

* **tilt** — over ``window_s`` (3 s): the horizontal part of the mean, ``|m_h|`` (m/s²),
  against ``g·sin(gate_deg) + spread_factor · σ_h``, σ_h the spread (RMS about the mean, m/s²)
  of the horizontal specific force in the window. A hovering or resting vehicle scatters little,
  so a steady tilt error of a little more than ``gate_deg`` (6°) fails; a vehicle that accelerates
  hard (a quadrotor on a circle, a hand shaking the sensor) scatters a lot, and its window mean
  is allowed to wander further before the test fails. A 15° tilt error on a calm vehicle fails
  about 2 s after it appears, a 30° one after 1.7 s.
* **gross** — over ``gross_window_s`` (1 s): the angle of the mean from the vertical (deg)
  against ``gross_deg + gross_spread_deg · σ_n``, σ_n the RMS of ``|f| − g`` (m/s²), which does
  not depend on the estimate. It catches an estimate that is far off (tens of degrees, tumbling)
  within a fraction of a second, where the tilt test's own spread, inflated by the tumbling
  estimate, would wait.

The monitor **flags** (``diverged``) when either ratio exceeds 1, and **clears** when both have
stayed below ``clear_ratio`` for ``clear_s`` (2 s). A window with fewer than ``min_samples``
usable rows, or with fewer than ``min_coverage`` of its 50 ms cells holding one (the first
seconds, a gap, a missing accelerometer), decides nothing. The statistics are evaluated on a
grid of ``step_s`` (50 ms) of sample time, whatever size the blocks handed to
:meth:`DivergenceMonitor.update` have, so a replay of a log flags where the running service did.

The heading innovation — the direction of the window's mean horizontal field in the estimated
earth frame, against the estimate's (magnetic) north — is reported when a field is given, never
flagged: disturbed fields are common, and an estimator that rejects one is right to disagree with
it. Linear acceleration in one direction for longer than the window (a long, hard acceleration of
a car or a fixed-wing aircraft) would look like a tilt error: the monitor is for vehicles that
hover, move about or are carried (docs/autopilot.md, "Divergence monitor", gives the numbers on
BROAD and DIDO).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

from ahrs_service.core.quaternion import quat_rotate_array
from ahrs_service.core.settings import Section, boolean, number

#: standard gravity, m/s² (the monitor's g: the accelerometer's calibrated scale)
G = 9.80665


@dataclass(frozen=True)
class DivergenceSettings:
    """The monitor's thresholds (module docstring). Angles in degrees, times in seconds of sample
    time, specific force in m/s².

    window_s: the tilt test's window. gate_deg: the tilt error a vehicle that does not scatter
        fails at. spread_factor: how much of the horizontal spread σ_h the tilt gate adds.
    gross_window_s: the gross test's window. gross_deg: the angle of the mean that fails it
        with no magnitude spread; gross_spread_deg: degrees added per m/s² of the RMS of
        ``|f| − g``.
    clear_ratio, clear_s: both ratios below ``clear_ratio`` for ``clear_s`` clear the flag.
    min_samples: usable rows a window needs to decide anything; min_coverage: the share of
    its ``step_s`` cells that must hold one (a window that is mostly gap, or the first
    seconds, averages too short a time to tell acceleration from tilt). step_s: the
    evaluation grid.
    """

    window_s: float = 3.0
    gate_deg: float = 6.0
    spread_factor: float = 0.7
    gross_window_s: float = 1.0
    gross_deg: float = 35.0
    gross_spread_deg: float = 5.0
    clear_ratio: float = 0.5
    clear_s: float = 2.0
    min_samples: int = 10
    min_coverage: float = 0.5
    step_s: float = 0.05

    def __post_init__(self) -> None:
        if not (self.step_s > 0 and self.window_s >= self.step_s and self.gross_window_s >= self.step_s):
            raise ValueError("divergence windows must be at least one step_s > 0 long")
        if not (0 < self.gate_deg < 90 and 0 < self.gross_deg < 180 and 0 < self.clear_ratio <= 1):
            raise ValueError("divergence gates out of range")

    @classmethod
    def from_config(cls, section: dict) -> "DivergenceSettings":
        """The settings of a validated ``[divergence]`` section (:data:`DIVERGENCE`)."""
        return cls(window_s=section["window_s"], gate_deg=section["gate_deg"], clear_s=section["clear_s"])


#: the ``[divergence]`` section of the configuration (docs/configuration.md, docs/autopilot.md)
DIVERGENCE: Section = {
    "enabled": (True, boolean),
    "window_s": (DivergenceSettings.window_s, number(0.5, 30.0)),  # the tilt test's window, s
    "gate_deg": (DivergenceSettings.gate_deg, number(1.0, 45.0)),  # tilt error of a calm vehicle that flags, deg
    "clear_s": (DivergenceSettings.clear_s, number(0.0, 60.0)),  # consistent this long clears the flag, s
}


@dataclass(frozen=True)
class DivergenceVerdict:
    """The monitor's state after the grid step ending at ``t_s`` (sample time, s).

    diverged: the attitude is not to be trusted. test_ratio: the larger of the two tests'
    ratios (above 1 fails; NaN: too few samples to say). tilt_ratio, gross_ratio: each test's.
    tilt_innovation_deg: angle of the tilt window's mean specific force from the estimated
    vertical, deg. gross_innovation_deg: the same over the gross window. heading_innovation_deg:
    direction of the mean horizontal field in the estimated earth frame, east of the estimate's
    north, deg in (−180, 180] (NaN without a field). samples: usable rows in the tilt window.
    since_s: when the current state (diverged or consistent) began, s. flags: times it flagged
    since the start. diverged_s: time spent flagged, s.
    """

    t_s: float = math.nan
    diverged: bool = False
    test_ratio: float = math.nan
    tilt_ratio: float = math.nan
    gross_ratio: float = math.nan
    tilt_innovation_deg: float = math.nan
    gross_innovation_deg: float = math.nan
    heading_innovation_deg: float = math.nan
    samples: int = 0
    since_s: float = math.nan
    flags: int = 0
    diverged_s: float = 0.0

    def as_dict(self) -> dict:
        """The fields a log's ``/attitude`` diagnostics carry (JSON: NaN as None)."""
        def num(x: float) -> float | None:
            return None if not math.isfinite(x) else round(float(x), 4)

        return {
            "diverged": self.diverged,
            "innovation_test_ratio": num(self.test_ratio),
            "tilt_innovation_deg": num(self.tilt_innovation_deg),
            "heading_innovation_deg": num(self.heading_innovation_deg),
            "divergence_flags": self.flags,
        }


@dataclass(frozen=True)
class DivergenceEvent:
    """The flag set (``diverged``) or cleared at ``t_s`` (sample time, s), with the verdict then."""

    t_s: float
    diverged: bool
    verdict: DivergenceVerdict

    def text(self) -> str:
        """One line for the operator (STATUSTEXT, journal, /log)."""
        v = self.verdict
        if self.diverged:
            return (f"attitude diverged: tilt innovation {_deg(v.tilt_innovation_deg)} deg "
                    f"(1 s: {_deg(v.gross_innovation_deg)}), test ratio {v.test_ratio:.2f}")
        return f"attitude consistent again ({_deg(v.tilt_innovation_deg)} deg)"


def _deg(x: float) -> str:
    return "?" if not math.isfinite(x) else f"{x:.1f}"


# the sums kept per grid cell: count, Σf (3), Σf² (3), Σ(|f| − g)², field count, Σ field (3)
_N, _F, _F2, _DN2, _NM, _M = 0, slice(1, 4), slice(4, 7), 7, 8, slice(9, 12)
_WIDTH = 12


@dataclass
class DivergenceMonitor:
    """Runs the tests of the module docstring over blocks of estimated rows.

    Feed every row in time order with :meth:`update`; read :attr:`verdict`. Not thread-safe:
    one caller (the loop's sink, a replay).
    """

    settings: DivergenceSettings = field(default_factory=DivergenceSettings)
    verdict: DivergenceVerdict = field(default_factory=DivergenceVerdict)

    def __post_init__(self) -> None:
        s = self.settings
        self._cells: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        self._keep = max(int(math.ceil(s.window_s / s.step_s)), int(math.ceil(s.gross_window_s / s.step_s)))
        self._cell: int | None = None  # grid cell being filled
        self._acc = np.zeros(_WIDTH)  # its sums
        self._good_since: float | None = None
        self._state_since = math.nan
        self._flagged_at = math.nan

    # ------------------------------------------------------------------ rows in
    def update(self, t_s: np.ndarray, acc: np.ndarray, q: np.ndarray,
               mag: np.ndarray | None = None) -> list[DivergenceEvent]:
        """Adds rows: ``t_s`` (n,) sample times, s, increasing; ``acc`` (n, 3) specific force,
        body FRD, m/s²; ``q`` (n, 4) the estimate after each row, q_earth←body [w, x, y, z]
        (NED); ``mag`` (n, 3) µT body FRD, or None (an estimator without field). Rows with a
        non-finite accelerometer or quaternion are not used (the field's likewise). Returns the
        flag's changes at the grid steps these rows completed, oldest first."""
        t_s = np.asarray(t_s, dtype=np.float64)
        if t_s.size == 0:
            return []
        s = self.settings
        acc = np.asarray(acc, dtype=np.float64)
        q = np.asarray(q, dtype=np.float64)
        sums = np.zeros((t_s.size, _WIDTH))
        f = quat_rotate_array(q, acc)
        ok = np.isfinite(f).all(axis=1)
        f = np.where(ok[:, None], f, 0.0)
        dn = np.where(ok, np.linalg.norm(np.where(ok[:, None], acc, 0.0), axis=1) - G, 0.0)
        sums[:, _N] = ok
        sums[:, _F] = f
        sums[:, _F2] = f * f
        sums[:, _DN2] = dn * dn
        if mag is not None:
            b = quat_rotate_array(q, np.asarray(mag, dtype=np.float64))
            ok_m = np.isfinite(b).all(axis=1)
            sums[:, _NM] = ok_m
            sums[:, _M] = np.where(ok_m[:, None], b, 0.0)
        cells = np.floor(t_s / s.step_s).astype(np.int64)
        starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
        per_cell = np.add.reduceat(sums, starts, axis=0)
        events: list[DivergenceEvent] = []
        for cell, part in zip(cells[starts].tolist(), per_cell):
            if self._cell is None:
                self._cell = cell
            elif cell != self._cell:
                event = self._close_cell()
                if event is not None:
                    events.append(event)
                self._cell = cell
            self._acc += part
        return events

    def _close_cell(self) -> DivergenceEvent | None:
        """The cell being filled is complete: keep it, evaluate at its end."""
        s = self.settings
        cell = self._cell
        self._cells.append((cell, self._acc))
        self._acc = np.zeros(_WIDTH)
        while self._cells and self._cells[0][0] <= cell - self._keep:
            self._cells.popleft()
        return self._evaluate((cell + 1) * s.step_s, cell)

    def _window(self, last_cell: int, seconds: float) -> tuple[np.ndarray, bool]:
        """The sums over the window ending with ``last_cell``, and whether enough of it holds
        usable rows (``min_samples``, ``min_coverage``)."""
        s = self.settings
        cells = int(round(seconds / s.step_s))
        first = last_cell - cells + 1
        rows = [sums for c, sums in self._cells if c >= first and sums[_N] > 0]
        if not rows:
            return np.zeros(_WIDTH), False
        total = np.sum(rows, axis=0)
        return total, total[_N] >= s.min_samples and len(rows) >= s.min_coverage * cells

    # ------------------------------------------------------------------ the tests
    def _evaluate(self, t: float, last_cell: int) -> DivergenceEvent | None:
        s = self.settings
        tilt, tilt_ok = self._window(last_cell, s.window_s)
        gross, gross_ok = self._window(last_cell, s.gross_window_s)
        tilt_ratio = tilt_deg = gross_ratio = gross_deg = heading = math.nan
        n = int(tilt[_N])
        if tilt_ok:
            m = tilt[_F] / n
            var = tilt[_F2] / n - m * m
            m_h = math.hypot(m[0], m[1])
            spread = math.sqrt(max(var[0] + var[1], 0.0))
            tilt_ratio = m_h / (G * math.sin(math.radians(s.gate_deg)) + s.spread_factor * spread)
            tilt_deg = math.degrees(math.atan2(m_h, -m[2]))
            if tilt[_NM] >= s.min_samples:
                b = tilt[_M]
                heading = math.degrees(math.atan2(b[1], b[0])) if math.hypot(b[0], b[1]) > 0 else math.nan
        ng = int(gross[_N])
        if gross_ok:
            m = gross[_F] / ng
            gross_deg = math.degrees(math.atan2(math.hypot(m[0], m[1]), -m[2]))
            gross_ratio = gross_deg / (s.gross_deg + s.gross_spread_deg * math.sqrt(gross[_DN2] / ng))
        known = [r for r in (tilt_ratio, gross_ratio) if math.isfinite(r)]
        ratio = max(known) if known else math.nan
        v = self.verdict
        diverged, flags = v.diverged, v.flags
        diverged_s = v.diverged_s + (t - v.t_s if v.diverged and math.isfinite(v.t_s) else 0.0)
        if math.isnan(self._state_since):
            self._state_since = t - s.step_s
        event_kind: bool | None = None
        if not diverged:
            if known and ratio > 1.0:
                diverged, flags, event_kind = True, flags + 1, True
                self._state_since, self._good_since = t, None
        else:
            consistent = len(known) == 2 and ratio < s.clear_ratio
            if not consistent:
                self._good_since = None
            else:
                if self._good_since is None:
                    self._good_since = t
                if t - self._good_since >= s.clear_s:
                    diverged, event_kind = False, False
                    self._state_since, self._good_since = t, None
        self.verdict = DivergenceVerdict(
            t_s=t, diverged=diverged, test_ratio=ratio, tilt_ratio=tilt_ratio, gross_ratio=gross_ratio,
            tilt_innovation_deg=tilt_deg, gross_innovation_deg=gross_deg, heading_innovation_deg=heading,
            samples=n, since_s=self._state_since, flags=flags, diverged_s=diverged_s,
        )
        return None if event_kind is None else DivergenceEvent(t, event_kind, self.verdict)

    # ------------------------------------------------------------------ summaries
    def summary(self) -> str:
        """One line for the end of a run: "attitude: consistent throughout" or how often and how
        long it was flagged, and whether it still is."""
        v = self.verdict
        if v.flags == 0:
            return "attitude: consistent throughout"
        times = f"{v.flags} time{'s' if v.flags != 1 else ''}"
        now = "still diverged at the end" if v.diverged else "consistent at the end"
        return f"attitude: diverged {times} ({v.diverged_s:.1f} s in all), {now}"


def scan(t_s: np.ndarray, acc: np.ndarray, q: np.ndarray, mag: np.ndarray | None = None,
         settings: DivergenceSettings | None = None) -> tuple[DivergenceMonitor, list[DivergenceEvent]]:
    """The monitor run over a whole recording at once (a replay, an evaluation): the monitor
    at the end and every change of its flag."""
    monitor = DivergenceMonitor(settings or DivergenceSettings())
    return monitor, monitor.update(t_s, acc, q, mag)
