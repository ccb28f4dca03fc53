"""Evaluation tooling: the BROAD metric, L2 index, group means, rank tests, peers and the command."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, studentized_range

from ahrs_service.core.quaternion import (
    quat_from_euler_array,
    quat_from_rotvec_array,
    quat_mul_array,
    quat_to_matrix_array,
)
from ahrs_service.evaluation import broad, command, metrics, peers, report, stats
from tests.analytic import static

RATE = 100.0
TRIAL = "02_undisturbed_slow_rotation_B"


def _random_attitudes(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _about(axis, deg: float) -> np.ndarray:
    return quat_from_rotvec_array(np.radians(deg) * np.asarray(axis, dtype=float))


# ------------------------------------------------------------------------------ the metric


def test_heading_only_error_is_heading():
    q_ref = _random_attitudes(50)
    q_est = quat_mul_array(_about([0, 0, 1], 5.0), q_ref)  # 5° about the vertical, in the earth frame
    total, heading, incl = (np.degrees(a) for a in metrics.error_angles(q_est, q_ref))
    np.testing.assert_allclose(heading, 5.0, atol=1e-6)
    np.testing.assert_allclose(incl, 0.0, atol=1e-5)
    np.testing.assert_allclose(total, 5.0, atol=1e-6)


def test_inclination_only_error_is_inclination():
    q_ref = _random_attitudes(50, seed=2)
    q_est = quat_mul_array(_about([1, 0, 0], -3.0), q_ref)
    total, heading, incl = (np.degrees(a) for a in metrics.error_angles(q_est, q_ref))
    np.testing.assert_allclose(incl, 3.0, atol=1e-6)
    np.testing.assert_allclose(heading, 0.0, atol=1e-5)
    np.testing.assert_allclose(total, 3.0, atol=1e-6)


def test_combined_error_splits_into_heading_and_inclination():
    a, b = 20.0, 7.0
    q_ref = _random_attitudes(20, seed=3)
    # heading a about z after inclination b about a horizontal axis
    q_err = quat_mul_array(_about([0, 0, 1], a), _about([0.6, 0.8, 0], b))
    q_est = quat_mul_array(q_err, q_ref)
    total, heading, incl = (np.degrees(x) for x in metrics.error_angles(q_est, q_ref))
    expected_total = 2 * np.degrees(np.arccos(np.cos(np.radians(a / 2)) * np.cos(np.radians(b / 2))))
    np.testing.assert_allclose(heading, a, atol=1e-6)
    np.testing.assert_allclose(incl, b, atol=1e-6)
    np.testing.assert_allclose(total, expected_total, atol=1e-6)


def test_error_ignores_quaternion_sign_and_gives_180_for_a_half_turn():
    q_ref = _random_attitudes(10, seed=4)
    q_est = -quat_mul_array(_about([0, 0, 1], 180.0), q_ref)
    total, heading, incl = (np.degrees(x) for x in metrics.error_angles(q_est, q_ref))
    np.testing.assert_allclose(total, 180.0, atol=1e-6)
    np.testing.assert_allclose(heading, 180.0, atol=1e-6)
    np.testing.assert_allclose(incl, 0.0, atol=1e-5)


def _enu_reference(q_ned: np.ndarray) -> np.ndarray:
    """ENU attitude of NED attitudes built independently, from rotation matrices."""
    p = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # NED components → ENU
    r_enu = p @ quat_to_matrix_array(q_ned)
    xyzw = Rotation.from_matrix(r_enu).as_quat()
    return np.column_stack([xyzw[:, 3], xyzw[:, :3]])


def test_score_turns_ned_estimates_into_enu():
    q_ned = _random_attitudes(40, seed=5)
    q_ref = _enu_reference(q_ned)
    perfect = metrics.score(q_ned, q_ref, rate_hz=RATE)
    assert perfect.total_rmse == pytest.approx(0.0, abs=1e-5)
    # 5° too far clockwise seen from above: yaw about NED's down axis is heading in ENU too
    yawed = metrics.score(quat_mul_array(_about([0, 0, 1], 5.0), q_ned), q_ref, rate_hz=RATE)
    assert yawed.heading_rmse == pytest.approx(5.0, abs=1e-6)
    assert yawed.total_rmse == pytest.approx(5.0, abs=1e-6)
    assert yawed.inclination_rmse == pytest.approx(0.0, abs=1e-5)
    # 4° about north (a roll error) is inclination only
    rolled = metrics.score(quat_mul_array(_about([1, 0, 0], 4.0), q_ned), q_ref, rate_hz=RATE)
    assert rolled.inclination_rmse == pytest.approx(4.0, abs=1e-6)
    assert rolled.heading_rmse == pytest.approx(0.0, abs=1e-5)
    # without the conversion the same perfect estimate would be scored ~180° off
    raw_total = np.degrees(metrics.error_angles(q_ned, q_ref)[0])
    assert np.median(raw_total) > 90.0


def test_rmse_over_movement_samples_skips_reference_gaps():
    q_ned = quat_from_euler_array(np.zeros((6, 3)))
    q_ref = _enu_reference(q_ned)
    q_ref[4] = np.nan  # cameras lost the marker
    errors = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    q_est = np.vstack([quat_mul_array(_about([0, 0, 1], e), q) for e, q in zip(errors, q_ned)])
    movement = np.array([True, True, True, False, True, True])
    s = metrics.score(q_est, q_ref, movement, rate_hz=RATE)
    kept = errors[[0, 1, 2, 5]]
    assert s.samples == 4
    assert s.heading_rmse == pytest.approx(math.sqrt(np.mean(kept**2)), abs=1e-6)
    assert s.total_rmse == pytest.approx(math.sqrt(np.mean(kept**2)), abs=1e-6)
    assert s.mean == pytest.approx(np.mean(kept), abs=1e-6)
    assert s.l2 == pytest.approx(math.sqrt(np.mean(kept)), abs=1e-6)


def test_without_heading_only_inclination_is_scored():
    q_ned = _random_attitudes(30, seed=6)
    q_est = quat_mul_array(_about([0, 0, 1], 30.0), quat_mul_array(_about([0, 1, 0], 2.0), q_ned))
    s = metrics.score(q_est, _enu_reference(q_ned), rate_hz=RATE, with_heading=False)
    assert s.total_rmse is None and s.heading_rmse is None
    assert s.inclination_rmse == pytest.approx(2.0, abs=1e-6)
    assert s.l2 == pytest.approx(math.sqrt(2.0), abs=1e-6)


def test_score_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="N, 4"):
        metrics.score(np.zeros((5, 4)), np.zeros((4, 4)), rate_hz=RATE)


def test_l2_index_is_eq_38():
    # constant |e| = 4 → √4
    assert metrics.l2_index(np.full(100, -4.0), 0.01) == pytest.approx(2.0)
    # uneven steps weight the samples by time: (1·0.75 + 9·0.25) / 1 = 3
    assert metrics.l2_index(np.array([1.0, 9.0]), np.array([0.75, 0.25])) == pytest.approx(math.sqrt(3.0))
    assert math.isnan(metrics.l2_index(np.array([np.nan]), 0.01))


def test_group_figure_is_mean_of_trial_rmses():
    per_trial = {"a": 1.0, "b": 2.0, "c": 6.0, "d": None}
    assert metrics.group_mean(per_trial, ["a", "c"]) == pytest.approx(3.5)
    assert metrics.group_mean(per_trial, ["a", "b", "c"]) == pytest.approx(3.0)
    assert metrics.group_mean(per_trial, ["a", "d"]) is None


# ------------------------------------------------------------------------------ statistics


def test_friedman_matches_hand_computation():
    trials = ["t1", "t2", "t3", "t4"]
    table = {"A": [1.0, 2.0, 3.0, 1.5], "B": [2.0, 1.0, 4.0, 2.5], "C": [3.0, 3.0, 5.0, 3.5]}
    # rank sums A 5, B 7, C 12: χ² = 12/(n k (k+1)) Σ R² − 3 n (k+1) = 0.25·218 − 48
    test = stats.rank_test(table, trials)
    assert test.statistic == pytest.approx(6.5)
    assert test.pvalue == pytest.approx(chi2.sf(6.5, 2))
    assert test.mean_ranks == pytest.approx([1.25, 1.75, 3.0])
    assert test.significant
    # Nemenyi A vs C: |ΔR̄| / √(k(k+1)/(6n)) · √2 is Studentised-range distributed
    q = 1.75 / math.sqrt(3 * 4 / (6 * 4)) * math.sqrt(2)
    p_ac = studentized_range.sf(q, 3, np.inf)
    nem = np.array(test.nemenyi)
    assert nem[0, 2] == pytest.approx(p_ac, rel=1e-3)
    np.testing.assert_allclose(nem, nem.T)
    np.testing.assert_allclose(np.diag(nem), 1.0)
    assert "| A | 1.25 |" in stats.friedman_markdown(test, "x")
    # A vs C differs at α = 0.05, A vs B does not: only the former is bold
    md = stats.nemenyi_markdown(test, "x")
    assert p_ac < 0.05 < nem[0, 1]
    assert f"| A | – | {nem[0, 1]:.3f} | **{p_ac:.3f}** |" in md


def test_nemenyi_finds_the_always_worst_estimator_and_critical_difference():
    rng = np.random.default_rng(7)
    n = 10
    base = rng.uniform(1, 5, n)
    table = {"good": list(base), "mid": list(base + 1 + rng.uniform(0, 0.1, n)), "bad": list(base + 3)}
    test = stats.rank_test(table, [f"t{i}" for i in range(n)])
    assert test.pvalue < 1e-3
    nem = np.array(test.nemenyi)
    assert nem[0, 2] < 0.05
    # Demšar 2006, table 5: q_0.05 = 2.343 for k = 3
    assert test.cd == pytest.approx(2.343 * math.sqrt(3 * 4 / (6 * n)), rel=1e-3)


def test_rank_test_drops_incomplete_trials_and_needs_three_columns():
    two = stats.rank_test({"A": [1.0, 2.0], "B": [2.0, 3.0]}, ["t1", "t2"])
    assert math.isnan(two.statistic) and "at least 3" in two.note
    table = {"A": [1.0, 2.0, None, 1.0], "B": [2.0, 3.0, 1.0, 2.0], "C": [3.0, 1.0, 2.0, 3.0]}
    test = stats.rank_test(table, ["t1", "t2", "t3", "t4"])
    assert test.trials == ["t1", "t2", "t4"]


# ------------------------------------------------------------------------------ peers and options


def test_field_dip_from_first_sample():
    _, _, acc, mag = static(0.3, -0.2, 1.0, n=5)
    # analytic field (20 north, 45 down) µT
    assert peers.field_dip_deg(acc, mag) == pytest.approx(math.degrees(math.atan2(45.0, 20.0)), abs=1e-9)


def test_peer_and_param_selection_errors_are_clear():
    assert peers.select("none") == []
    with pytest.raises(ValueError, match="unknown peer 'bogus'"):
        peers.select("bogus")
    assert report.parse_params(["madgwick.beta=0.05"], ["madgwick"]) == {"madgwick": {"beta": 0.05}}
    assert report.parse_params(["ahrs.madgwick.gain=0.2"], ["ahrs.madgwick"]) == {"ahrs.madgwick": {"gain": 0.2}}
    with pytest.raises(ValueError, match="name.key=value"):
        report.parse_params(["beta0.05"], ["madgwick"])
    with pytest.raises(ValueError, match="not among the selected"):
        report.parse_params(["vqf.tauAcc=3"], ["madgwick"])
    with pytest.raises(ValueError, match="unknown parameter"):
        report.make_columns(["madgwick"], [], {"madgwick": {"gamma": 1.0}})


@pytest.mark.parametrize("name", ["vqf", "imufusion"])
def test_fast_peers_come_out_in_ned(name, broad_dir):
    if not peers.PEERS[name].available():
        pytest.skip(f"{name} not installed")
    trial = broad.load_trial(broad_dir, TRIAL)
    q = peers.run(name, trial.gyr, trial.acc, trial.mag, rate_hz=trial.rate_hz)
    ok = metrics.score(q, trial.ref, trial.movement, rate_hz=trial.rate_hz)
    # read as ENU instead of NED, the same output would be far off: the frame matters
    wrong = metrics.score(quat_mul_array(peers.Q_NWU_TO_NED, q), trial.ref, trial.movement, rate_hz=trial.rate_hz)
    assert ok.total_rmse < 2.0  # measured: vqf 1.38°, imufusion 1.71°
    assert wrong.total_rmse > 45.0


# ------------------------------------------------------------------------------ data and command


def test_load_trial_and_groups(broad_dir):
    trial = broad.load_trial(broad_dir, TRIAL)
    n = len(trial)
    assert trial.gyr.shape == trial.acc.shape == trial.mag.shape == (n, 3)
    assert trial.ref.shape == (n, 4) and trial.movement.shape == (n,)
    assert trial.rate_hz == pytest.approx(285.714, abs=1e-3)
    assert "rotation" in trial.groups
    groups = broad.list_groups(broad_dir)
    assert len(groups["all_trials"]) == len(broad.list_trials(broad_dir))
    assert groups["attached_magnet"] == [
        "32_disturbed_attached_magnet_1cm",
        "34_disturbed_attached_magnet_3cm",
        "36_disturbed_attached_magnet_5cm",
    ]
    assert broad.list_trials(broad_dir, "magnet_?cm") == groups["attached_magnet"]


# ------------------------------------------------------------------------------ timing


def _rate_at(q_ref: np.ndarray, rate_hz: float, at: np.ndarray) -> np.ndarray:
    w = metrics.reference_rate(q_ref, rate_hz)
    t_ref = np.arange(len(w)) + 0.5
    return np.stack([np.interp(at, t_ref, w[:, j]) for j in range(3)], axis=1)


def test_reference_rate_of_a_constant_rotation():
    rate_hz, w = 200.0, np.array([0.3, -1.2, 2.0])  # rad/s, body frame
    q = quat_from_rotvec_array(np.outer(np.arange(400) / rate_hz, w))  # about a fixed axis: body = earth axis
    np.testing.assert_allclose(metrics.reference_rate(q, rate_hz), np.tile(w, (399, 1)), atol=1e-9)


@pytest.mark.parametrize("delay", [0.0, 0.6, 2.3, -1.4])
def test_imu_delay_recovers_a_known_delay(broad_dir, delay):
    """Gyro samples made from a real recording's reference motion, late by ``delay`` samples,
    with a bias and white noise: the delay comes back to within 1/30 sample."""
    trial = broad.load_trial(broad_dir, FAST)
    n = len(trial)
    rng = np.random.default_rng(7)
    gyr = _rate_at(trial.ref, trial.rate_hz, np.arange(n) - delay) + np.radians([0.5, -0.3, 0.2])
    gyr += rng.normal(scale=np.radians(0.5), size=gyr.shape)
    assert metrics.imu_delay(gyr, trial.ref, trial.rate_hz, trial.movement) == pytest.approx(delay, abs=1 / 30)


def test_imu_delay_needs_motion_and_samples():
    still = np.tile([1.0, 0.0, 0.0, 0.0], (500, 1))
    gyr = np.tile(np.radians([0.5, -0.3, 0.2]), (500, 1))  # bias only
    assert math.isnan(metrics.imu_delay(gyr, still, 100.0))
    q = quat_from_rotvec_array(np.outer(np.arange(50) / 100.0, [0.0, 0.0, 1.0]))
    assert math.isnan(metrics.imu_delay(np.tile([0.0, 0.0, 1.0], (50, 1)), q, 100.0))  # < 100 samples


def _evaluate(argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    command.add_subcommands(parser.add_subparsers(dest="command"))
    # in-process: the parallel runs are test_execution.py's
    extra = [] if "--workers" in argv or "--scheduler" in argv else ["--workers", "1"]
    args = parser.parse_args(["evaluate", *argv, *extra])
    return args.func(args)


def _floats(node):
    if isinstance(node, dict):
        for v in node.values():
            yield from _floats(v)
    elif isinstance(node, list):
        for v in node:
            yield from _floats(v)
    elif isinstance(node, float):
        yield node


FAST = "07_undisturbed_fast_rotation_B"


@pytest.fixture(scope="module")
def evaluated(broad_dir, tmp_path_factory):
    """One `evaluate` run on two BROAD trials (with the vqf peer when it is installed):
    (exit code, output folder, whether vqf ran)."""
    with_vqf = peers.PEERS["vqf"].available()
    out = tmp_path_factory.mktemp("evaluate") / "eval"
    code = _evaluate(
        ["--data", str(broad_dir), "--estimators", "madgwick", "--peers", "vqf" if with_vqf else "none",
         "--trials", "0[27]_undisturbed", "--out", str(out), "--param", "madgwick.beta=0.1", "--quiet"]
    )
    return code, out, with_vqf


def test_evaluate_command_end_to_end(evaluated):
    code, out, _ = evaluated
    fast = FAST
    assert code == 0
    md = (out / "results.md").read_text(encoding="utf-8")
    assert "doi:10.3390/data6070072" in md and "Laidig" in md
    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    assert results["trials"] == [TRIAL, fast]
    assert "doi:10.3390/data6070072" in results["citation"]
    assert all(math.isfinite(x) for x in _floats(results["per_trial"]))
    assert all(math.isfinite(x) for x in _floats(results["per_group"]))
    mad = results["per_trial"]["madgwick"]
    assert mad[TRIAL]["total_rmse"] < 2.0  # measured 1.64°
    assert mad[fast]["total_rmse"] < 6.0  # measured 5.01°
    assert mad[TRIAL]["inclination_rmse"] < mad[TRIAL]["total_rmse"]
    assert mad[TRIAL]["us_per_sample"] > 0
    # both are rotation trials, only the first is slow
    groups = results["per_group"]["madgwick"]
    assert groups["rotation"]["total"] == pytest.approx((mad[TRIAL]["total_rmse"] + mad[fast]["total_rmse"]) / 2)
    assert groups["slow"]["inclination"] == pytest.approx(mad[TRIAL]["inclination_rmse"])
    assert "translation" not in groups
    for trial in (TRIAL, fast):
        assert (out / f"error_{trial}.png").stat().st_size > 1000
    assert (out / "group_rotation.png").is_file()
    assert sorted(results["plots"]) == sorted(p.name for p in out.glob("*.png"))
    # the recordings' timing against their reference (measured 1.04 and 1.12 samples)
    assert set(results["imu_delay"]) == {TRIAL, fast}
    assert all(0.95 < d["samples"] < 1.2 for d in results["imu_delay"].values())
    assert "## Timing of the recordings" in md


def test_evaluate_command_runs_the_vqf_peer(evaluated):
    pytest.importorskip("vqf", reason="the vqf peer (the 'peers' extra) is not installed")
    code, out, with_vqf = evaluated
    assert code == 0 and with_vqf
    results = json.loads((out / "results.json").read_text(encoding="utf-8"))
    vqf = results["per_trial"]["vqf"]
    assert set(vqf) == {TRIAL, FAST}
    assert vqf[TRIAL]["total_rmse"] < 1.6  # measured 1.38°


def test_evaluate_command_reports_missing_data(tmp_path, capsys):
    code = _evaluate(["--data", str(tmp_path / "nowhere"), "--estimators", "madgwick", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_evaluate_command_rejects_unknown_estimator(broad_dir, tmp_path, capsys):
    code = _evaluate(["--data", str(broad_dir), "--estimators", "nope", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "unknown estimator 'nope'" in capsys.readouterr().err
