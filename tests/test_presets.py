"""Presets of the paper filters: search spaces inside each field's bounds, ``preset="paper"``
giving the source papers' values, the shipped tuned presets being the defaults, the
``estimator.preset`` configuration key, and Mahony's heading-only field term."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ahrs_service import config, estimators
from ahrs_service.estimators import presets
from ahrs_service.estimators.presets import SearchRange

#: Every recursive filter of the source papers (TRIAD and QUEST are single-shot, robust is the
#: project's own).
PAPER_FILTERS = [
    "complementary_reduced", "complementary_full", "kalman_roll_pitch", "quaternion_kf", "mahony_direct",
    "mahony_passive", "immersion_invariance", "ekf", "madgwick", "valenti",
]

#: The papers' values, written out from the papers (docs/estimators-paper*.md); where a paper
#: gives none (ω0, the EKF's Q and R) the value used before tuning, where it has no such
#: mechanism (acc_gate, acc_lowpass, mag_gate, Valenti's bias_alpha, the bias_rate of the QKF and
#: the roll/pitch filters) the value that turns it
#: off; Mahony's and the QKF's paper field term (mag_heading_only 0); the roll/pitch KF's
#: first-order step as eq. 31–32 print it (exact_step 0).
PAPER_VALUES = {
    "complementary_reduced": {"omega0": 0.2, "acc_gate": 1e9, "acc_lowpass": 0.0, "acc_soft": 0.0,
                              "bias_rate": 0.0, "rest_time": 0.0},
    "complementary_full": {"omega0": 0.2, "declination": 0.0, "acc_gate": 1e9, "acc_lowpass": 0.0, "acc_soft": 0.0,
                           "mag_gate": 1e9},
    "kalman_roll_pitch": {"sigma_zeta": 5.0, "sigma_xi": 3.0, "acc_gate": 1e9, "acc_lowpass": 0.0, "exact_step": 0.0,
                          "bias_rate": 0.0, "rest_time": 0.0},
    "quaternion_kf": {"sigma_zeta": 0.1, "sigma_xi": 0.1, "p0": 1.0, "w_acc": 2.0, "w_mag": 2.0, "acc_gate": 1e9,
                      "mag_heading_only": 0.0, "mag_gate": 1e9, "bias_rate": 0.0},
    "mahony_direct": {"kp": 25.0, "ki": 10.0, "w_acc": 1.0, "w_mag": 1.0, "mag_heading_only": 0.0,
                      "acc_gate": 1e9, "mag_gate": 1e9},
    "mahony_passive": {"kp": 25.0, "ki": 10.0, "w_acc": 1.0, "w_mag": 1.0, "mag_heading_only": 0.0,
                      "acc_gate": 1e9, "mag_gate": 1e9},
    "immersion_invariance": {"gamma1": 0.5, "gamma2": 0.7, "gamma3": 0.9, "xi_bar": -30.0, "mu_bar": 10.0,
                             "acc_gate": 1e9, "acc_lowpass": 0.0},
    "ekf": {"gyro_noise": 0.01, "bias_noise": 1e-5, "acc_noise": 0.2, "mag_noise": 0.3, "init_attitude_std": 0.01,
            "init_bias_std": 0.01, "mag_gate": 1e9},
    "madgwick": {"beta": 0.1},
    "valenti": {"alpha": 0.03, "beta": 0.3, "gain_rate_hz": 100.0, "adaptive_low": 0.1, "adaptive_high": 0.2,
                "bias_alpha": 0.0, "mag_gate": 1e9},
}


def test_the_list_is_every_recursive_paper_filter():
    assert set(PAPER_FILTERS) == set(estimators.names()) - {"triad", "quest", "robust"}


@pytest.mark.parametrize("name", PAPER_FILTERS)
def test_paper_preset_gives_the_papers_values(name):
    assert estimators.create(name, preset="paper").get_params() == PAPER_VALUES[name]
    # explicit parameters still override it
    key = next(iter(PAPER_VALUES[name]))
    assert estimators.create(name, preset="paper", **{key: 0.5}).get_params()[key] == 0.5


@pytest.mark.parametrize("name", PAPER_FILTERS)
def test_every_paper_filter_declares_a_search_space_inside_its_bounds(name):
    from ahrs_service.evaluation import tuning

    space = tuning.search_space(name)
    assert space, name
    tuning.check_space(name, space)  # raises on a range the Params class refuses
    defaults = estimators.create(name).get_params()
    for key, rng in space.items():
        assert rng.low < rng.high and (not rng.log or rng.low > 0)
        assert rng.low <= defaults[key] <= rng.high, (name, key)  # the tuned default lies inside


@pytest.mark.parametrize("name", PAPER_FILTERS)
def test_shipped_tuned_preset_is_the_default(name):
    path = presets.tuned_preset_path(name)
    assert path.is_file(), f"no shipped preset {path}"
    data = json.loads(path.read_text())
    assert data["estimator"] == name
    assert data["command"].startswith(f"ahrs-service tune {name} --dataset both")
    assert {"date", "budget", "train_by_dataset", "validation_by_dataset", "importances"} <= set(data)
    defaults = estimators.create(name).get_params()
    for key, value in data["params"].items():
        assert defaults[key] == value, (name, key)
    # the file loads as a preset too, to the same parameters
    assert estimators.create(name, preset=path).get_params() == defaults


def test_run_with_paper_preset_is_the_run_at_the_papers_values():
    rng = np.random.default_rng(5)
    gyr = rng.normal(0.0, 0.2, (400, 3))
    acc = np.array([0.0, 0.0, -9.81]) + rng.normal(0.0, 0.5, (400, 3))
    mag = np.array([20.0, 0.0, 45.0]) + rng.normal(0.0, 1.0, (400, 3))
    for name in ("mahony_direct", "valenti"):
        paper = estimators.run(name, gyr, acc, mag, rate_hz=100.0, preset="paper")
        assert np.array_equal(paper, estimators.run(name, gyr, acc, mag, rate_hz=100.0, **PAPER_VALUES[name]))
        assert not np.array_equal(paper, estimators.run(name, gyr, acc, mag, rate_hz=100.0))  # the default differs


def test_robust_and_single_shot_have_no_paper_preset():
    for name in ("robust", "triad"):
        with pytest.raises(ValueError, match=f"{name!r} has no preset 'paper'"):
            estimators.create(name, preset="paper")


def test_out_of_bounds_search_ranges_name_the_field():
    from ahrs_service.evaluation import tuning

    with pytest.raises(ValueError, match=r"valenti\.alpha .* outside its bounds"):
        tuning.check_space("valenti", {"alpha": SearchRange(0.001, 2.0)})  # alpha is a fraction
    with pytest.raises(ValueError, match=r"immersion_invariance\.gamma1 .* outside its bounds"):
        tuning.check_space("immersion_invariance", {"gamma1": SearchRange(0.0, 1.0)})  # γ must be > 0
    with pytest.raises(ValueError, match=r"unknown parameter 'gain' in the search space of 'ekf'"):
        tuning.check_space("ekf", {"gain": SearchRange(0.1, 1.0)})
    # a pair tied by low < high passes when declared disjoint, fails when crossed
    tuning.check_space("valenti", {"adaptive_low": SearchRange(0.01, 0.15), "adaptive_high": SearchRange(0.16, 1.0)})
    with pytest.raises(ValueError, match="adaptive_low"):
        tuning.check_space("valenti", {"adaptive_low": SearchRange(0.02, 0.5), "adaptive_high": SearchRange(0.35, 0.4)})


def test_out_of_bounds_preset_value_names_the_field(tmp_path):
    p = tmp_path / "v.json"
    p.write_text(json.dumps({"estimator": "valenti", "params": {"alpha": 3.0}}))
    with pytest.raises(ValueError, match="alpha must be in"):
        estimators.create("valenti", preset=p)


def test_config_preset_paper_runs_the_papers_values_under_params():
    cfg = config.validate({"estimator": {"name": "mahony_passive", "preset": "paper", "params": {"kp": 2.0}}})
    assert cfg.estimator["params"] == {**PAPER_VALUES["mahony_passive"], "kp": 2.0}
    assert config.validate({"estimator": {"name": "mahony_passive"}}).estimator["params"] == {}


def test_config_bad_presets_are_one_line_errors(tmp_path):
    with pytest.raises(config.ConfigError, match=r"estimator\.preset: .*no such file"):
        config.validate({"estimator": {"name": "madgwick", "preset": str(tmp_path / "none.json")}})
    p = tmp_path / "p.json"
    p.write_text(json.dumps({"estimator": "madgwick", "params": {"gain": 1.0}}))
    with pytest.raises(config.ConfigError, match=r"estimator\.preset: unknown parameter\(s\) gain"):
        config.validate({"estimator": {"name": "madgwick", "preset": str(p)}})
    with pytest.raises(config.ConfigError, match=r"estimator\.preset: estimator 'robust' has no preset 'paper'"):
        config.validate({"estimator": {"name": "robust", "preset": "paper"}})
    with pytest.raises(config.ConfigError, match=r"estimator\.preset: expected a string"):
        config.validate({"estimator": {"name": "madgwick", "preset": 3}})


def test_evaluate_preset_option_applies_paper_values_under_params():
    from ahrs_service.evaluation import report

    out = report.with_presets(["paper"], ["madgwick", "robust", "valenti"], {"valenti": {"alpha": 0.01}})
    assert out["madgwick"] == {"beta": 0.1} and "robust" not in out
    assert out["valenti"] == {**PAPER_VALUES["valenti"], "alpha": 0.01}


def _disturbed_field_run(heading_only: float) -> np.ndarray:
    """At rest, level, facing north; after 2 s a magnet turns the measured field 60° about the
    vertical: the gravity direction never changes."""
    n, rate = 2000, 100.0
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, -9.81], (n, 1))
    field = np.tile([20.0, 0.0, 45.0], (n, 1))
    a = np.radians(60.0)
    field[200:] = np.array([np.cos(a) * 20.0, np.sin(a) * 20.0, 45.0])
    return estimators.run("mahony_passive", gyr, acc, field, rate_hz=rate, kp=1.0, ki=0.0, w_acc=1.0, w_mag=1.0,
                          mag_heading_only=heading_only)


def _tilt_deg(q: np.ndarray) -> float:
    # angle between the estimated body z and earth down: 2·asin(√(x² + y²)) for q_earth←body
    return float(np.degrees(2.0 * np.arcsin(np.minimum(1.0, np.hypot(q[1], q[2])))))


def test_mahony_heading_only_field_term_cannot_tilt_the_estimate():
    paper_form = _disturbed_field_run(0.0)
    heading_only = _disturbed_field_run(1.0)
    assert max(_tilt_deg(q) for q in heading_only) < 0.01  # the field moves heading only
    assert max(_tilt_deg(q) for q in paper_form) > 5.0  # the paper's term drags roll/pitch with it
    # the heading follows the disturbed field: body turned 60° west of the field's north
    q = heading_only[-1]
    yaw = np.degrees(np.arctan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2)))
    assert yaw == pytest.approx(-60.0, abs=5.0)


def test_mahony_heading_only_is_a_switch():
    with pytest.raises(ValueError, match="mag_heading_only must be 0"):
        estimators.create("mahony_direct", mag_heading_only=0.5)
    field = {f.name: f for f in dataclasses.fields(estimators.get("mahony_direct").Params)}["mag_heading_only"]
    assert "search" not in field.metadata  # a form, not a gain: never tuned


#: the 9D filters with the magnetic-disturbance gate (``_kernel.mag_gate_accepts``)
MAG_GATED = ["ekf", "mahony_direct", "mahony_passive", "quaternion_kf", "valenti"]


def _heading_deg(q: np.ndarray) -> float:
    return float(np.degrees(np.arctan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))))


def _magnet_run(name: str, **params: float) -> np.ndarray:
    """At rest, level, facing north for 60 s at 100 Hz; after 5 s a magnet near the sensor adds
    its own field: the measured field is 1.4 times as strong, turned 60° about the vertical and
    less steep (the dip's sine 0.91 → 0.83). Nothing else changes: earth's field still points
    north."""
    n, rate = 6000, 100.0
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, -9.81], (n, 1))
    field = np.tile([20.0, 0.0, 45.0], (n, 1))
    a = np.radians(60.0)
    magnet = np.array([np.cos(a) * 30.0, np.sin(a) * 30.0, 45.0])  # dip's sine 0.83 instead of 0.91
    field[500:] = 1.4 * np.hypot(20.0, 45.0) * magnet / np.linalg.norm(magnet)
    return estimators.run(name, gyr, acc, field, rate_hz=rate, **params)


@pytest.mark.parametrize("name", MAG_GATED)
def test_mag_gate_keeps_the_heading_through_a_magnet(name):
    gated = _magnet_run(name)  # the tuned default: gate on
    assert estimators.create(name).get_params()["mag_gate"] < 1.0
    assert max(abs(_heading_deg(q)) for q in gated) < 0.5  # the magnet's field is never used
    assert max(_tilt_deg(q) for q in gated) < 0.5
    # the same filter with the gate off (the paper's 1e9) turns towards the magnet's field
    ungated = _magnet_run(name, mag_gate=1e9)
    assert abs(_heading_deg(ungated[-1])) > 10.0


@pytest.mark.parametrize("name", MAG_GATED)
def test_mag_gate_still_follows_earths_field(name):
    """A heading error at start-up (the field turned by 40° against the first sample, with the
    same magnitude and dip) is still corrected within 3 minutes (the EKF's tuned heading time
    constant is about a minute): the gate only refuses a different field."""
    n, rate = 18000, 100.0
    gyr = np.zeros((n, 3))
    acc = np.tile([0.0, 0.0, -9.81], (n, 1))
    field = np.tile([20.0, 0.0, 45.0], (n, 1))
    a = np.radians(40.0)
    field[0] = (np.cos(a) * 20.0, np.sin(a) * 20.0, 45.0)  # the first sample sets a wrong heading
    q = estimators.run(name, gyr, acc, field, rate_hz=rate)
    assert abs(_heading_deg(q[0])) > 30.0  # started from the first sample
    assert abs(_heading_deg(q[-1])) < 0.25 * abs(_heading_deg(q[0]))


@pytest.mark.parametrize("name", ["kalman_roll_pitch", "complementary_reduced"])
def test_rest_bias_estimate_keeps_the_tilt_while_the_accelerometer_is_out(name):
    """``bias_rate`` (the roll/pitch filters' steady-state bias, K.rest_bias_update): 40 s at
    rest with a biased gyro, then 30 s without accelerometer (the gyro alone, as through a shut
    gate): the default has learned the bias and keeps the tilt; without it (0, the paper) the
    bias integrates into roll and pitch."""
    rate = 100.0
    rng = np.random.default_rng(3)
    bias = np.array([0.01, -0.008, 0.005])  # rad/s
    n_rest, n_blind = int(40 * rate), int(30 * rate)
    gyr = bias + 1e-4 * rng.standard_normal((n_rest + n_blind, 3))
    acc = np.tile([0.0, 0.0, -9.81], (n_rest + n_blind, 1)) + 1e-3 * rng.standard_normal((n_rest + n_blind, 3))
    acc[n_rest:] = np.nan

    def tilt_deg(est):
        w, x, y, z = est.run(gyr, acc, None, dt=1.0 / rate)[-1]
        return np.degrees(np.arccos(np.clip(1.0 - 2.0 * (x * x + y * y), -1.0, 1.0)))

    learned = estimators.create(name)
    assert tilt_deg(learned) < 1.0  # measured 0.49° (KF), 0.28° (complementary)
    np.testing.assert_allclose(learned.gyro_bias, bias, atol=2e-4)
    assert tilt_deg(estimators.create(name, bias_rate=0.0)) > 15.0  # measured 29.5°, 24.9°
