"""Drop patterns (``ahrs_service/evaluation/gaps.py``): parsing, which rows a pattern drops, the
lengths of the gaps, the scoring of a gapped run against the gap-free one, and
``ahrs-service evaluate --drop-pattern`` end to end on one BROAD recording and one DIDO flight
(skipped with the reason when ../shared/data is absent).

Not here: the accuracy targets of the estimators across gaps (the issue's ratios, bounded error
and recovery time) — they are measured by ``benchmarks/gaps.py``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import pytest

from ahrs_service.cli import main as cli_main
from ahrs_service.core.quaternion import ned_to_enu_array, quat_from_rotvec_array
from ahrs_service.evaluation import broad, dido, gaps, metrics

RATE = 285.714  # BROAD's rate
BURST_PATTERNS = [p for p in gaps.STANDARD_PATTERNS if p.startswith("bursts")]


def uniform_times(seconds: float = 180.0, rate: float = RATE) -> np.ndarray:
    return np.arange(int(seconds * rate)) / rate


def jittered_times(seconds: float = 60.0, rate: float = 400.0, seed: int = 1) -> np.ndarray:
    """Host stamps like DIDO's: a 400 Hz clock plus up to ±1 ms of latency, still increasing."""
    t = np.arange(int(seconds * rate)) / rate
    return t + np.random.default_rng(seed).uniform(-1e-3, 1e-3, t.size) + 1.6e9


