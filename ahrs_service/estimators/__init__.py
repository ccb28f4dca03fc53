"""Attitude estimators: every estimator of the source papers behind one API.

>>> from ahrs_service import estimators
>>> estimators.names()                                   # doctest: +SKIP
>>> q = estimators.run("madgwick", gyr, acc, mag, rate_hz=285.7, beta=0.1)  # doctest: +SKIP

``run`` returns an (N, 4) array of q_earth←body [w, x, y, z] (earth NED, body FRD), one row
per sample. Inputs are (N, 3) arrays in the sensor's own axes: gyroscope rad/s, specific
force m/s², magnetic field µT. For one sample at a time use ``create(name, **params)`` and
its ``update`` method: the same compiled step serves both paths.

``SAMPLE_ROW`` and ``STATE_HEADER`` name the columns of a sample row and the state slots
every estimator shares (``state[STATE_HEADER.slices.bias]``); see ``layout``.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from ahrs_service.estimators._cache import drop_stale_kernels

drop_stale_kernels()  # before any kernel is loaded from the cache

from ahrs_service.estimators._kernel import SAMPLE_ROW, STATE_HEADER  # noqa: E402
from ahrs_service.estimators.base import Estimator, stack_rows, time_steps  # noqa: E402
from ahrs_service.estimators.presets import load_preset  # noqa: E402
from ahrs_service.estimators.registry import get, names  # noqa: E402


def kernels_cached(name: str) -> bool:
    """Whether estimator ``name``'s compiled kernels are in numba's on-disk cache: False means
    its first use in a process compiles them (seconds for a paper filter, minutes for robust);
    True, that it loads them (tens of ms). ValueError for an unknown name."""
    from ahrs_service.estimators._cache import kernels_cached as in_cache
    from ahrs_service.estimators.registry import module_of

    return in_cache(module_of(name))


def create(name: str, preset: str | os.PathLike | None = None, **params: float) -> Estimator:
    """A fresh estimator instance; unknown parameter names raise ValueError.

    ``preset``: a preset file (``ahrs-service tune`` writes them, ``presets.load_preset``)
    whose parameters the instance starts from; ``params`` override it.
    """
    if preset is not None:
        params = {**load_preset(name, preset), **params}
    return get(name)(**params)


def run(
    name: str,
    gyr: Any,
    acc: Any,
    mag: Any = None,
    *,
    rate_hz: float | None = None,
    timestamps: Any = None,
    recover_clock: bool = True,
    preset: str | os.PathLike | None = None,
    **params: float,
) -> np.ndarray:
    """Runs estimator ``name`` over a recording and returns (N, 4) q_earth←body (NED).

    gyr rad/s, acc m/s² (specific force), mag µT or None, each (N, 3) in the sensor's axes.
    Time steps come from ``timestamps`` (s) when given, else from ``rate_hz``. Host stamps are
    first recovered onto the sensor's steady clock (``ahrs_service.core.sample_clock``, causal;
    uniform stamps pass unchanged); ``recover_clock=False`` integrates the raw steps instead.
    Stamps that cannot be seconds (NaN, not increasing, steps over a second) raise ValueError.
    ``preset`` and ``params`` as for :func:`create`.
    """
    est = create(name, preset, **params)
    n = np.shape(gyr)[0]
    return est.run(gyr, acc, mag, dt=time_steps(n, rate_hz, timestamps, recover_clock=recover_clock))


__all__ = ["SAMPLE_ROW", "STATE_HEADER", "Estimator", "create", "get", "kernels_cached", "names", "run", "stack_rows",
           "time_steps"]
