"""Sensor calibration and mounting: the one place where raw sensor axes become body FRD.

Every source delivers samples in the sensor's own axes, uncalibrated; the service passes
each through :func:`apply_calibration` before the estimator (and records both). The order is
fixed — first the calibration in sensor axes, then the mounting rotation:

    gyr_body = M · (gyr − b_g)
    acc_body = M · A · (acc − b_a)
    mag_body = M · S · (mag − h)

b_g gyro bias (rad/s), b_a accelerometer bias (m/s²), A accelerometer scale/misalignment
correction (3×3), h hard-iron offset (µT), S soft-iron correction (3×3), M the mounting: the
rotation from sensor axes to body FRD (v_body = M · v_sensor).

In the TOML config (section of the sensor), every key optional::

    gyro_bias = [0.01, -0.02, 0.0]        # rad/s
    acc_bias = [0.1, 0.0, -0.05]          # m/s²
    acc_scale = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    mag_hard_iron = [12.0, -3.0, 40.0]    # µT
    mag_soft_iron = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    mounting_rpy_deg = [180, 0, 90]       # or mounting = [[…], […], […]], not both

``mounting_rpy_deg`` are the ZYX Euler angles (roll, pitch, yaw in degrees) of the sensor
axes relative to the body: M = R_z(yaw) · R_y(pitch) · R_x(roll). A sensor mounted upside
down about the forward axis is [180, 0, 0].
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit

from ahrs_service.core.quaternion import quat_from_euler, quat_to_matrix_array
from ahrs_service.core.samples import ImuSample, SampleBlock
from ahrs_service.core.settings import ConfigError, Section, number

__all__ = ["CALIBRATION", "CALIBRATION_LIMITS", "MOUNTING", "SensorCalibration", "apply_calibration",
           "apply_calibration_block", "check_calibration_section", "mounting_from_rpy_deg"]


def mounting_from_rpy_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Mounting matrix M (sensor axes → body FRD) of ZYX Euler angles in degrees."""
    q = np.array(quat_from_euler(math.radians(roll), math.radians(pitch), math.radians(yaw)))
    m = quat_to_matrix_array(q)
    # snap round-off of quarter turns to exact 0/±1 so configured 90° mountings are exact
    m[np.abs(m) < 1e-15] = 0.0
    return m


@dataclass(frozen=True, eq=False)
class SensorCalibration:
    """Calibration of one IMU and its mounting (see the module docstring for the formulas).

    gyro_bias: (3,) rad/s. acc_bias: (3,) m/s². acc_scale: (3, 3) correction A.
    mag_hard_iron: (3,) µT. mag_soft_iron: (3, 3) correction S. mounting: (3, 3) rotation
    M from sensor axes to body FRD. Arrays are stored read-only; build a new calibration
    (``dataclasses.replace``) to change one.
    """

    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc_scale: np.ndarray = field(default_factory=lambda: np.eye(3))
    mag_hard_iron: np.ndarray = field(default_factory=lambda: np.zeros(3))
    mag_soft_iron: np.ndarray = field(default_factory=lambda: np.eye(3))
    mounting: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        for name, shape in _SHAPES.items():
            try:
                a = np.array(getattr(self, name), dtype=float)
            except (TypeError, ValueError):
                a = np.full(1, np.nan)
            if a.shape != shape or not np.isfinite(a).all():
                raise ValueError(f"calibration key {name!r} must be finite numbers of shape {shape}, got {getattr(self, name)!r}")
            a.setflags(write=False)
            object.__setattr__(self, name, a)
        m = self.mounting
        if not np.allclose(m @ m.T, np.eye(3), atol=1e-6) or np.linalg.det(m) < 0:
            raise ValueError("calibration key 'mounting' must be a rotation matrix (orthonormal, det +1)")
        for name in ("acc_scale", "mag_soft_iron"):
            if abs(np.linalg.det(getattr(self, name))) < 1e-9:
                raise ValueError(f"calibration key {name!r} must be an invertible (3, 3) matrix")
        # the products applied per sample, computed once
        object.__setattr__(self, "_matrices", np.stack([m, m @ self.acc_scale, m @ self.mag_soft_iron]))
        object.__setattr__(self, "_offsets", np.stack([self.gyro_bias, self.acc_bias, self.mag_hard_iron]))
        object.__setattr__(self, "is_identity", all(
            np.array_equal(getattr(self, n), _DEFAULTS[n]) for n in _SHAPES
        ))

    @classmethod
    def from_dict(cls, d: dict[str, Any] | None) -> "SensorCalibration":
        """From a config mapping (TOML section); unknown keys or bad values raise ValueError naming the key."""
        d = dict(d or {})
        allowed = set(_SHAPES) | {"mounting_rpy_deg"}
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise ValueError(f"unknown calibration key(s) {unknown}; allowed: {sorted(allowed)}")
        if "mounting" in d and "mounting_rpy_deg" in d:
            raise ValueError("calibration keys 'mounting' and 'mounting_rpy_deg' are exclusive: give one")
        if "mounting_rpy_deg" in d:
            rpy = d.pop("mounting_rpy_deg")
            try:
                r = np.array(rpy, dtype=float)
            except (TypeError, ValueError):
                r = np.array([np.nan])
            if r.shape != (3,) or not np.isfinite(r).all():
                raise ValueError(f"calibration key 'mounting_rpy_deg' must be [roll, pitch, yaw] in degrees, got {rpy!r}")
            d["mounting"] = mounting_from_rpy_deg(*r)
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        """Plain lists for the TOML config; ``from_dict(to_dict())`` gives the same calibration."""
        return {name: getattr(self, name).tolist() for name in _SHAPES}

    def with_gyro_bias_shift(self, residual_body: Any) -> "SensorCalibration":
        """A copy whose gyro bias also removes ``residual_body`` (rad/s, body FRD).

        A rate still seen at rest after calibration is in body axes; the bias lives in sensor
        axes, so the shift is Mᵀ·residual: M·(gyr − b_g − Mᵀ r) = M·(gyr − b_g) − r.
        """
        r = np.asarray(residual_body, dtype=float)
        if r.shape != (3,) or not np.isfinite(r).all():
            raise ValueError(f"residual_body must be 3 finite numbers (rad/s), got {residual_body!r}")
        return dataclasses.replace(self, gyro_bias=self.gyro_bias + self.mounting.T @ r)

    def with_mounting_rpy_deg(self, roll: float, pitch: float, yaw: float) -> "SensorCalibration":
        """A copy with the mounting from ZYX Euler angles in degrees."""
        return dataclasses.replace(self, mounting=mounting_from_rpy_deg(roll, pitch, yaw))


