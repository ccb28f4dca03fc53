"""Replay: a recording made the service's way (one row at a time, live parameter change) is
reproduced bit for bit; other settings are compared; `ahrs-service replay` writes a new log."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service.cli import main as cli_main
from ahrs_service.logs import schemas
from ahrs_service.logs.reader import read_log
from ahrs_service.replay import compare, error_angles, replay

_spec = importlib.util.spec_from_file_location(
    "make_fixtures", Path(__file__).resolve().parent / "fixtures" / "make_fixtures.py"
)
make_fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_fixtures)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(log, q_live, change index) of a fresh recording with a live beta change half-way."""
    directory = tmp_path_factory.mktemp("rec")
    path, q_live, t_ns, rows, q_true = make_fixtures.record_analytic(directory, seconds=3.0)
    return read_log(path), q_live, len(t_ns) // 2


def test_replay_reproduces_the_live_estimate_bit_exact(recording):
    log, q_live, k = recording
    assert log.damage is None
    assert [(c["sample_index"], c["name"], c["new"]) for c in log.param_changes] == [(k, "beta", 0.3)]
    assert np.array_equal(log.attitudes, q_live)  # the writer stored what the loop computed
    q = replay(log)
    assert np.array_equal(q, q_live)
    result = compare(log, q)["vs_recorded"]
    assert result["identical"] and result["rms_deg"] == 0.0 and result["max_abs_diff"] == 0.0


def test_parameter_change_applies_exactly_at_its_sample(recording):
    log, q_live, k = recording
    q = replay(log, follow_param_changes=False)
    same = np.all(q == q_live, axis=1)
    assert same[:k].all() and not same[k:].any()
    # pinning beta overrides both the start value and the recorded change
    pinned = replay(log, params={"beta": 0.3})
    assert not np.array_equal(pinned[:k], q_live[:k])


def test_replay_with_other_settings_is_compared_to_recording_and_truth(recording):
    log, q_live, k = recording
    q = replay(log, "madgwick", {"beta": 0.02})
    result = compare(log, q)
    assert result["vs_recorded"]["rms_deg"] > 0.0 and not result["vs_recorded"]["identical"]
    # the error vs truth agrees with an independent evaluation of the same angles
    total = error_angles(q, log.truth)[0]
    assert result["vs_truth"]["total"] == pytest.approx(np.degrees(np.sqrt(np.mean(total**2))), rel=1e-12)
    assert result["vs_truth"]["samples"] == len(log)


def test_unknown_parameter_or_missing_estimator_is_an_error(recording):
    log, _, _ = recording
    with pytest.raises(ValueError, match="unknown parameter"):
        replay(log, params={"gain": 1.0})
    nameless = read_log(log.path)
    nameless.estimator = None
    with pytest.raises(ValueError, match="names no estimator"):
        replay(nameless)


def test_cli_replay_writes_a_new_log(recording, tmp_path, capsys):
    log, q_live, _ = recording
    out = tmp_path / "new.mcap"
    code = cli_main(["replay", str(log.path), "--estimator", "madgwick", "--param", "beta=0.05", "--out", str(out), "--json"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    assert result["params"] == {"beta": 0.05} and result["output"] == str(out)
    new = read_log(out)
    assert new.estimator == "madgwick" and new.params == {"beta": 0.05}
    assert np.array_equal(new.rows, log.rows)  # raw copied
    assert np.array_equal(new.original, q_live)  # the recorded estimate kept beside the new one
    assert np.array_equal(new.truth, log.truth)
    assert np.array_equal(new.attitudes, replay(log, "madgwick", {"beta": 0.05}))
    assert result["vs_recorded"]["rms_deg"] == pytest.approx(compare(log, new.attitudes)["vs_recorded"]["rms_deg"])
    # the new log replays to itself (its /config names what produced it)
    assert compare(new, replay(new, follow_param_changes=True))["vs_recorded"]["identical"]


def test_cli_replay_with_recorded_settings_keeps_the_live_change(recording, tmp_path, capsys):
    log, q_live, k = recording
    out = tmp_path / "same.mcap"
    assert cli_main(["replay", str(log.path), "--out", str(out)]) == 0
    assert "bit-exact" in capsys.readouterr().out
    new = read_log(out)
    assert new.param_changes == log.param_changes and new.params == log.params
    assert np.array_equal(new.attitudes, q_live) and np.array_equal(replay(new), q_live)


@pytest.mark.parametrize("one_call", [False, True], ids=["three calls", "write_sample"])
def test_every_rotated_file_replays_exactly_from_its_state_snapshot(tmp_path, one_call):
    path, q_live, t_ns, rows, _ = make_fixtures.record_analytic(
        tmp_path, seconds=3.0, pace_every=10, chunk_size=8192, rotate_bytes=15_000, flush_interval_s=0.05,
        one_call=one_call,
    )
    files = sorted(tmp_path.glob("flight-*.mcap"), key=lambda p: read_log(p).index[0])
    assert len(files) >= 3
    logs = [read_log(p) for p in files]
    assert np.array_equal(np.concatenate([log.rows for log in logs]), rows)
    assert logs[0].initial_state is None
    start = 0
    for log in logs:
        if log is not logs[0]:
            # a rotated file starts from the state after the previous file's last sample
            assert log.initial_state is not None and log.initial_state["sample_index"] == log.index[0]
        q = replay(log)
        assert np.array_equal(q, q_live[start : start + len(log)]), log.path.name
        fresh = replay(log, use_recorded_state=False)
        assert log is logs[0] or not np.array_equal(fresh, q)
        start += len(log)
    with open(files[1], "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            assert schemas.validate(json.loads(message.data), json.loads(schema.data)) == [], channel.topic


def test_replay_of_a_log_whose_config_was_lost_names_the_damage(recording, tmp_path, capsys):
    """Issue 14: a log cut before its /config says it is damaged, not only 'no estimator'."""
    log, _, _ = recording
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(log.path.read_bytes()[:40])
    assert cli_main(["replay", str(cut)]) == 2
    err = capsys.readouterr().err
    assert "names no estimator" in err and "/config was lost" in err and "damaged" in err


@pytest.mark.parametrize("argv", [["log", "info"], ["replay"], ["log", "recover"], ["log", "import-broad"]])
@pytest.mark.parametrize("kind", ["missing", "directory"])
def test_every_command_taking_a_path_gives_one_line_for_a_bad_one(argv, kind, tmp_path, capsys):
    path = tmp_path / "nope.mcap"
    if kind == "directory":
        path.mkdir()
    extra = [str(tmp_path / "out.mcap")] if argv[-1] == "import-broad" else []
    assert cli_main([*argv, str(path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "Traceback" not in err
    if argv == ["replay"] and kind == "directory":  # a directory is a fleet of logs: here an empty one
        assert "no MCAP log" in err
    else:
        assert ("does not exist" if kind == "missing" else "is a directory") in err
