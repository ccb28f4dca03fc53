"""The gap targets on real flights: every estimator on the 8 DIDO quadrotor flights with
samples dropped (``ahrs_service/evaluation/gaps.py``, docs/gaps.md), scored against its own
gap-free run on the same rows. Skipped with the reason when ../shared/data/dido is absent.

Each test asserts one target for one estimator. The estimators that miss a target today are
marked ``xfail(strict=True)`` with the figure measured (benchmarks/README.md, "Sample gaps"):
the target stays asserted, and an estimator that comes to meet it fails the suite until its
mark is removed. ``benchmarks/gaps.py --dataset dido --quick`` prints the same figures.
"""

from __future__ import annotations

import math

import pytest

from ahrs_service import estimators
from ahrs_service.evaluation import dido, gaps

DIDO_DATA = dido.default_dir()
DIDO_REASON = dido.missing_reason(DIDO_DATA)
pytestmark = pytest.mark.skipif(DIDO_REASON is not None, reason=DIDO_REASON or "")

FINE_BURSTS, LONG_BURSTS = gaps.RATIO_TARGETS  # 20-100 ms and 20-400 ms bursts until 10 % are gone
OUTAGE = "outage:2s"
PATTERNS = (FINE_BURSTS, LONG_BURSTS, OUTAGE)

#: mean ratio over the flights measured with seed 0, where it misses the target
MISSES_FINE = {"complementary_reduced": 1.50, "complementary_full": 1.43, "kalman_roll_pitch": 1.66,
               "quaternion_kf": 1.60, "immersion_invariance": 1.56, "valenti": 1.47, "robust": 1.34}
MISSES_LONG = {"complementary_reduced": 2.20, "complementary_full": 2.18, "kalman_roll_pitch": 2.56,
               "quaternion_kf": 2.51, "mahony_direct": 1.90, "mahony_passive": 1.93,
               "immersion_invariance": 1.71, "valenti": 2.07, "robust": 1.98}
#: estimators that, after the 2 s outage, are not back within 2° of their gap-free estimate
#: within 5 s on every flight
MISSES_RECOVERY = set(estimators.names()) - {"triad", "quest"}
#: estimators with a flight at most 5° gap-free that scores above 10° with one of the patterns
MISSES_BOUNDED = {"complementary_reduced", "complementary_full", "kalman_roll_pitch", "quaternion_kf",
                  "immersion_invariance", "robust"}

_scores: dict[str, dict[tuple[str, str], gaps.GapSummary]] = {}


def summaries(estimator: str) -> dict[tuple[str, str], gaps.GapSummary]:
    """The estimator's summaries over the flights under PATTERNS (seed 0), computed once."""
    if estimator not in _scores:
        scores = []
        for name in dido.list_trials(DIDO_DATA):
            scores += gaps.score_patterns(dido.load_trial(DIDO_DATA, name), estimator, PATTERNS, seed=0)
        _scores[estimator] = gaps.summarize(scores)
    return _scores[estimator]


def known_miss(name: str, misses, what: str):
    if name not in misses:
        return name
    figure = f" (measured {misses[name]:.2f}x)" if isinstance(misses, dict) else ""
    return pytest.param(name, marks=pytest.mark.xfail(strict=True, reason=f"misses {what}{figure}"))


@pytest.mark.parametrize("name", [known_miss(n, MISSES_FINE, "1.25x with 20-100 ms bursts") for n in estimators.names()])
def test_mean_ratio_with_fifo_overflow_bursts(name):
    s = summaries(name)[(name, FINE_BURSTS)]
    assert s.recordings == 8
    assert s.mean_ratio <= gaps.RATIO_TARGETS[FINE_BURSTS]


@pytest.mark.parametrize("name", [known_miss(n, MISSES_LONG, "1.5x with 20-400 ms bursts") for n in estimators.names()])
def test_mean_ratio_with_long_bursts(name):
    assert summaries(name)[(name, LONG_BURSTS)].mean_ratio <= gaps.RATIO_TARGETS[LONG_BURSTS]


@pytest.mark.parametrize("name", [known_miss(n, MISSES_BOUNDED, "the 10 deg bound") for n in estimators.names()])
def test_no_accurate_flight_goes_above_ten_degrees(name):
    misses = {p: summaries(name)[(name, p)].bounded_misses for p in PATTERNS}
    assert not any(misses.values()), misses


@pytest.mark.parametrize("name", [known_miss(n, MISSES_RECOVERY, "the 5 s recovery") for n in estimators.names()])
def test_back_within_two_degrees_five_seconds_after_an_outage(name):
    recovery = summaries(name)[(name, OUTAGE)].recovery_s
    assert len(recovery) == 8
    assert all(v <= gaps.RECOVERY_TARGET_S for v in recovery.values()), recovery


def test_the_memoryless_estimators_are_untouched_by_gaps():
    """TRIAD and QUEST solve each sample alone: a gap changes none of the kept rows' estimates."""
    for name in ("triad", "quest"):
        for p in PATTERNS:
            assert math.isclose(summaries(name)[(name, p)].mean_ratio, 1.0, rel_tol=1e-9)
