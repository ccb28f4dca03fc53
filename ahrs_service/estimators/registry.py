"""The estimator registry: every estimator's name, and its class loaded on first use.

A leaf of the estimators package (it imports no estimator module at import time), so that
:mod:`.presets` can resolve a name without importing the package that imports it.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from ahrs_service.estimators.base import Estimator

# name -> (module, class). Order: first paper, second paper, third paper, then the project's own.
_REGISTRY: dict[str, tuple[str, str]] = {
    "complementary_reduced": ("complementary", "ComplementaryReduced"),
    "complementary_full": ("complementary", "ComplementaryFull"),
    "triad": ("triad", "Triad"),
    "quest": ("quest", "Quest"),
    "kalman_roll_pitch": ("kalman_roll_pitch", "KalmanRollPitch"),
    "quaternion_kf": ("quaternion_kf", "QuaternionKF"),
    "mahony_direct": ("mahony", "MahonyDirect"),
    "mahony_passive": ("mahony", "MahonyPassive"),
    "immersion_invariance": ("immersion_invariance", "ImmersionInvariance"),
    "ekf": ("ekf", "QuaternionEKF"),
    "madgwick": ("madgwick", "Madgwick"),
    "valenti": ("valenti", "Valenti"),
    "robust": ("robust", "RobustEstimator"),
}

_PACKAGE = __name__.rpartition(".")[0]


def names() -> list[str]:
    """Names of all estimators available, in the order of the source papers."""
    return list(_REGISTRY)


def module_of(name: str) -> str:
    """The module (of this package) that defines estimator ``name``; ValueError if unknown."""
    try:
        return _REGISTRY[name][0]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; available: {', '.join(names())}") from None


def get(name: str) -> type[Estimator]:
    """The estimator class registered under ``name`` (its module is imported on first use)."""
    try:
        module, cls = _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown estimator {name!r}; available: {', '.join(names())}") from None
    return getattr(importlib.import_module(f"{_PACKAGE}.{module}"), cls)
