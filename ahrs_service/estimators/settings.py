"""The ``[estimator]`` section of the configuration, and how far a parameter may be moved.

Which estimator runs, its parameters and preset, checked the same way wherever parameters come
from: the configuration file, ``replay --param``, ``evaluate --param``, a tuning search range
(:func:`check_estimator_params`). A parameter's range is :func:`param_bounds` around its
reference value; the MAVLink bridge gives the same function a narrower factor for PARAM_SET.
"""

from __future__ import annotations

from typing import Any

from ahrs_service import estimators
from ahrs_service.core.settings import ConfigError, Section, finite_table, number, short, string
# the ranges live beside the presets, which a preset file's values must keep too
from ahrs_service.estimators.presets import (  # noqa: F401 (CONFIG_RANGE_FACTOR, param_bounds: imported from here)
    CONFIG_RANGE_FACTOR,
    load_preset,
    param_bounds,
    range_violation,
    reference_params,
)


def estimator_name(key: str, v: Any) -> str:
    """One of :func:`ahrs_service.estimators.names`."""
    if v not in estimators.names():
        raise ConfigError(f"{key}: {v!r} is not one of {', '.join(estimators.names())}")
    return v


ESTIMATOR: Section = {
    "name": ("robust", estimator_name),
    "params": ({}, finite_table),
    # "" = the tuned defaults; "paper" = the source paper's values; else a preset file
    # (ahrs-service tune): its values sit under estimator.params, which override them
    "preset": ("", string),
    "mag_timeout_s": (0.5, number(0.01, 60.0)),
    "declination_deg": (0.0, number(-180.0, 180.0)),
}


def _reference_params(name: str) -> list[dict[str, Any]]:
    """The values a parameter's range is taken from: its defaults, and its paper values."""
    return reference_params(name)


def check_estimator_section(section: dict[str, Any]) -> None:
    """The checked ``[estimator]`` section's parameters and preset, together: the estimator
    accepts them and each is within its range. What runs is the preset with the table's own
    values over it (service, reload, live), so ``section["params"]`` becomes that."""
    try:
        references = _reference_params(section["name"])
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(f"estimator.params: {exc}") from None
    if section["preset"]:
        try:
            preset = load_preset(section["name"], section["preset"])
            estimators.create(section["name"], **preset)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ConfigError(f"estimator.preset: {exc}") from None
        except OSError as exc:  # a name too long for the file system, a folder not searchable …
            raise ConfigError(f"estimator.preset: {short(section['preset'])} cannot be read: "
                              f"{exc.strerror or exc}; accepted: 'paper' or a preset file") from None
        section["params"] = {**preset, **section["params"]}  # its values were checked against the references
    try:
        estimators.create(section["name"], **section["params"])
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(f"estimator.params: {exc}") from None
    check_param_ranges(section["params"], references)


def check_param_ranges(params: dict[str, Any], references: list[dict[str, Any]],
                       label: str = "estimator.params.{}") -> None:
    """Each numeric value within ``CONFIG_RANGE_FACTOR`` of its reference: the larger of its
    default and its paper value (a paper's 1e9 for "gate off"), never a preset's own value
    (``presets.range_violation``). A finite 1e300 passes the estimator's own checks and
    overflows inside it. ``label`` names a parameter in the error (``"--param {}"`` on the
    command line)."""
    for name, value in params.items():
        wrong = range_violation(name, value, references)
        if wrong is not None:
            raise ConfigError(f"{label.format(name)} = {wrong}")


def check_estimator_params(name: str, params: dict[str, Any], label: str = "--param {}") -> None:
    """The configuration file's check of ``estimator.params`` for parameters given elsewhere
    (``replay --param``, ``evaluate --param``): each a parameter of estimator ``name``, accepted
    by its ``Params`` and within the same ranges as in the file (:func:`check_param_ranges`).
    Raises :class:`ConfigError` naming the parameter with ``label``."""
    try:
        references = _reference_params(name)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(str(exc)) from None  # an unknown estimator: its own message names it
    try:  # its own checks first (finite, positive …), then the ranges, as for the file
        estimators.create(name, **params)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(str(exc)) from None  # Params' own message names the parameter
    check_param_ranges(params, references, label)
