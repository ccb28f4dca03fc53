"""Gyroscope bias from a recording at rest.

At rest the gyroscope reads its bias plus noise, so the bias is the mean reading — provided
the sensor really was still. Stillness is judged from the data: the gyro's spread, and the
accelerometer's norm and direction, which move whenever the sensor is turned or shaken.
(A perfectly steady rotation about the vertical is invisible to the accelerometer; pass the
magnetometer too and its direction is checked as well.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["GyroBiasResult", "gyro_bias_at_rest"]


@dataclass(frozen=True)
class GyroBiasResult:
    """Outcome of :func:`gyro_bias_at_rest`.

    bias: (3,) rad/s in sensor axes — the mean reading (NaN when no data). noise_std: (3,)
    rad/s per-axis standard deviation. acc_norm_std: m/s², std of |acc|. acc_direction_rms_deg:
    rms angle between the accelerometer's block means and their mean direction, degrees.
    mag_direction_rms_deg: the same for the magnetometer (NaN when not given). samples: rows
    used. at_rest: whether the data show no motion (the bias may be stored); reason: why not
    (or "ok").
    """

    bias: np.ndarray
    noise_std: np.ndarray
    acc_norm_std: float
    acc_direction_rms_deg: float
    mag_direction_rms_deg: float
    samples: int
    at_rest: bool
    reason: str

    @property
    def accepted(self) -> bool:
        return self.at_rest

    def summary(self) -> str:
        """Human-readable lines (for the command line)."""
        b = np.array2string(self.bias, precision=6, suppress_small=True)
        s = np.array2string(self.noise_std, precision=6, suppress_small=True)
        return (
            f"samples:          {self.samples}\n"
            f"bias (rad/s):     {b}\n"
            f"noise (rad/s):    {s} (std)\n"
            f"acc |f| std:      {self.acc_norm_std:.4f} m/s²\n"
            f"acc direction:    {self.acc_direction_rms_deg:.3f}° rms"
            + ("" if math.isnan(self.mag_direction_rms_deg) else f"\nmag direction:    {self.mag_direction_rms_deg:.3f}° rms")
        )


def _direction_rms_deg(v: np.ndarray, blocks: int = 10) -> float:
    """rms angle (deg) between the means of ``blocks`` consecutive blocks of v and their mean direction.

    Block means average the sensor noise away (which would otherwise dominate at high rates)
    while a tilt or a slow turn during the recording still moves them apart.
    """
    v = np.stack([b.mean(axis=0) for b in np.array_split(v, min(blocks, v.shape[0]))])
    n = np.linalg.norm(v, axis=1)
    keep = n > 0
    if not keep.any():
        return math.nan
    u = v[keep] / n[keep, None]
    mean = u.mean(axis=0)
    mean_norm = np.linalg.norm(mean)
    if mean_norm == 0:
        return 180.0
    cos = np.clip(u @ (mean / mean_norm), -1.0, 1.0)
    return math.degrees(math.sqrt(float(np.mean(np.arccos(cos) ** 2))))


def _array3(name: str, x: np.ndarray, unit: str) -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array in {unit}, got shape {a.shape}")
    return a


def gyro_bias_at_rest(
    gyr: np.ndarray,
    acc: np.ndarray,
    mag: np.ndarray | None = None,
    *,
    min_samples: int = 50,
    max_gyro_std: float = 0.02,
    max_acc_norm_std: float = 0.2,
    max_acc_direction_deg: float = 1.0,
    max_mag_direction_deg: float = 1.0,
) -> GyroBiasResult:
    """The gyro bias (mean reading) of a recording that must be at rest.

    gyr: (N, 3) rad/s, acc: (N, 3) m/s², mag: optional (N, 3) µT — uncalibrated, sensor axes,
    the same rows. Rows with a NaN in gyr or acc are skipped (mag NaN rows only for the mag
    check).
    Refused (``at_rest`` False) when fewer than ``min_samples`` rows, when any gyro axis has a
    standard deviation above ``max_gyro_std`` rad/s (0.02 rad/s ≈ 1.1°/s: above the noise of
    consumer MEMS gyros up to 1 kHz, e.g. L3G4200D 0.012 rad/s, far below hand motion), when
    |acc| varies by more than ``max_acc_norm_std`` m/s² (std; ADXL345 noise at 1 kHz ≈ 0.09),
    or when the mean accelerometer (magnetometer) direction of ten consecutive blocks wanders
    more than ``max_acc_direction_deg`` (``max_mag_direction_deg``) degrees rms from the
    overall mean — a slow tilt or turn during the recording.
    """
    g = _array3("gyr", gyr, "rad/s")
    a = _array3("acc", acc, "m/s²")
    if g.shape != a.shape:
        raise ValueError(f"gyr and acc must have the same shape, got {g.shape} and {a.shape}")
    m = None if mag is None else _array3("mag", mag, "µT")
    if m is not None and m.shape != g.shape:
        raise ValueError(f"mag must have the shape of gyr {g.shape}, got {m.shape}")
    keep = np.all(np.isfinite(g), axis=1) & np.all(np.isfinite(a), axis=1)
    g, a = g[keep], a[keep]
    n = g.shape[0]
    if n < max(min_samples, 2):
        nan3 = np.full(3, np.nan)
        return GyroBiasResult(nan3, nan3, math.nan, math.nan, math.nan, n, False,
                              f"too few samples at rest ({n} < {max(min_samples, 2)})")
    bias = g.mean(axis=0)
    std = g.std(axis=0, ddof=1)
    acc_norm_std = float(np.linalg.norm(a, axis=1).std(ddof=1))
    acc_dir = _direction_rms_deg(a)
    mag_dir = math.nan
    if m is not None:
        mm = m[keep]
        mm = mm[np.all(np.isfinite(mm), axis=1)]
        if mm.shape[0] >= 2:
            mag_dir = _direction_rms_deg(mm)

    reason = "ok"
    if std.max() > max_gyro_std:
        reason = f"moving: gyro std {std.max():.4f} rad/s > {max_gyro_std:g} rad/s"
    elif acc_norm_std > max_acc_norm_std:
        reason = f"moving: accelerometer |f| std {acc_norm_std:.3f} m/s² > {max_acc_norm_std:g} m/s²"
    elif acc_dir > max_acc_direction_deg:
        reason = f"moving: accelerometer direction wanders {acc_dir:.2f}° rms > {max_acc_direction_deg:g}°"
    elif not math.isnan(mag_dir) and mag_dir > max_mag_direction_deg:
        reason = f"moving: magnetometer direction wanders {mag_dir:.2f}° rms > {max_mag_direction_deg:g}°"
    return GyroBiasResult(bias, std, acc_norm_std, acc_dir, mag_dir, n, reason == "ok", reason)
