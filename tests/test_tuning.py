"""``ahrs-service tune``: a tiny Optuna study on two BROAD recordings writes a preset file that
``estimators.create`` / ``estimators.run`` load; bad search spaces and presets name the key."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("optuna")

from ahrs_service import estimators  # noqa: E402
from ahrs_service.cli import main as cli_main  # noqa: E402
from ahrs_service.estimators.presets import SearchRange  # noqa: E402
from ahrs_service.evaluation import tuning  # noqa: E402


@pytest.mark.timeout(240)
def test_tiny_tune_writes_a_loadable_preset(broad_dir, tmp_path, capsys):
    out = tmp_path / "madgwick.preset.json"
    code = cli_main(["tune", "madgwick", "--data", str(broad_dir), "--trials", "_B", "--budget", "3",
                     "--workers", "1", "--out", str(out)])
    assert code == 0, capsys.readouterr().err
    preset = json.loads(out.read_text())
    assert preset["estimator"] == "madgwick" and set(preset["params"]) == {"beta"}
    assert 0.005 <= preset["params"]["beta"] <= 1.0  # inside the declared space
    assert preset["trials"] == 3 and preset["command"].startswith("ahrs-service tune madgwick --dataset broad")
    assert preset["budget"] == 3 and preset["dataset"] == "broad" and len(preset["date"]) == 10
    # leave-one-recording-out: one validation score per recording, their mean reported
    assert set(preset["validation"]) == set(preset["recordings"]) and len(preset["recordings"]) >= 2
    assert all(r.startswith("broad/") for r in preset["recordings"])
    assert preset["validation_by_dataset"]["broad"] == pytest.approx(np.mean(list(preset["validation"].values())))
    assert preset["validation_objective"] == pytest.approx(preset["validation_by_dataset"]["broad"])
    # one data set: the objective is the plain mean of the best trial's per-recording scores
    assert preset["train_objective"] == pytest.approx(np.mean(list(preset["train"].values())))
    assert preset["metrics"] == {"broad": "total rmse"}
    est = estimators.create("madgwick", preset=out)
    assert est.get_params()["beta"] == preset["params"]["beta"]
    # explicit parameters override the preset
    assert estimators.create("madgwick", preset=out, beta=0.2).get_params()["beta"] == 0.2
    gyr = np.zeros((20, 3)); acc = np.tile([0.0, 0.0, -9.81], (20, 1))
    q = estimators.run("madgwick", gyr, acc, rate_hz=100.0, preset=out)
    assert q.shape == (20, 4)


def test_declared_search_space_comes_from_the_params_field():
    assert tuning.search_space("madgwick") == {"beta": SearchRange(0.005, 1.0, log=True)}


def test_bad_search_spaces_name_the_key():
    with pytest.raises(ValueError, match="unknown parameter 'gain'"):
        tuning.check_space("madgwick", {"gain": SearchRange(0.1, 1.0)})
    with pytest.raises(ValueError, match=r"madgwick\.beta .* outside its bounds"):
        tuning.check_space("madgwick", {"beta": SearchRange(-1.0, 1.0)})  # beta must be >= 0
    with pytest.raises(ValueError, match="LOW < HIGH"):
        tuning.check_space("madgwick", {"beta": SearchRange(1.0, 0.1)})
    with pytest.raises(ValueError, match="expected NAME=LOW:HIGH"):
        tuning.parse_space(["beta=0.1"], "madgwick")


def test_cli_bad_space_is_a_one_line_error(broad_dir, capsys):
    assert cli_main(["tune", "madgwick", "--data", str(broad_dir), "--space", "gain=0:1", "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'gain'" in err[0]


def test_bad_presets_name_the_problem(tmp_path):
    p = tmp_path / "p.json"
    p.write_text(json.dumps({"estimator": "madgwick", "params": {"gain": 1.0}}))
    with pytest.raises(ValueError, match="gain"):
        estimators.create("madgwick", preset=p)
    p.write_text(json.dumps({"estimator": "ekf", "params": {}}))
    with pytest.raises(ValueError, match="for estimator 'ekf'"):
        estimators.create("madgwick", preset=p)
    with pytest.raises(ValueError, match="no such file"):
        estimators.create("madgwick", preset=tmp_path / "none.json")
    p.write_text(json.dumps({"estimator": "madgwick", "params": {"beta": -1.0}}))
    with pytest.raises(ValueError, match="beta"):
        estimators.create("madgwick", preset=p)


def test_objective_is_the_worse_data_set_against_its_target():
    per = np.array([1.0, 3.0, 5.0, 10.0])
    # BROAD mean 3 (target 6: 0.5), DIDO 10 (target 5: 2.0): the worse one counts
    assert tuning.objective(per, ["broad", "broad", "broad", "dido"]) == pytest.approx(2.0)
    # without heading BROAD is judged on inclination against 3 deg
    assert tuning.objective(np.array([6.0, 1.0]), ["broad", "dido"], False) == pytest.approx(2.0)
    assert tuning.objective(per, ["dido"] * 4) == pytest.approx(4.75)  # one data set: degrees
    assert tuning.metric_of("broad", True) == "total_rmse"
    assert tuning.metric_of("broad", False) == tuning.metric_of("dido", True) == "inclination_rmse"


@pytest.mark.timeout(240)
def test_tune_on_both_data_sets_scores_each_on_its_metric(broad_dir):
    from ahrs_service.evaluation import dido
    from ahrs_service.execution import open_runner

    if dido.missing_reason(dido.default_dir()):
        pytest.skip(dido.missing_reason(dido.default_dir()))
    recs = [tuning.Recording("broad", str(broad_dir), tuning.recordings_of("broad", str(broad_dir), None)[0].name),
            tuning.Recording("dido", str(dido.default_dir()), dido.list_trials(dido.default_dir())[-1])]
    with open_runner(1, None) as runner:
        result = tuning.tune("madgwick", recs, tuning.search_space("madgwick"), budget=2, runner=runner)
    assert result.metrics == {"broad": "total rmse", "dido": "inclination rmse"}
    assert set(result.train) == set(result.validation) == {r.label for r in recs}
    b, d = (result.train[r.label] for r in recs)
    assert result.train_objective == pytest.approx(max(b / 6.0, d / 5.0))
    assert set(result.validation_by_dataset) == {"broad", "dido"}
    vb, vd = (result.validation[r.label] for r in recs)
    assert result.validation_objective == pytest.approx(max(vb / 6.0, vd / 5.0))


def test_cli_both_with_one_data_folder_is_a_one_line_error(broad_dir, capsys):
    assert cli_main(["tune", "madgwick", "--dataset", "both", "--data", str(broad_dir), "--workers", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dataset both" in err[0]


@pytest.mark.timeout(300)
def test_tune_on_a_cluster_asks_trials_in_batches_sized_for_the_task_floor(broad_dir):
    """Two recordings of about 30 ms a job by the cost model: a batch gives each of the 2
    workers two 0.5 s floors of work, 2 x ceil(1.0 / 0.06) = 34 trials; the batch's 68 jobs
    run as 2 tasks, a recording's 34 jobs (a worker's share) each, not 68."""
    from ahrs_service.evaluation import report
    from ahrs_service.execution import open_runner

    recs = tuning.recordings_of("broad", str(broad_dir), None)[:2]
    base = report.make_columns(["madgwick"], [], {})[0]
    one_trial = [report.TrialJob(r.data_dir, r.name, base, False, r.dataset) for r in recs]
    trial_s = sum(report.expected_job_seconds(job) for job in one_trial)
    assert 0.04 < trial_s < 0.08
    with open_runner(1, None) as serial:
        assert tuning.trials_per_batch(serial, one_trial) == 1
    with open_runner(2, None, task_floor_s=0.5) as runner:
        batch = tuning.trials_per_batch(runner, one_trial)
        assert batch == 2 * math.ceil(1.0 / trial_s)
        result = tuning.tune("madgwick", recs, tuning.search_space("madgwick"), budget=batch, runner=runner)
        assert runner.tasks_submitted == 2
    assert result.trials == batch and set(result.train) == {r.label for r in recs}
    assert all(0.0 < v < 20.0 for v in result.train.values())
