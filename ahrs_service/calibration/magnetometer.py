"""Magnetometer hard- and soft-iron calibration from readings in many orientations.

Model (sensor axes, µT): a reading is ``m = D·B + h + noise`` where B is the local Earth field
(constant norm F), D the soft-iron/scale/misalignment distortion and h the hard-iron offset.
The readings of a sensor turned through all orientations lie on the ellipsoid

    (m − h)ᵀ Q (m − h) = 1,

and the correction of :mod:`ahrs_service.core.calibration`, ``S·(m − h)``, has the
constant norm F when Sᵀ S = F² Q. Of all such S the fit returns the symmetric one,
S = F·Q^½ (it rotates the sensor axes least; a rotation between the magnetometer and the
other sensors is the mounting's business, not this fit's).

The fit is in two steps:

1. the algebraic ellipsoid-specific least-squares fit of Li & Griffiths (2004, "Least squares
   ellipsoid specific fitting", with the constraint 4J − I² = 1), on centred and scaled data
   for conditioning; it refuses data that determine no ellipsoid;
2. a refinement of h and the symmetric Q^½ minimising Σ (|Q^½ (m − h)| − 1)² — closer to the
   geometric error than the algebraic one, which is biased by noise.

The overall scale is not observable from the readings (a stronger field and a more sensitive
sensor look alike): F is either given (e.g. from the World Magnetic Model) or taken as the
geometric mean radius of the fitted ellipsoid, which makes det S = 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ahrs_service.calibration.least_squares import TRIU, levenberg_marquardt, sphere_residuals, symmetric_from

__all__ = ["MagCalibrationResult", "fit_magnetometer", "sphere_coverage", "COVERAGE_BANDS", "COVERAGE_SECTORS"]

#: equal-area direction bins of the coverage measure: bands of equal height in z (equal area
#: by Archimedes' hat-box theorem) times equal sectors in azimuth — 6 × 12 = 72 cells of
#: about 573 deg² each (a cone of ~13.5° half-angle).
COVERAGE_BANDS = 6
COVERAGE_SECTORS = 12


@dataclass(frozen=True)
class MagCalibrationResult:
    """Outcome of :func:`fit_magnetometer`.

    hard_iron: (3,) µT, sensor axes. soft_iron: (3, 3) symmetric correction S; the corrected
    field S·(m − h) has norm ``field_strength``. field_strength: F, µT. residual_rms: rms of
    |S(m − h)| − F over the samples used, µT; residual_rel = residual_rms / F. coverage:
    fraction of the equal-area direction cells (see :data:`COVERAGE_BANDS`) visited by the
    corrected unit vectors, 0…1. axis_ratio: longest/shortest radius of the fitted
    ellipsoid. samples: readings used. accepted: whether the result may be stored; reason:
    why not (or "ok"). hard_iron/soft_iron are NaN when no ellipsoid could be fitted.
    """

    hard_iron: np.ndarray
    soft_iron: np.ndarray
    field_strength: float
    residual_rms: float
    residual_rel: float
    coverage: float
    axis_ratio: float
    samples: int
    accepted: bool
    reason: str

    def summary(self) -> str:
        """Several human-readable lines (for the command line)."""
        h = np.array2string(self.hard_iron, precision=3, suppress_small=True)
        s = np.array2string(self.soft_iron, precision=5, suppress_small=True).replace("\n", "\n" + " " * 18)
        return (
            f"samples:          {self.samples}\n"
            f"hard iron (µT):   {h}\n"
            f"soft iron:        {s}\n"
            f"field strength:   {self.field_strength:.3f} µT\n"
            f"residual rms:     {self.residual_rms:.3f} µT ({100 * self.residual_rel:.2f} %)\n"
            f"coverage:         {100 * self.coverage:.0f} % of directions\n"
            f"axis ratio:       {self.axis_ratio:.3f}"
        )


def sphere_coverage(directions: np.ndarray) -> float:
    """Fraction (0…1) of the equal-area direction cells hit by at least one of ``directions``.

    directions: (N, 3) vectors (normalised here; zero rows are ignored). The cells are
    :data:`COVERAGE_BANDS` bands of equal z-height times :data:`COVERAGE_SECTORS` azimuth sectors.
    """
    d = np.asarray(directions, dtype=float)
    n = np.linalg.norm(d, axis=1)
    d = d[n > 0] / n[n > 0, None]
    if d.shape[0] == 0:
        return 0.0
    band = np.minimum(((d[:, 2] + 1.0) * 0.5 * COVERAGE_BANDS).astype(int), COVERAGE_BANDS - 1)
    az = np.arctan2(d[:, 1], d[:, 0]) + math.pi  # 0 … 2π
    sector = np.minimum((az / (2 * math.pi) * COVERAGE_SECTORS).astype(int), COVERAGE_SECTORS - 1)
    cells = np.unique(band * COVERAGE_SECTORS + sector)
    return cells.size / (COVERAGE_BANDS * COVERAGE_SECTORS)


def _li_griffiths(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centre (3,) and shape Q (3, 3) of the ellipsoid (x − c)ᵀQ(x − c) = 1 fitted to x (N, 3).

    Raises ValueError when the data determine no ellipsoid.
    """
    X, Y, Z = x[:, 0], x[:, 1], x[:, 2]
    # quadric a x² + b y² + c z² + 2f yz + 2g xz + 2h xy + 2p x + 2q y + 2r z + d = 0
    D = np.stack([X * X, Y * Y, Z * Z, 2 * Y * Z, 2 * X * Z, 2 * X * Y, 2 * X, 2 * Y, 2 * Z, np.ones_like(X)])
    S = D @ D.T
    S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
    if np.linalg.cond(S22) > 1e12:
        raise ValueError("the readings do not span three dimensions")
    k = 4.0  # ellipsoid-specific constraint kJ − I² = 1 (k = 4: any ellipsoid with axis ratio ≤ 2)
    C1 = np.zeros((6, 6))
    C1[:3, :3] = k / 2 - 1
    np.fill_diagonal(C1[:3, :3], -1.0)
    C1[3:, 3:] = -k * np.eye(3)
    S22_inv_S21 = np.linalg.solve(S22, S12.T)
    M = np.linalg.solve(C1, S11 - S12 @ S22_inv_S21)
    w, V = np.linalg.eig(M)
    w = np.real(w)
    best = int(np.argmax(w))
    if not w[best] > 0:
        raise ValueError("no ellipsoid fits the readings")
    v1 = np.real(V[:, best])
    v2 = -S22_inv_S21 @ v1
    a, b, c, f, g, h = v1
    A = np.array([[a, h, g], [h, b, f], [g, f, c]])
    u = v2[:3]
    d = v2[3]
    centre = -np.linalg.solve(A, u)
    scale = centre @ A @ centre - d
    if not (np.isfinite(scale) and abs(scale) > 0):
        raise ValueError("no ellipsoid fits the readings")
    Q = A / scale
    if np.linalg.eigvalsh(Q).min() <= 0:
        raise ValueError("the fitted quadric is not an ellipsoid")
    return centre, Q