_SHAPES: dict[str, tuple[int, ...]] = {
    "gyro_bias": (3,),
    "acc_bias": (3,),
    "acc_scale": (3, 3),
    "mag_hard_iron": (3,),
    "mag_soft_iron": (3, 3),
    "mounting": (3, 3),
}
_DEFAULTS: dict[str, np.ndarray] = {
    "gyro_bias": np.zeros(3),
    "acc_bias": np.zeros(3),
    "acc_scale": np.eye(3),
    "mag_hard_iron": np.zeros(3),
    "mag_soft_iron": np.eye(3),
    "mounting": np.eye(3),
}


@njit(cache=True)
def _calibrate(mats, offs, gyr, acc, mag, has_mag, out):
    """out[r] = mats[r] · (x_r − offs[r]) for the rows gyr, acc and (if has_mag) mag."""
    for r in range(3 if has_mag else 2):
        x = gyr if r == 0 else (acc if r == 1 else mag)
        d0, d1, d2 = x[0] - offs[r, 0], x[1] - offs[r, 1], x[2] - offs[r, 2]
        for i in range(3):
            out[r, i] = mats[r, i, 0] * d0 + mats[r, i, 1] * d1 + mats[r, i, 2] * d2


_NO_MAG = np.zeros(3)


def _f64(x: np.ndarray) -> np.ndarray:
    # one compiled specialisation: float64 vectors (sources may hand lists or float32)
    return x if type(x) is np.ndarray and x.dtype == np.float64 else np.asarray(x, dtype=np.float64)


def apply_calibration(sample: ImuSample, cal: SensorCalibration) -> ImuSample:
    """The sample in body FRD, calibrated: calibration first, then the mounting rotation.

    gyr_body = M (gyr − b_g), acc_body = M A (acc − b_a), mag_body = M S (mag − h). Flags,
    ``raw``, ``truth_q``, timestamp and temperature are kept; ``mag`` None stays None. The
    input sample is not modified (an identity calibration returns it as it is). Runs once
    per sample at up to 1 kHz: the matrix products are precomputed and the three vectors
    come out of one compiled call into one new (3, 3) block.
    """
    if cal.is_identity:  # type: ignore[attr-defined]
        return sample  # nothing to do: no copy
    has_mag = sample.mag is not None
    out = np.empty((3, 3))
    _calibrate(
        cal._matrices,  # type: ignore[attr-defined]
        cal._offsets,  # type: ignore[attr-defined]
        _f64(sample.gyr),
        _f64(sample.acc),
        _f64(sample.mag) if has_mag else _NO_MAG,
        has_mag,
        out,
    )
    return ImuSample(
        t_ns=sample.t_ns,
        gyr=out[0],
        acc=out[1],
        mag=out[2] if has_mag else None,
        flags=sample.flags,
        raw=sample.raw,
        truth_q=sample.truth_q,
        temperature_c=sample.temperature_c,
    )


