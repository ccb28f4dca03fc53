"""Accuracy of the paper filters at their tuned defaults on the shared recordings (issue 16's
targets), and ``preset="paper"`` reproducing the papers' figures. Skipped without the data.

Scored by ``report.run_trial_job`` itself, the job ``ahrs-service evaluate`` and ``tune`` score
with (recorded stamps recovered onto the sensor clock for DIDO, BROAD at its rate; RMSE over
the scored samples):
BROAD on the total RMSE (inclination for the three filters without heading), DIDO on the
inclination RMSE. Targets: ≤ 6° mean total on the 12 BROAD trials (≤ 3° inclination for
those without heading), ≤ 5° mean inclination on the 8 DIDO flights.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_presets import PAPER_FILTERS

from ahrs_service.estimators.presets import load_preset
from ahrs_service.evaluation import report

NO_HEADING = {"complementary_reduced", "kalman_roll_pitch", "immersion_invariance"}


def _load(dataset, folder):
    """(data set, folder, recording names) of a data set; skips without its recordings."""
    source = report.DATASETS[dataset]
    reason = source.missing_reason(folder) if hasattr(source, "missing_reason") else None
    if reason or not folder.is_dir() or not any(folder.glob("*.hdf5")):
        pytest.skip(reason or f"no recordings in {folder}")
    return dataset, str(folder), source.list_trials(folder)


@pytest.fixture(scope="module")
def broad_recordings(broad_dir):
    return _load("broad", broad_dir)


@pytest.fixture(scope="module")
def dido_recordings():
    return _load("dido", report.DATASETS["dido"].default_dir())


_SCORES: dict = {}  # (estimator, data set, heading, preset) → mean: each run once per session


def mean_score(name: str, recordings, *, heading: bool, **preset) -> float:
    key = (name, recordings[0], heading, tuple(sorted(preset.items())))
    if key not in _SCORES:
        _SCORES[key] = _mean_score(name, recordings, heading=heading, **preset)
    return _SCORES[key]


def _mean_score(name: str, recordings, *, heading: bool, preset: str | None = None) -> float:
    dataset, folder, names = recordings
    col = report.make_columns([name], [], {name: load_preset(name, preset) if preset else {}})[0]
    metric = "total_rmse" if heading else "inclination_rmse"
    rows = [report.run_trial_job(report.TrialJob(folder, t, col, False, dataset)).row for t in names]
    return float(np.mean([row[metric] for row in rows]))


#: Filters whose tuned default does not reach BROAD's target (docs/tuning.md says why), with
#: the mean measured at the shipped preset on 2026-12-02: their target test is a strict xfail
#: (it fails the suite the day one meets it, so the mark is removed; only the target's
#: assertion is the expected failure, an error in the run is not), and a regression guard
#: holds them within 2 % of what was measured.
BROAD_TARGET_MISSED: dict[str, float] = {}  # none since 2026-12-03 (the roll/pitch filters' bias_rate)


def _broad_target(name: str) -> float:
    return 3.0 if name in NO_HEADING else 6.0


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    "name",
    [pytest.param(n, marks=pytest.mark.xfail(strict=True, raises=AssertionError, reason="BROAD target not met (docs/tuning.md)"))
     if n in BROAD_TARGET_MISSED else n for n in PAPER_FILTERS],
)
def test_tuned_default_meets_the_broad_target(name, broad_recordings):
    value = mean_score(name, broad_recordings, heading=name not in NO_HEADING)
    assert value <= _broad_target(name), f"{name}: {value:.2f}°"


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", sorted(BROAD_TARGET_MISSED))
def test_tuned_default_keeps_its_measured_broad_score(name, broad_recordings):
    value = mean_score(name, broad_recordings, heading=name not in NO_HEADING)
    assert value <= 1.02 * BROAD_TARGET_MISSED[name], f"{name}: {value:.2f}°"
    # and far better than the paper's values on the same trials (docs/accuracy.md: preset "paper")
    assert value < mean_score(name, broad_recordings, heading=name not in NO_HEADING, preset="paper")


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", PAPER_FILTERS)
def test_tuned_default_meets_the_dido_target(name, dido_recordings):
    value = mean_score(name, dido_recordings, heading=False)
    assert value <= 5.0, f"{name}: {value:.2f}°"


# The papers' values at the figures recorded before tuning (docs/accuracy.md, column "BROAD
# `paper`"; 2026-12-01, when they were the defaults): preset="paper" must give back exactly
# those filters.
PAPER_BROAD = {"mahony_direct": 39.81, "mahony_passive": 40.13, "quaternion_kf": 22.22, "madgwick": 5.86,
               "kalman_roll_pitch": 12.36, "immersion_invariance": 14.47}


@pytest.mark.timeout(300)
@pytest.mark.parametrize("name", sorted(PAPER_BROAD))
def test_paper_preset_reproduces_the_papers_figures_on_broad(name, broad_recordings):
    value = mean_score(name, broad_recordings, heading=name not in NO_HEADING, preset="paper")
    assert value == pytest.approx(PAPER_BROAD[name], abs=0.006)
