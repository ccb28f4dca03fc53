"""Config writes (ahrs_service.config_file): the user's comments and layout survive, the result
is valid TOML the service loads, and the write is atomic with a backup."""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from ahrs_service import config as config_mod
from ahrs_service.calibration.storage import save_calibration
from ahrs_service.config_file import render, update_config_file
from ahrs_service.core.calibration import SensorCalibration

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# every shape of TOML a user may write: comments at every place, an inline table
# (board_options), a sub-table, a multi-line array with comments inside, a multi-line
# string holding a newline, literal strings, odd spacing and indentation
COMMENTED = '''# ahrs-service on the test quad
# (edited by hand; keep this header)

[source]            # the IMU
type = "simulated_i2c"
board   =   'gy80'  # GY-80 on I2C bus 1
board_options = { retries = 3, reinit_period_s = 0.1 }  # inline table
can_channel = """first line
second line"""

[estimator]
name = "madgwick"   # a paper filter

  # gains, indented sub-table
  [estimator.params]
  beta = 0.05  # the gradient step

[mavlink]
endpoints = [
    "udpout:127.0.0.1:14550",  # QGroundControl
    "udpout:127.0.0.1:14551",  # MAVProxy
]

[calibration]
# terms of the last calibration, sensor axes
gyro_bias = [0.01, -0.02, 0.003]  # rad/s, from the bench
mounting_rpy_deg = [0.0, 0.0, 90.0]  # the board is turned on the frame

[log]
directory = "flight-logs"  # relative to WorkingDirectory
'''

NEW_BIAS = [0.1, -0.25, 0.30000000000000004]  # a float that needs all 17 digits


def _subsequence(needles: list[str], haystack: list[str]) -> bool:
    it = iter(haystack)
    return all(any(line == h for h in it) for line in needles)


def test_a_calibration_save_keeps_every_comment_and_line_the_user_wrote(tmp_path):
    path = tmp_path / "ahrs.toml"
    path.write_text(COMMENTED, encoding="utf-8")
    before = config_mod.load(path)
    new = SensorCalibration(gyro_bias=NEW_BIAS, acc_bias=[0.0, 0.1, 0.0], mag_hard_iron=[1.5, -2.0, 3.25])
    save_calibration(path, new)

    text = path.read_text(encoding="utf-8")
    lines = text.splitlines()
    # every line but the changed value is still there, in the same order, byte for byte
    kept = [line for line in COMMENTED.splitlines() if not line.startswith("gyro_bias")]
    assert _subsequence(kept, lines), text
    # the changed value kept its place in the section and its trailing comment
    [bias_line] = [line for line in lines if line.startswith("gyro_bias")]
    assert bias_line.endswith("# rad/s, from the bench")
    assert lines.index(bias_line) == COMMENTED.splitlines().index("gyro_bias = [0.01, -0.02, 0.003]  # rad/s, from the bench")
    # and the new keys are in [calibration], before [log]
    section = lines[lines.index("[calibration]"): lines.index("[log]")]
    assert {line.split(" =")[0] for line in section if " = " in line} == {
        "gyro_bias", "mounting_rpy_deg", "acc_bias", "acc_scale", "mag_hard_iron", "mag_soft_iron"}

    after = config_mod.load(path)
    for name in ("source", "estimator", "mavlink", "log", "mounting", "rates"):
        assert after.raw[name] == before.raw[name], name
    assert after.raw["source"]["can_channel"] == "first line\nsecond line"
    assert after.raw["source"]["board_options"] == {"retries": 3, "reinit_period_s": 0.1}
    cal = after.raw["calibration"]
    assert cal["gyro_bias"] == NEW_BIAS  # exact: floats round-trip
    assert cal["mag_hard_iron"] == [1.5, -2.0, 3.25]
    assert cal["mag_soft_iron"] == np.eye(3).tolist()
    assert cal["mounting_rpy_deg"] == [0.0, 0.0, 90.0]  # the mounting is not the calibration's
    assert (tmp_path / "ahrs.toml.bak").read_text(encoding="utf-8") == COMMENTED

    # a second save changes only the values again: the document does not drift
    save_calibration(path, SensorCalibration(gyro_bias=[0.0, 0.0, 0.0], acc_bias=[0.0, 0.1, 0.0],
                                             mag_hard_iron=[1.5, -2.0, 3.25]))
    second = path.read_text(encoding="utf-8")
    assert second.replace("gyro_bias = [0.0, 0.0, 0.0]", f"gyro_bias = {NEW_BIAS}".replace("'", "")) == text


def test_a_write_keeps_the_file_mode_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "ahrs.toml"
    path.write_text(COMMENTED, encoding="utf-8")
    os.chmod(path, 0o640)
    update_config_file(path, {"estimator": {"declination_deg": 3.5}}, backup=False)
    assert os.stat(path).st_mode & 0o777 == 0o640
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ahrs.toml"]  # no .bak asked, no .tmp left
    assert config_mod.load(path).estimator["declination_deg"] == 3.5
    assert "declination_deg = 3.5" in path.read_text().split("[estimator.params]")[0]  # in its own section


