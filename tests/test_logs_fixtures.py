"""Regression: the small logs in tests/fixtures/logs/ (made by tests/fixtures/make_fixtures.py)
still read, replay to exactly their recorded estimate, and score within the asserted bounds.

broad_02_slice.mcap holds 3 s of BROAD trial 02 — D. Laidig, M. Caruso, A. Cereatti, T. Seel,
"BROAD — A Benchmark for Robust Inertial Orientation Estimation", Data 6(7), 2021,
doi:10.3390/data6070072 (CC BY 4.0).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service.logs import schemas
from ahrs_service.logs.reader import read_log
from ahrs_service.replay import compare, replay

LOGS = Path(__file__).resolve().parent / "fixtures" / "logs"
ANALYTIC = LOGS / "analytic_madgwick.mcap"
BROAD = LOGS / "broad_02_slice.mcap"


@pytest.mark.parametrize("path", [ANALYTIC, BROAD], ids=lambda p: p.name)
def test_fixture_is_small_sound_and_schema_valid(path):
    assert path.stat().st_size < 300_000
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_summary().chunk_indexes
        for schema, channel, message in reader.iter_messages():
            assert schemas.validate(json.loads(message.data), json.loads(schema.data)) == [], channel.topic


def test_analytic_fixture_replays_exactly_with_its_live_change():
    log = read_log(ANALYTIC)
    assert log.estimator == "madgwick" and log.params == {"beta": 0.1}
    assert [(c["name"], c["new"]) for c in log.param_changes] == [("beta", 0.3)]
    q = replay(log)
    assert np.array_equal(q, log.attitudes)
    result = compare(log, q)
    # measured when the fixture was made: total 0.26°, heading 0.17°, inclination 0.21°
    assert result["vs_truth"]["total"] < 0.4 and result["vs_truth"]["inclination"] < 0.3
    # without the live change the replay departs from the recording from that sample on
    k = log.local_index(log.param_changes[0]["sample_index"])
    other = replay(log, follow_param_changes=False)
    assert np.array_equal(other[:k], log.attitudes[:k]) and not np.array_equal(other[k:], log.attitudes[k:])


def test_broad_fixture_replays_exactly_and_scores_within_bound():
    log = read_log(BROAD)
    assert log.estimator == "madgwick" and log.truth is not None and log.movement is not None
    meta = log.metadata
    assert meta["broad"]["citation"].startswith("D. Laidig")
    q = replay(log)
    assert np.array_equal(q, log.attitudes)
    result = compare(log, q)["vs_truth"]
    # measured when the fixture was made: total 2.38°, heading 2.30°, inclination 0.64°
    assert result["total"] < 3.0 and result["inclination"] < 1.0