@njit(cache=True)
def _calibrate_rows(mats, offs, gyr, acc, mag, out):
    """Row k of a block through :func:`_calibrate` itself into ``out[:, k]`` ((3, n, 3): gyr,
    acc, mag), so a block and the same samples one by one give the same bits; NaN rows (no
    field) stay NaN."""
    for k in range(gyr.shape[0]):
        _calibrate(mats, offs, gyr[k], acc[k], mag[k], True, out[:, k])


def apply_calibration_block(block: SampleBlock, cal: SensorCalibration) -> SampleBlock:
    """A :class:`~ahrs_service.core.samples.SampleBlock` in body FRD, calibrated, in one
    compiled pass over its rows: the formulas of :func:`apply_calibration`, row by row with
    the same arithmetic. Times, flags, temperatures, ``raw``, ``truth_q`` and ``lost`` are
    kept (shared, not copied); rows without a field (NaN) stay NaN. The input is not
    modified; an identity calibration returns it as it is."""
    if cal.is_identity or not len(block):  # type: ignore[attr-defined]
        return block
    out = np.empty((3, len(block), 3))  # one allocation for the three readings
    _calibrate_rows(
        cal._matrices,  # type: ignore[attr-defined]
        cal._offsets,  # type: ignore[attr-defined]
        # contiguous float64 (a no-op for the usual block): one compiled specialisation
        np.ascontiguousarray(block.gyr, dtype=np.float64), np.ascontiguousarray(block.acc, dtype=np.float64),
        np.ascontiguousarray(block.mag, dtype=np.float64),
        out,
    )
    # the constructor, not dataclasses.replace: a tenth of the cost, once per block
    return SampleBlock(block.t_ns, out[0], out[1], out[2], block.flags, block.temperature_c, block.raw, block.truth_q,
                       block.lost)


#: the ``[mounting]`` section of the configuration: the sensor's mounting as ZYX Euler angles,
#: used when ``[calibration]`` gives no mounting of its own
MOUNTING: Section = {
    "roll_deg": (0.0, number(-180.0, 180.0)),
    "pitch_deg": (0.0, number(-180.0, 180.0)),
    "yaw_deg": (0.0, number(-180.0, 180.0)),
}

#: the ``[calibration]`` section: free-form, its keys are those of :meth:`SensorCalibration.from_dict`
#: and are checked together by :func:`check_calibration_section`
CALIBRATION: Section = {}

#: the largest magnitude of each [calibration] value that a real sensor's calibration can
#: have (the terms are offsets of a few units and near-identity matrices); beyond it a value is
#: a typo, and a finite but absurd one (1e300 rad/s of gyro bias) would overflow the estimate
CALIBRATION_LIMITS = {
    "gyro_bias": 10.0,  # rad/s (a gyro off by ~570 °/s is broken, not biased)
    "acc_bias": 50.0,  # m/s²
    "acc_scale": 10.0,  # each matrix element
    "mag_hard_iron": 5000.0,  # µT (the earth field is 25–65 µT; a nearby magnet may add hundreds)
    "mag_soft_iron": 100.0,  # each matrix element
    "mounting": 1.0,  # each element of a rotation matrix
    "mounting_rpy_deg": 360.0,  # each angle, degrees
}


def check_calibration_section(given: dict[str, Any]) -> dict[str, Any]:
    """The ``[calibration]`` table as read from TOML, checked: each value within
    :data:`CALIBRATION_LIMITS`, then the whole through :meth:`SensorCalibration.from_dict`.
    Returns a copy; raises :class:`ConfigError` naming the key."""
    for key, value in given.items():  # before from_dict: its matrix checks would overflow on 1e300
        limit = CALIBRATION_LIMITS.get(key)
        try:
            values = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            continue  # not numbers: from_dict names the key and the shape it wants
        if limit is not None and values.size and np.isfinite(values).all() and np.abs(values).max() > limit * (1 + 1e-9):
            raise ConfigError(f"calibration.{key}: {value!r} is out of range; accepted: each value within "
                              f"±{limit:g} (calibration key {key!r})")
    try:
        SensorCalibration.from_dict(given)
    except ValueError as exc:
        raise ConfigError(str(exc) if str(exc).startswith("calibration") else f"calibration: {exc}") from None
    return dict(given)
