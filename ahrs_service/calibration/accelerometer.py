"""Six-position accelerometer calibration: bias and scale/misalignment from still poses.

Procedure: hold the IMU still for a few seconds in each of six orientations — each sensor
axis pointing straight up and straight down (the faces of a box with square corners) — and
move it between them. From the recording:

1. :func:`find_static_segments` finds the still stretches (gyro and accelerometer quiet);
2. each segment's mean specific force is labelled with the sensor axis it points along
   (±x, ±y, ±z, within ``max_tilt_deg``); all six labels must be present;
3. the six-position solution: A·(x_k − b) = g·u_k for every labelled segment k (u_k the unit
   vector of its label, specific force points *up*: +g along the upward axis) is linear in
   (A, A·b) and solved by least squares. A then holds the small rotation between the box and
   the sensor as well; only the symmetric factor of its polar decomposition is kept (same
   |A(x − b)|, no rotation of the accelerometer against the other sensors);
4. with at least nine segments whose directions determine it, the result is refined by least
   squares of |A(x_k − b)| − g over every still segment (tilted ones too), which drops the
   assumption that the six faces are exactly perpendicular.

The result follows :mod:`ahrs_service.core.calibration`: acc_corrected = A·(acc − b).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ahrs_service.calibration.least_squares import TRIU, levenberg_marquardt, sphere_residuals, symmetric_from

__all__ = ["AccCalibrationResult", "AXIS_LABELS", "G0", "find_static_segments", "fit_accelerometer"]

G0 = 9.80665  # standard gravity, m/s²
#: label of each ±axis orientation, index = 2·axis + (0 for +, 1 for −)
AXIS_LABELS = ("+x", "-x", "+y", "-y", "+z", "-z")


@dataclass(frozen=True)
class AccCalibrationResult:
    """Outcome of :func:`fit_accelerometer`.

    bias: (3,) m/s², sensor axes. scale: (3, 3) symmetric correction A. residual_rms: rms of
    |A(x_k − b)| − g over the still segments, m/s². segments: (K, 2) sample index ranges
    [start, stop) of the still segments; means: (K, 3) their mean raw specific force; labels:
    the ±axis label of each segment ("" when tilted). orientations: the distinct labels found.
    refined: whether step 4 (sphere least squares) was used. accepted / reason as elsewhere.
    """

    bias: np.ndarray
    scale: np.ndarray
    residual_rms: float
    segments: np.ndarray
    means: np.ndarray
    labels: list[str]
    orientations: list[str]
    refined: bool
    accepted: bool
    reason: str
    g: float = G0
    notes: list[str] = field(default_factory=list)

    def summary(self) -> str:
        """Human-readable lines (for the command line)."""
        b = np.array2string(self.bias, precision=4, suppress_small=True)
        a = np.array2string(self.scale, precision=5, suppress_small=True).replace("\n", "\n" + " " * 18)
        return (
            f"still segments:   {len(self.labels)} ({', '.join(lb or 'tilted' for lb in self.labels)})\n"
            f"orientations:     {len(self.orientations)} of 6 ({' '.join(self.orientations)})\n"
            f"bias (m/s²):      {b}\n"
            f"scale:            {a}\n"
            f"residual rms:     {self.residual_rms:.4f} m/s²"
            + (" (sphere refinement)" if self.refined else " (six-position solution)")
        )


def _moving_std(x: np.ndarray, window: int) -> np.ndarray:
    """Per-axis standard deviation over a centred window of ``window`` samples, (N, 3)."""
    n = x.shape[0]
    c1 = np.vstack([np.zeros((1, 3)), np.cumsum(x - x.mean(axis=0), axis=0)])
    c2 = np.vstack([np.zeros((1, 3)), np.cumsum((x - x.mean(axis=0)) ** 2, axis=0)])
    half = window // 2
    lo = np.clip(np.arange(n) - half, 0, n)
    hi = np.clip(np.arange(n) - half + window, 0, n)
    cnt = (hi - lo)[:, None].astype(float)
    mean = (c1[hi] - c1[lo]) / cnt
    var = (c2[hi] - c2[lo]) / cnt - mean**2
    return np.sqrt(np.maximum(var, 0.0))


def find_static_segments(
    acc: np.ndarray,
    gyr: np.ndarray | None = None,
    *,
    window: int = 50,
    min_length: int = 100,
    acc_std_max: float = 0.2,
    gyro_std_max: float = 0.03,
) -> np.ndarray:
    """Still stretches of a recording, as (K, 2) index ranges [start, stop).

    acc (N, 3) m/s², gyr (N, 3) rad/s or None. A sample is still when, over the ``window``
    samples centred on it, every accelerometer axis has a standard deviation below
    ``acc_std_max`` m/s² and every gyro axis below ``gyro_std_max`` rad/s (a standard
    deviation, so the gyro's unknown bias does not matter). Runs of at least ``min_length``
    still samples are returned. Rows with NaN are never still.
    """
    a = np.asarray(acc, dtype=float)
    finite = np.all(np.isfinite(a), axis=1)
    still = np.all(_moving_std(np.where(finite[:, None], a, 0.0), window) < acc_std_max, axis=1) & finite
    if gyr is not None:
        g = np.asarray(gyr, dtype=float)
        gfinite = np.all(np.isfinite(g), axis=1)
        still &= np.all(_moving_std(np.where(gfinite[:, None], g, 0.0), window) < gyro_std_max, axis=1) & gfinite
    # a NaN row contaminates its neighbours' windows through the zero fill: exclude them too
    bad = np.convolve((~finite).astype(float), np.ones(window), mode="same") > 0
    still &= ~bad
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    stops = np.flatnonzero(edges == -1)
    keep = stops - starts >= min_length
    return np.stack([starts[keep], stops[keep]], axis=1) if keep.any() else np.zeros((0, 2), dtype=int)


def _label(v: np.ndarray, max_tilt_deg: float) -> str:
    """The ±axis label of a specific-force direction, or "" when it is tilted more than max_tilt_deg."""
    u = v / np.linalg.norm(v)
    axis = int(np.argmax(np.abs(u)))
    if math.degrees(math.acos(min(1.0, abs(u[axis])))) > max_tilt_deg:
        return ""
    return AXIS_LABELS[2 * axis + (0 if u[axis] > 0 else 1)]


def _six_position(means: np.ndarray, labels: list[str], g: float) -> tuple[np.ndarray, np.ndarray]:
    """A (3, 3) symmetric and b (3,) from A·(x_k − b) = g·u_k over the labelled segments."""
    rows = [k for k, lb in enumerate(labels) if lb]
    X = np.hstack([means[rows], -np.ones((len(rows), 1))])
    U = np.zeros((len(rows), 3))
    for j, k in enumerate(rows):
        i = AXIS_LABELS.index(labels[k])
        U[j, i // 2] = g if i % 2 == 0 else -g
    # each row i of A (and c_i = (A b)_i) solves X · [A_i, c_i] = U[:, i]
    sol, *_ = np.linalg.lstsq(X, U, rcond=None)
    A_full = sol[:3].T
    c = sol[3]
    b = np.linalg.solve(A_full, c)
    # polar decomposition A = R·P: keep P (symmetric), the same |A y| without the box's rotation
    _, s, Vt = np.linalg.svd(A_full)
    P = Vt.T @ np.diag(s) @ Vt
    return 0.5 * (P + P.T), b  # exactly symmetric, not just to round-off


def _refine(means: np.ndarray, A: np.ndarray, b: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Sphere least squares over all segments; None when the data do not determine all 9 terms."""
    sol = levenberg_marquardt(sphere_residuals(means, g), np.concatenate([b, A[TRIU]]))
    sv = np.linalg.svd(sol.jacobian, compute_uv=False)
    if sv.min() < 1e-6 * sv.max():
        return None  # e.g. six perpendicular poses only: the off-diagonal terms are free
    A_fit = symmetric_from(sol.x[3:])
    if not np.all(np.isfinite(sol.x)) or np.linalg.eigvalsh(A_fit).min() <= 0:
        return None
    return A_fit, sol.x[:3]


def fit_accelerometer(
    acc: np.ndarray,
    gyr: np.ndarray | None = None,
    *,
    sample_rate_hz: float = 100.0,
    g: float = G0,
    window_s: float = 0.5,
    min_still_s: float = 1.0,
    acc_std_max: float = 0.2,
    gyro_std_max: float = 0.03,
    max_tilt_deg: float = 25.0,
    max_residual: float = 0.1,
    max_scale_error: float = 0.2,
) -> AccCalibrationResult:
    """Six-position calibration of a recording (see the module docstring).

    acc: (N, 3) m/s² raw specific force, sensor axes; gyr: (N, 3) rad/s, same rows (or None:
    stillness from the accelerometer alone). sample_rate_hz: rate of the rows, to turn
    ``window_s`` (stillness window) and ``min_still_s`` (shortest still segment) into samples.
    g: local gravity, m/s². acc_std_max, gyro_std_max: stillness thresholds (see
    :func:`find_static_segments`). max_tilt_deg: a segment within this angle of a sensor axis
    counts as that ±axis orientation. Refused when fewer than six distinct orientations, when
    the rms residual exceeds ``max_residual`` m/s², or when a principal scale of A is off 1 by
    more than ``max_scale_error`` (wrong units or a failed segmentation).
    """
    a = np.asarray(acc, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"acc must be an (N, 3) array in m/s², got shape {a.shape}")
    if gyr is not None and np.shape(gyr) != a.shape:
        raise ValueError(f"gyr must have the shape of acc {a.shape}, got {np.shape(gyr)}")
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise ValueError(f"sample_rate_hz must be a positive number, got {sample_rate_hz!r}")
    if not (math.isfinite(g) and g > 0):
        raise ValueError(f"g must be a positive number of m/s², got {g!r}")
    window = max(3, int(round(window_s * sample_rate_hz)))
    min_length = max(window, int(round(min_still_s * sample_rate_hz)))
    segments = find_static_segments(a, gyr, window=window, min_length=min_length,
                                    acc_std_max=acc_std_max, gyro_std_max=gyro_std_max)
    means = np.array([a[s:e].mean(axis=0) for s, e in segments]).reshape(-1, 3)
    labels = [_label(m, max_tilt_deg) if np.linalg.norm(m) > 0 else "" for m in means]
    found = [lb for lb in AXIS_LABELS if lb in labels]
    nan3 = np.full(3, np.nan)

    def refuse(reason: str, A: np.ndarray = np.full((3, 3), np.nan), b: np.ndarray = nan3,
               residual: float = math.nan, refined: bool = False) -> AccCalibrationResult:
        return AccCalibrationResult(b, A, residual, segments, means, labels, found, refined, False, reason, g)

    if len(found) < 6:
        missing = [lb for lb in AXIS_LABELS if lb not in found]
        return refuse(f"only {len(found)} of 6 orientations held still (missing {' '.join(missing)}; "
                      f"{len(segments)} still segments of ≥ {min_still_s:g} s): hold each axis up and down in turn")
    A, b = _six_position(means, labels, g)
    refined = False
    if len(segments) >= 9:
        better = _refine(means, A, b, g)
        if better is not None:
            A, b = better
            refined = True
    residual = float(np.sqrt(np.mean((np.linalg.norm((means - b) @ A.T, axis=1) - g) ** 2)))
    scales = np.linalg.eigvalsh(A)
    if residual > max_residual:
        return refuse(f"residual too high: rms {residual:.3f} m/s² > {max_residual:g} m/s² "
                      "(moved during a pose, or poses on a slope)", A, b, residual, refined)
    if np.max(np.abs(scales - 1.0)) > max_scale_error:
        return refuse(f"implausible scale correction (principal scales {np.round(scales, 3).tolist()}): "
                      "check the units (m/s²)", A, b, residual, refined)
    return AccCalibrationResult(b, A, residual, segments, means, labels, found, refined, True, "ok", g)