def _sqrtm_sym(Q: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(0.5 * (Q + Q.T))
    R = (V * np.sqrt(w)) @ V.T
    return 0.5 * (R + R.T)  # exactly symmetric, not just to round-off


def _refine(x: np.ndarray, centre: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Minimises Σ (|T (x − c)| − 1)² over c (3,) and symmetric T, from the algebraic fit."""
    p0 = np.concatenate([centre, T[TRIU]])
    sol = levenberg_marquardt(sphere_residuals(x, 1.0), p0, max_iterations=500)
    T_fit = symmetric_from(sol.x[3:])
    if not np.all(np.isfinite(sol.x)) or np.linalg.eigvalsh(T_fit).min() <= 0:
        return centre, T  # keep the algebraic solution rather than an unphysical one
    return sol.x[:3], T_fit


def _refused(reason: str, samples: int, coverage: float) -> MagCalibrationResult:
    nan3 = np.full(3, np.nan)
    return MagCalibrationResult(nan3, np.full((3, 3), np.nan), math.nan, math.nan, math.nan,
                                coverage, math.nan, samples, False, reason)


def fit_magnetometer(
    mag: np.ndarray,
    *,
    field_strength: float | None = None,
    min_samples: int = 50,
    min_coverage: float = 0.5,
    max_residual_rel: float = 0.05,
    max_axis_ratio: float = 2.0,
    field_range: tuple[float, float] = (15.0, 100.0),
) -> MagCalibrationResult:
    """Fits hard iron and soft iron to raw magnetometer readings (sensor axes).

    mag: (N, 3) µT, uncalibrated, taken while the sensor is turned through as many
        orientations as possible, away from iron and currents. Rows with NaN are skipped.
    field_strength: the local field F in µT (e.g. :func:`..declination.field_at`); None
        takes the geometric mean radius of the fitted ellipsoid (det S = 1).
    min_samples: fewer usable rows are refused.
    min_coverage: refuse when the corrected directions visit less than this fraction of the
        72 equal-area cells (0.5 ≈ half the sphere; the readings of a rotation about one axis
        lie on one circle, which crosses at most about a third of the cells).
    max_residual_rel: refuse when the rms of |S(m − h)| − F exceeds this fraction of F
        (magnetic disturbances, a moving field, or a model that does not fit).
    max_axis_ratio: refuse ellipsoids more elongated than this (the constrained fit is only
        guaranteed up to 2; real soft iron is far milder).
    field_range: (lo, hi) µT; with ``field_strength`` None, a fitted F outside it is refused
        (the Earth's field is 22–67 µT: another value means wrong units or a disturbance).

    Never raises for bad *data* (the result says why it was refused); raises ValueError for
    a wrongly shaped array or bad parameters.
    """
    m = np.asarray(mag, dtype=float)
    if m.ndim != 2 or m.shape[1] != 3:
        raise ValueError(f"mag must be an (N, 3) array in µT, got shape {m.shape}")
    if field_strength is not None and not (math.isfinite(field_strength) and field_strength > 0):
        raise ValueError(f"field_strength must be a positive number of µT, got {field_strength!r}")
    m = m[np.all(np.isfinite(m), axis=1)]
    n = m.shape[0]
    if n < max(min_samples, 10):
        return _refused(f"too few magnetometer readings ({n} < {max(min_samples, 10)})", n, 0.0)

    # centre and scale for conditioning; the rms spread is the size of the data
    mu = m.mean(axis=0)
    spread = math.sqrt(float(np.mean(np.sum((m - mu) ** 2, axis=1))))
    if not spread > 0:
        return _refused("the readings do not change: turn the sensor through all orientations", n, 0.0)
    xn = (m - mu) / spread
    # a planar or linear cloud (rotation about one axis) determines no ellipsoid: measure the
    # coverage about the mean so the refusal names the real cause
    raw_coverage = sphere_coverage(xn)
    try:
        centre_n, Q_n = _li_griffiths(xn)
    except (ValueError, np.linalg.LinAlgError) as exc:
        if raw_coverage < min_coverage:
            return _refused(_coverage_reason(raw_coverage, min_coverage) + f" ({exc})", n, raw_coverage)
        return _refused(f"degenerate data: {exc}", n, raw_coverage)
    T_n = _sqrtm_sym(Q_n)
    # too few directions: refuse on the algebraic fit (refining a near-degenerate fit is slow
    # and would not change the verdict)
    if sphere_coverage((xn - centre_n) @ T_n) >= min_coverage:
        centre_n, T_n = _refine(xn, centre_n, T_n)
    hard_iron = mu + spread * centre_n
    T = T_n / spread  # |T (m − h)| ≈ 1
    radii = 1.0 / np.linalg.eigvalsh(T)
    axis_ratio = float(radii.max() / radii.min())
    F = float(field_strength) if field_strength is not None else float(np.prod(radii) ** (1.0 / 3.0))
    S = F * T
    corrected = (m - hard_iron) @ S.T
    norms = np.linalg.norm(corrected, axis=1)
    residual = float(np.sqrt(np.mean((norms - F) ** 2)))
    coverage = sphere_coverage(corrected)

    reason = "ok"
    if coverage < min_coverage:
        reason = _coverage_reason(coverage, min_coverage)
    elif residual / F > max_residual_rel:
        reason = (f"residual too high: rms {residual:.2f} µT = {100 * residual / F:.1f} % of the field "
                  f"(limit {100 * max_residual_rel:.1f} %): magnetic disturbance or motion near iron")
    elif axis_ratio > max_axis_ratio:
        reason = f"implausible soft iron: ellipsoid axis ratio {axis_ratio:.2f} > {max_axis_ratio:.2f}"
    elif field_strength is None and not field_range[0] <= F <= field_range[1]:
        reason = (f"fitted field strength {F:.1f} µT outside {field_range[0]:g}–{field_range[1]:g} µT: "
                  "check the units (µT) and for nearby magnets")
    return MagCalibrationResult(hard_iron, S, F, residual, residual / F, coverage, axis_ratio, n, reason == "ok", reason)


def _coverage_reason(coverage: float, min_coverage: float) -> str:
    return (f"poor coverage: the readings visit {100 * coverage:.0f} % of directions "
            f"(need {100 * min_coverage:.0f} %): rotate the sensor through all orientations, "
            "not about one axis only")
