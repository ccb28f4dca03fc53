"""Storing a calibration in the service's TOML configuration file.

:func:`save_calibration` rewrites the ``[calibration]`` section and keeps every other section
and key. The file is re-rendered with :func:`ahrs_service.config.to_toml`, so comments and
formatting are not kept; the previous file is kept beside it as ``<name>.bak``. Nothing is
written unless the new document passes the same validation as the service's start
(:func:`ahrs_service.config.validate`), and the new file replaces the old one atomically.

The mounting rotation is *not* written: it stays where the configuration keeps it (the
``[mounting]`` section, or a ``mounting``/``mounting_rpy_deg`` key already in
``[calibration]``, which is preserved). Only the five sensor terms are written —
gyro_bias, acc_bias, acc_scale, mag_hard_iron, mag_soft_iron.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from ahrs_service import config as config_mod
from ahrs_service.drivers.calibration import SensorCalibration

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["SENSOR_KEYS", "calibration_from_config_dict", "calibration_section", "save_calibration"]

#: the calibration keys a fit produces (the mounting is configuration, not calibration)
SENSOR_KEYS = ("gyro_bias", "acc_bias", "acc_scale", "mag_hard_iron", "mag_soft_iron")
_MOUNTING_KEYS = ("mounting", "mounting_rpy_deg")


def calibration_from_config_dict(cfg: dict[str, Any]) -> SensorCalibration:
    """The calibration in force for a configuration dict (as loaded, or as recorded in a log).

    The ``[calibration]`` terms, with the mounting from ``[calibration]`` when it has one and
    otherwise from ``[mounting]`` (roll/pitch/yaw_deg) — the service's rule. Raises ValueError
    for bad values.
    """
    data = dict(cfg.get("calibration") or {})
    if not any(k in data for k in _MOUNTING_KEYS):
        mounting = cfg.get("mounting") or {}
        data["mounting_rpy_deg"] = [float(mounting.get(k, 0.0)) for k in ("roll_deg", "pitch_deg", "yaw_deg")]
    return SensorCalibration.from_dict(data)


def calibration_section(calibration: SensorCalibration, existing: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``[calibration]`` table: the sensor terms of ``calibration`` plus the mounting key(s)
    of ``existing`` (kept as they were)."""
    d = calibration.to_dict()
    section = {k: d[k] for k in SENSOR_KEYS}
    for k in _MOUNTING_KEYS:
        if existing and k in existing:
            section[k] = existing[k]
    return section


def save_calibration(config_path: str | os.PathLike, calibration: SensorCalibration, *, backup: bool = True) -> Path:
    """Writes ``calibration``'s sensor terms into the ``[calibration]`` section of a TOML file.

    config_path: the service's configuration file; created (with only this section) when it
    does not exist. backup: copy the old file to ``<config_path>.bak`` first. Returns the
    path written. Raises :class:`ahrs_service.config.ConfigError` when the existing file is
    not valid TOML or the result would not load, leaving the file untouched.
    """
    path = Path(config_path)
    existed = path.exists()
    data: dict[str, Any] = {}
    if existed:
        try:
            with path.open("rb") as f:
                data = tomllib.load(f)
        except tomllib.TOMLDecodeError as exc:
            raise config_mod.ConfigError(f"{path}: not valid TOML, not rewritten: {exc}") from None
    existing = data.get("calibration")
    if existing is not None and not isinstance(existing, dict):
        raise config_mod.ConfigError(f"{path}: [calibration] is not a table, not rewritten")
    data["calibration"] = calibration_section(calibration, existing)
    text = config_mod.to_toml(data)
    # the service must be able to start from what we write: check before touching the file
    config_mod.validate(tomllib.loads(text))
    if existed and backup:
        shutil.copy2(path, path.with_name(path.name + ".bak"))
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent if str(path.parent) else ".")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if existed:
            shutil.copymode(path, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path
