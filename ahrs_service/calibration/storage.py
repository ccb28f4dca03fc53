"""Storing a calibration in the service's TOML configuration file.

:func:`save_calibration` rewrites the ``[calibration]`` section and keeps every other section
and key, with the user's comments and layout: it goes through
:func:`ahrs_service.config_file.update_config_file` (tomlkit, in place), which keeps the
previous file beside it as ``<name>.bak``, writes nothing unless the new document passes the
same validation as the service's start (:func:`ahrs_service.config.validate`), and replaces
the old file atomically.

The mounting rotation is *not* written: it stays where the configuration keeps it (the
``[mounting]`` section, or a ``mounting``/``mounting_rpy_deg`` key already in
``[calibration]``, which is preserved). Only the five sensor terms are written —
gyro_bias, acc_bias, acc_scale, mag_hard_iron, mag_soft_iron.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ahrs_service.config_file import update_config_file
from ahrs_service.core.calibration import MOUNTING, SensorCalibration

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
        data["mounting_rpy_deg"] = [float(mounting.get(k, 0.0)) for k in MOUNTING]
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
    not valid TOML or the result would not load, leaving the file untouched. Comments, layout
    and every other key (the mounting included) stay as they were.
    """
    d = calibration.to_dict()
    return update_config_file(config_path, {"calibration": {k: d[k] for k in SENSOR_KEYS}}, backup=backup)