def runs(keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    first, end = gaps.dropped_runs(keep)
    return first, end - first


# ------------------------------------------------------------------------------ parse


@pytest.mark.parametrize(
    "text, kind, values",
    [
        ("bursts:20-100ms:10%", "bursts", (0.020, 0.100, 0.10, 0.0)),
        ("bursts:20-400ms:40%", "bursts", (0.020, 0.400, 0.40, 0.0)),
        (" bursts:2.5-2.5ms:0.5% ", "bursts", (0.0025, 0.0025, 0.005, 0.0)),
        ("outage:2s", "outage", (0.0, 0.0, 0.0, 2.0)),
        ("outage:0.25s", "outage", (0.0, 0.0, 0.0, 0.25)),
    ],
)
def test_parse_reads_the_two_kinds(text, kind, values):
    p = gaps.parse(text)
    assert p.kind == kind
    assert (p.burst_min_s, p.burst_max_s, p.fraction, p.outage_s) == pytest.approx(values)
    assert gaps.parse(p.label) == p  # the label reads back as the same pattern
    assert gaps.parse(p) is p


def test_standard_patterns_parse_and_label_themselves():
    assert [gaps.parse(p).label for p in gaps.STANDARD_PATTERNS] == list(gaps.STANDARD_PATTERNS)
    assert set(gaps.RATIO_TARGETS) <= set(gaps.STANDARD_PATTERNS)


@pytest.mark.parametrize(
    "text, says",
    [
        ("", "not understood"),
        ("bursts", "not understood"),
        ("burst:20-100ms:10%", "not understood"),
        ("bursts:20-100ms:10", "not understood"),
        ("bursts:20-100s:10%", "not understood"),
        ("bursts:-20-100ms:10%", "not understood"),
        ("bursts:20-100ms:10%,outage:2s", "not understood"),
        ("outage:2", "not understood"),
        ("outage:-2s", "not understood"),
        ("outage:2min", "not understood"),
        ("bursts:100-20ms:10%", "0 < LO <= HI"),
        ("bursts:0-20ms:10%", "0 < LO <= HI"),
        ("bursts:20-100ms:0%", "above 0 % and below 90 %"),
        ("bursts:20-100ms:90%", "above 0 % and below 90 %"),
        ("outage:0s", "more than 0 s"),
    ],
)
def test_parse_refuses_bad_patterns_naming_them(text, says):
    with pytest.raises(ValueError) as err:
        gaps.parse(text)
    message = str(err.value)
    assert says in message and repr(text.strip()) in message and "\n" not in message


def test_parse_list_splits_commas_expands_standard_and_drops_duplicates():
    labels = [p.label for p in gaps.parse_list(["bursts:20-100ms:10%, outage:2s", "outage:2s"])]
    assert labels == ["bursts:20-100ms:10%", "outage:2s"]
    assert [p.label for p in gaps.parse_list("standard")] == list(gaps.STANDARD_PATTERNS)
    assert [p.label for p in gaps.parse_list("outage:2s,standard")][0] == "outage:2s"
    assert len(gaps.parse_list("outage:2s,standard")) == len(gaps.STANDARD_PATTERNS)
    with pytest.raises(ValueError, match="no drop pattern"):
        gaps.parse_list(" , ")
    with pytest.raises(ValueError, match="'nope' not understood"):
        gaps.parse_list("outage:2s,nope")


# ------------------------------------------------------------------------------ kept_rows


@pytest.mark.parametrize("pattern", BURST_PATTERNS)
@pytest.mark.parametrize("make_times", [uniform_times, jittered_times], ids=["broad-like", "dido-like"])
def test_bursts_drop_the_share_in_bursts_of_the_lengths_asked(pattern, make_times):
    t = make_times()
    p = gaps.parse(pattern)
    period = (t[-1] - t[0]) / (t.size - 1)
    shortest, longest = max(1, round(p.burst_min_s / period)), round(p.burst_max_s / period)
    for seed in range(4):
        keep = gaps.kept_rows(t, p, seed=seed)
        dropped = int((~keep).sum())
        # the share, to within half a burst (the last burst is kept when that lands nearer)
        assert abs(dropped - p.fraction * t.size) <= longest / 2 + 1
        first, lengths = runs(keep)
        # every run of lost rows is one burst: whole samples between LO and HI
        assert lengths.min() >= shortest and lengths.max() <= longest
        assert lengths.sum() == dropped
        # the first second and the last row are always kept
        assert keep[t < t[0] + gaps.KEEP_AT_START_S].all() and keep[-1]
        # the bursts are spread over the recording, not packed at one end
        if first.size >= 10:
            assert np.ptp(first) > 0.5 * t.size


def test_bursts_are_deterministic_per_seed_and_differ_between_seeds():
    t = uniform_times(60.0)
    a = gaps.kept_rows(t, "bursts:20-100ms:10%", seed=7)
    assert np.array_equal(a, gaps.kept_rows(t, "bursts:20-100ms:10%", seed=7))
    assert not np.array_equal(a, gaps.kept_rows(t, "bursts:20-100ms:10%", seed=8))
    # the same seed on another pattern draws other places
    assert not np.array_equal(a, gaps.kept_rows(t, "bursts:20-400ms:10%", seed=7))


def test_bursts_that_do_not_fit_stop_short_of_the_share():
    # 3 s at 100 Hz: 199 droppable rows (the first second and the last row are kept)
    t = np.arange(300) / 100.0
    keep = gaps.kept_rows(t, "bursts:400-400ms:80%", seed=0)  # 40-row bursts, 240 rows asked
    first, lengths = runs(keep)
    assert set(lengths) == {40} and lengths.sum() <= 199 - (lengths.size - 1)
    assert keep[:100].all() and keep[-1]


def test_short_recordings_keep_every_row():
    assert gaps.kept_rows(np.arange(2) / RATE, "bursts:20-100ms:40%").all()
    assert gaps.kept_rows(np.arange(int(0.9 * RATE)) / RATE, "bursts:20-100ms:40%").all()
    assert gaps.kept_rows(np.arange(int(0.9 * RATE)) / RATE, "outage:2s").all()


@pytest.mark.parametrize("make_times", [uniform_times, jittered_times], ids=["broad-like", "dido-like"])
def test_outage_is_one_gap_of_its_length_in_the_middle_of_the_scored_rows(make_times):
    t = make_times()
    period = (t[-1] - t[0]) / (t.size - 1)
    for scored, middle in ((None, t[t.size // 2]), (np.arange(t.size) >= t.size // 2, t[t.size // 2 + t.size // 4])):
        keep = gaps.kept_rows(t, "outage:2s", seed=0, scored=scored)
        first, lengths = runs(keep)
        assert first.size == 1
        lost = t[first[0] : first[0] + lengths[0]]
        assert lost[-1] - lost[0] == pytest.approx(2.0, abs=2 * period)  # the rows of 2 s
        assert gaps.gap_lengths(t, keep) == pytest.approx([2.0 + period], abs=2 * period)
        assert (lost[0] + lost[-1]) / 2 == pytest.approx(middle, abs=2 * period)
        # the seed does not move an outage
        assert np.array_equal(keep, gaps.kept_rows(t, "outage:2s", seed=5, scored=scored))


def test_an_outage_longer_than_the_recording_is_cut_to_the_droppable_rows():
    t = np.arange(1000) / 100.0  # 10 s
    keep = gaps.kept_rows(t, "outage:60s")
    assert keep[:100].all() and not keep[100:-1].any() and keep[-1]


# ------------------------------------------------------------------------------ gap_lengths


def test_gap_lengths_are_the_steps_across_each_run_of_dropped_rows():
    t = np.arange(10) * 0.1
    keep = np.array([1, 1, 0, 0, 1, 1, 0, 1, 0, 0], bool)
    # rows 2–3: from row 1 to row 4; row 6: from 5 to 7; rows 8–9 run to the end: no step across
    assert gaps.gap_lengths(t, keep) == pytest.approx([0.3, 0.2])
    assert gaps.gap_lengths(t, np.ones(10, bool)).size == 0
    first, end = gaps.dropped_runs(keep)
    assert first.tolist() == [2, 6, 8] and end.tolist() == [4, 7, 10]


def test_gap_lengths_of_bursts_are_a_period_longer_than_the_bursts():
    t = uniform_times(60.0)
    keep = gaps.kept_rows(t, "bursts:20-100ms:10%", seed=2)
    _, lengths = runs(keep)
    assert gaps.gap_lengths(t, keep) == pytest.approx((lengths + 1) / RATE)


def test_gap_lengths_ignore_the_jitter_of_host_stamps():
    t = jittered_times(20.0)
    t[1000:1010] += 0.004  # a late run of stamps, no sample lost
    assert gaps.gap_lengths(t, np.ones(t.size, bool)).size == 0


# ------------------------------------------------------------------------------ scoring


@dataclass
class FakeTrial:
    """The fields ``gaps.compare`` reads from a BROAD trial (no timestamps: times from the rate)."""

    name: str
    ref: np.ndarray
    movement: np.ndarray
    rate_hz: float = 100.0
    mag: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.ref)


def tilted(n: int, degrees: float) -> np.ndarray:
    """(n, 4) NED attitudes rolled by ``degrees`` (an inclination error against level)."""
    return quat_from_rotvec_array(np.tile([math.radians(degrees), 0.0, 0.0], (n, 1)))


def fake_trial(n: int = 3000) -> FakeTrial:
    level = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    return FakeTrial("fake", ned_to_enu_array(level), np.arange(n) >= 200)


def test_compare_scores_both_runs_on_the_same_kept_rows():
    trial = fake_trial()
    keep = gaps.kept_rows(np.arange(3000) / 100.0, "bursts:20-100ms:10%", seed=1, scored=trial.movement)
    q_free = tilted(3000, 3.0)
    q_gapped = tilted(int(keep.sum()), 6.0)
    q_gapped[:50] = np.nan  # rows the gapped run leaves without an attitude
    s = gaps.compare(trial, q_free, q_gapped, keep, pattern="bursts:20-100ms:10%", with_heading=False,
                     estimator="x", seed=1)
    assert s.kind == "inclination" and s.gap_free.total_rmse is None
    assert s.rmse_gap_free == pytest.approx(3.0) and s.rmse_gapped == pytest.approx(6.0) and s.ratio == pytest.approx(2.0)
    scored = trial.movement & keep
    nan_rows = np.zeros(3000, bool)
    nan_rows[np.flatnonzero(keep)[:50]] = True
    assert s.unscored_rows == int((scored & nan_rows).sum())
    assert s.gap_free.samples == s.gapped.samples == int((scored & ~nan_rows).sum())
    assert s.dropped_fraction == pytest.approx(1.0 - keep.mean())
    assert s.gaps == runs(keep)[0].size and s.longest_gap_s == pytest.approx(gaps.gap_lengths(np.arange(3000) / 100.0, keep).max())
    assert s.recovery_s is None and s.recovered is None  # bursts: no recovery time
    d = s.as_dict()
    assert d["ratio"] == pytest.approx(2.0) and d["gapped"]["inclination_rmse"] == pytest.approx(6.0)
    json.dumps(d)  # plain values


def test_compare_measures_the_recovery_after_an_outage():
    trial = fake_trial()
    t = np.arange(3000) / 100.0
    keep = gaps.kept_rows(t, "outage:2s", scored=trial.movement)
    after = gaps.dropped_runs(keep)[1][0]  # the first row after the outage
    q_free = tilted(3000, 1.0)
    q_gapped = q_free[keep].copy()
    t_kept = t[keep]
    off = (t_kept >= t[after]) & (t_kept < t[after] + 1.5)
    q_gapped[off] = tilted(int(off.sum()), 11.0)  # 10° from the gap-free estimate for 1.5 s
    s = gaps.compare(trial, q_free, q_gapped, keep, pattern="outage:2s", with_heading=False)
    assert s.recovery_s == pytest.approx(1.5) and s.recovered
    assert s.observed_after_s == pytest.approx(t[-1] - t[after])
    assert s.max_divergence_deg == pytest.approx(10.0)
    # never back by the end: inf; never off: 0
    q_gapped[t_kept >= t[after]] = tilted(int((t_kept >= t[after]).sum()), 5.0)
    late = gaps.compare(trial, q_free, q_gapped, keep, pattern="outage:2s", with_heading=False)
    assert math.isinf(late.recovery_s) and late.recovered is False
    same = gaps.compare(trial, q_free, q_free[keep], keep, pattern="outage:2s", with_heading=False)
    assert same.recovery_s == 0.0 and same.ratio == pytest.approx(1.0)


def test_recovery_time_counts_nan_as_not_back():
    t = np.arange(10) * 0.5
    assert gaps.recovery_time(t, np.array([5, 5, 1, 1, 1, 1, 1, 1, 1, 1.0]), 2) == 0.0
    assert gaps.recovery_time(t, np.array([5, 5, 5, 3, 1, np.nan, 1, 1, 1, 1.0]), 2) == pytest.approx(2.0)
    assert math.isinf(gaps.recovery_time(t, np.array([1, 1, 1, 1, 1, 1, 1, 1, 1, 3.0]), 2))


def test_compare_refuses_estimates_that_do_not_fit_the_rows():
    trial = fake_trial(500)
    keep = np.ones(500, bool)
    keep[300:320] = False
    with pytest.raises(ValueError, match="do not fit"):
        gaps.compare(trial, tilted(500, 1.0), tilted(500, 1.0), keep, pattern="outage:2s", with_heading=False)


def _score(trial: str, estimator: str, pattern: str, free: float, gapped: float, recovery: float | None = None):
    return gaps.GapScore(trial, estimator, pattern, 0, "inclination", 0.1, 3, 0.1,
                         metrics.TrialScore(free), metrics.TrialScore(gapped), recovery_s=recovery)


def test_summaries_and_targets():
    scores = [
        _score("a", "good", "bursts:20-100ms:10%", 2.0, 2.2),
        _score("b", "good", "bursts:20-100ms:10%", 4.0, 4.4),
        _score("a", "bad", "bursts:20-100ms:10%", 2.0, 3.0),
        _score("b", "bad", "bursts:20-100ms:10%", 4.0, 12.0),
        _score("a", "good", "outage:2s", 2.0, 2.0, 0.5),
        _score("b", "good", "outage:2s", 4.0, 4.0, 4.9),
        _score("a", "bad", "outage:2s", 2.0, 2.0, math.inf),
        _score("b", "bad", "outage:2s", 4.0, 4.0, 1.0),
    ]
    summary = gaps.summarize(scores)
    good, bad = summary[("good", "bursts:20-100ms:10%")], summary[("bad", "bursts:20-100ms:10%")]
    assert good.mean_ratio == pytest.approx(1.1) and good.worst_gapped == pytest.approx(4.4) and good.worst_recording == "b"
    assert bad.mean_ratio == pytest.approx(2.25) and bad.worst_ratio == pytest.approx(3.0)
    assert bad.bounded_misses == ["b"] and good.bounded_misses == []
    assert summary[("good", "outage:2s")].worst_recovery_s == pytest.approx(4.9)
    checks = gaps.check_targets(summary)
    ratio = next(c for c in checks if "mean ratio" in c.name)
    assert not ratio.met and ratio.misses == ["bad 2.25x"]
    bounded = next(c for c in checks if "gap-free above" in c.name)
    assert not bounded.met and bounded.misses == ["bad at bursts:20-100ms:10% on b"]
    recovery = next(c for c in checks if "after outage" in c.name)
    assert not recovery.met and recovery.misses == ["bad on 1 of 2 (worst inf s)"]
    # a pattern that was not run has no check
    assert len(checks) == 3 and not any("20-400ms" in c.name for c in checks)


# ------------------------------------------------------------------------------ the command


def _evaluate(argv: list[str]) -> int:
    return cli_main(["evaluate", *argv, "--workers", "1", "--quiet"])


@pytest.mark.parametrize(
    "argv, says",
    [
        (["--drop-pattern", "bursts:100-20ms:10%"], "--drop-pattern: drop pattern 'bursts:100-20ms:10%': burst lengths"),
        (["--drop-pattern", "outage:2s,gaps"], "--drop-pattern: drop pattern 'gaps' not understood"),
        (["--drop-pattern", ","], "--drop-pattern: no drop pattern"),
        (["--drop-pattern", "outage:2s", "--drop-seed", "-1"], "--drop-seed -1: must be 0 or more"),
        (["--drop-seed", "3"], "--drop-seed 3: only with --drop-pattern"),
    ],
)
def test_bad_drop_options_are_one_line_naming_the_option(tmp_path, capsys, argv, says):
    rc = _evaluate(["--data", str(tmp_path / "nowhere"), "--estimators", "madgwick", "--out", str(tmp_path / "ev"), *argv])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in err, err
    assert err.startswith("ahrs-service evaluate: error: ") and says in err, err
    assert not (tmp_path / "ev").exists()


BROAD_TRIAL = "36_disturbed_attached_magnet_5cm"  # one of the shortest BROAD recordings


def test_evaluate_with_drop_patterns_on_broad(broad_dir, tmp_path):
    if not (broad_dir / f"{BROAD_TRIAL}.hdf5").is_file():
        pytest.skip(f"{BROAD_TRIAL} is not among the BROAD recordings at {broad_dir}")
    out = tmp_path / "ev"
    rc = _evaluate(["--data", str(broad_dir), "--estimators", "madgwick", "--trials", BROAD_TRIAL, "--out", str(out),
                    "--drop-pattern", "bursts:20-100ms:10%", "--drop-pattern", "outage:2s", "--drop-seed", "3"])
    assert rc == 0
    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    g = results["gaps"]
    assert g["patterns"] == ["bursts:20-100ms:10%", "outage:2s"] and g["seed"] == 3 and g["columns"] == ["madgwick"]
    trial = broad.load_trial(broad_dir, BROAD_TRIAL)
    for pattern in g["patterns"]:
        row = g["per_trial"][pattern]["madgwick"][BROAD_TRIAL]
        # the command's numbers are the library's (score_with_gaps, the same seed)
        lib = gaps.score_with_gaps(trial, "madgwick", pattern, seed=3)
        assert row["kind"] == lib.kind == "total"  # madgwick observes heading with the magnetometer
        for key in ("rmse_gap_free", "rmse_gapped", "ratio", "dropped_fraction", "gaps"):
            assert row[key] == pytest.approx(getattr(lib, key)), key
        assert row["ratio"] == pytest.approx(row["rmse_gapped"] / row["rmse_gap_free"])
        assert row["gap_free"]["samples"] == row["gapped"]["samples"] > 0.5 * trial.movement.sum()
        # the gap-free run is evaluate's own run, scored on the kept rows
        keep = gaps.kept_rows(gaps.sample_times(trial), pattern, seed=3, scored=trial.movement)
        assert row["rmse_gap_free"] == pytest.approx(
            metrics.score(gaps.run_gap_free(trial, "madgwick"), trial.ref, trial.movement & keep,
                          rate_hz=trial.rate_hz).total_rmse)
        summary = g["summary"][pattern]["madgwick"]
        assert summary["mean_ratio"] == pytest.approx(row["ratio"]) and summary["worst_trial"] == BROAD_TRIAL
    bursts = g["per_trial"]["bursts:20-100ms:10%"]["madgwick"][BROAD_TRIAL]
    assert bursts["dropped_fraction"] == pytest.approx(0.10, abs=0.002) and bursts["recovery_s"] is None
    outage = g["per_trial"]["outage:2s"]["madgwick"][BROAD_TRIAL]
    assert outage["gaps"] == 1 and outage["longest_gap_s"] == pytest.approx(2.0, abs=0.01)
    assert outage["recovered"] in (True, False) and outage["observed_after_s"] > 20.0
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "## Sample gaps (`--drop-pattern`, seed 3)" in md
    assert "### bursts:20-100ms:10% per trial" in md and "### outage:2s per trial" in md


DIDO_DATA = dido.default_dir()
DIDO_REASON = dido.missing_reason(DIDO_DATA)


@pytest.mark.skipif(DIDO_REASON is not None, reason=DIDO_REASON or "")
def test_evaluate_with_an_outage_on_a_dido_flight(tmp_path):
    flight = min(dido.list_trials(DIDO_DATA), key=lambda n: (DIDO_DATA / f"{n}.hdf5").stat().st_size)
    out = tmp_path / "ev"
    rc = _evaluate(["--dataset", "dido", "--data", str(DIDO_DATA), "--estimators", "madgwick", "--trials", flight,
                    "--out", str(out), "--drop-pattern", "outage:2s"])
    assert rc == 0
    g = json.loads((out / "results.json").read_text(encoding="utf-8"))["gaps"]
    row = g["per_trial"]["outage:2s"]["madgwick"][flight]
    assert g["seed"] == 0
    # no magnetometer: inclination only, for the scores and for the recovery
    assert row["kind"] == "inclination" and row["gapped"]["total_rmse"] is None
    f = dido.load_trial(DIDO_DATA, flight)
    lib = gaps.score_with_gaps(f, "madgwick", "outage:2s")
    assert row["rmse_gapped"] == pytest.approx(lib.rmse_gapped) and row["ratio"] == pytest.approx(lib.ratio)
    assert (row["recovery_s"] is None) == (not lib.recovered)  # inf is written as null, "recovered" says which
    # the outage lies in the middle of the scored part (after the first 10 %) and lasts 2 s of stamps
    keep = gaps.kept_rows(f.timestamps, "outage:2s", scored=f.movement)
    assert gaps.gap_lengths(f.timestamps, keep) == pytest.approx([2.0], abs=0.02)
    scored_t = f.timestamps[f.movement]
    lost_t = f.timestamps[~keep]
    assert (lost_t[0] + lost_t[-1]) / 2 == pytest.approx(scored_t[scored_t.size // 2], abs=0.01)
    assert row["gap_free"]["samples"] == int((f.movement & keep).sum())