def test_a_write_that_would_not_load_or_a_broken_file_changes_nothing(tmp_path):
    path = tmp_path / "ahrs.toml"
    path.write_text(COMMENTED, encoding="utf-8")
    with pytest.raises(config_mod.ConfigError, match="estimator.declination_deg"):
        update_config_file(path, {"estimator": {"declination_deg": 500.0}})
    with pytest.raises(config_mod.ConfigError, match=r"\[log\] is not a table|log.*table"):
        path.write_text('log = "flat"\n', encoding="utf-8")
        update_config_file(path, {"log": {"directory": "x"}})
    path.write_text("[source\n", encoding="utf-8")
    with pytest.raises(config_mod.ConfigError, match="not valid TOML, not rewritten"):
        update_config_file(path, {"estimator": {"declination_deg": 1.0}})
    assert path.read_text(encoding="utf-8") == "[source\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ahrs.toml"]


def test_render_writes_valid_toml_for_newlines_deep_tables_and_arrays():
    # what the hand-written renderer got wrong: a string with a newline (and quotes,
    # backslashes, a tab), a table nested two deep, arrays of arrays, unset keys
    cfg = {
        "source": {"can_channel": 'a "quoted"\nsecond\\line\tend', "board_options": {"retries": 3}},
        "deep": {"outer": {"inner": {"x": 1.5, "names": ["a", "b"]}}},
        "calibration": {"mag_soft_iron": np.eye(3), "gyro_bias": np.array([0.1, 0.2, 0.30000000000000004])},
        "location": {"latitude_deg": None, "altitude_km": 0.0},
        "log": {"enabled": True, "rotate_mb": 0},
    }
    parsed = tomllib.loads(render(cfg))
    assert parsed == {
        "source": {"can_channel": 'a "quoted"\nsecond\\line\tend', "board_options": {"retries": 3}},
        "deep": {"outer": {"inner": {"x": 1.5, "names": ["a", "b"]}}},
        "calibration": {"mag_soft_iron": np.eye(3).tolist(), "gyro_bias": [0.1, 0.2, 0.30000000000000004]},
        "location": {"altitude_km": 0.0},
        "log": {"enabled": True, "rotate_mb": 0},
    }
    assert "# latitude_deg = (not set)" in render(cfg)


def test_the_default_configuration_prints_as_toml_that_loads_back():
    cfg = config_mod.load(None)
    assert config_mod.validate(tomllib.loads(config_mod.to_toml(cfg.raw))).raw == cfg.raw


# ------------------------------------------------------------------ from a ground station
def test_a_gyro_calibration_from_a_ground_station_saves_into_the_file_keeping_its_comments(tmp_path):
    """MAV_CMD_PREFLIGHT_CALIBRATION over real UDP from a pymavlink ground station: the service
    (started from a commented file) stores the new gyro bias there and every comment stays."""
    from pymavlink.dialects.v20 import common as mavlink2
    from test_service import RunningService, _ack, _wait_until, collect, make_gcs

    conn, port = make_gcs()
    text = COMMENTED.replace('"udpout:127.0.0.1:14550",  # QGroundControl', f'"udpout:127.0.0.1:{port}",  # this test')
    text = text.replace("[source]            # the IMU\n", "[source]            # the IMU\nprofile = 'static'  # at rest\n")
    text = text.replace("[log]\n", "[rates]\nestimation_hz = 200  # Hz\n\n[log]\n")
    text = text.replace('directory = "flight-logs"', f'directory = "{tmp_path / "logs"}"')
    path = tmp_path / "ahrs.toml"
    path.write_text(text, encoding="utf-8")
    run = RunningService(config_mod.load(path))
    try:
        pipeline = run.service.pipeline
        collect(conn, 0.5)
        assert _wait_until(lambda: pipeline.samples >= pipeline.rest_window, 60.0)  # a full rest window
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0)
        # the bounds only catch a hang: a starved machine (cold kernel caches compiling beside
        # it) delays the loop by seconds, and the save waits for nothing else
        ack = _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, seconds=60.0)
        assert ack is not None and ack.result == mavlink2.MAV_RESULT_ACCEPTED
        assert _wait_until(lambda: (tmp_path / "ahrs.toml.bak").exists(), 60.0)  # saved on the loop thread
        in_force = pipeline.calibration.gyro_bias.tolist()
    finally:
        run.stop()
        conn.close()
    saved = path.read_text(encoding="utf-8")
    kept = [line for line in text.splitlines() if not line.startswith("gyro_bias")]
    assert _subsequence(kept, saved.splitlines()), saved
    assert [line for line in saved.splitlines() if line.startswith("gyro_bias")][0].endswith("# rad/s, from the bench")
    assert config_mod.load(path).raw["calibration"]["gyro_bias"] == in_force != [0.01, -0.02, 0.003]
    assert (tmp_path / "ahrs.toml.bak").read_text(encoding="utf-8") == text
