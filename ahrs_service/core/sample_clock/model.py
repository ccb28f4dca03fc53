"""The model every clock of the package fits, and its one rounding rule.

A sensor samples on its own oscillator: sample ``k`` is taken at ``t_k = offset + k·period``
on the host's monotonic clock, the period off the nominal one by the oscillator's error and
drifting slowly with temperature. The fits differ only in what the host observes of that
line (``ahrs_service/sample_clock/__init__.py`` lists them); all of them count a gap in the
samples the same way, as a whole number of periods (:func:`whole_periods`).
"""

from __future__ import annotations

import math


def whole_periods(duration: float, period: float) -> int:
    """``duration`` in whole sample periods, rounded to the nearest (halves up): how far apart
    two samples of the line are in indices, or how many periods a run of stamps sits off it.
    Both in the same unit (ns or s)."""
    return math.floor(duration / period + 0.5)


__all__ = ["whole_periods"]
