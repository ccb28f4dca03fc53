"""Configuration: one validation path for ``config --check``, ``run`` and reloads (issue 14).

Every key of the schema is fed NaN, ±inf, wrong types and values beyond its range; each must give
one clean ConfigError line naming the key, never another exception.
"""

from __future__ import annotations

import math
import os

import pytest

from ahrs_service import cli
from ahrs_service import config as config_mod

HOSTILE = [float("nan"), float("inf"), float("-inf"), -1e300, 1e300, "text", True, [1, 2], {"a": 1}, -(2**70), 2**70]


def _keys():
    for section, keys in config_mod.SCHEMA.items():
        for key in keys:
            yield section, key


@pytest.mark.parametrize("section,key", list(_keys()))
def test_every_key_refuses_hostile_values_with_one_line_naming_it(section, key):
    default = config_mod.SCHEMA[section][key][0]
    refused = 0
    for value in HOSTILE:
        try:
            cfg = config_mod.validate({section: {key: value}})
        except config_mod.ConfigError as exc:
            msg = str(exc)
            assert "\n" not in msg
            assert msg.startswith(f"{section}.{key}"), msg
            refused += 1
            continue
        # accepted: only a value of the default's own kind, stored finite
        got = cfg.raw[section][key]
        assert type(got) is type(default) or (default is None), (key, value, got)
        if isinstance(got, float):
            assert math.isfinite(got)
    assert refused >= len(HOSTILE) - 2  # a table or list key may take one of the samples


@pytest.mark.parametrize("doc,key", [
    ({"estimator": {"declination_deg": float("nan")}}, "estimator.declination_deg"),
    ({"rates": {"estimation_hz": float("nan")}}, "rates.estimation_hz"),
    ({"log": {"rotate_mb": float("inf")}}, "log.rotate_mb"),
    ({"rates": {"attitude_hz": float("nan")}}, "rates.attitude_hz"),
    ({"estimator": {"mag_timeout_s": float("nan")}}, "estimator.mag_timeout_s"),
    ({"mounting": {"roll_deg": float("nan")}}, "mounting.roll_deg"),
    ({"location": {"latitude_deg": float("nan"), "longitude_deg": 0.0}}, "location.latitude_deg"),
    ({"mavlink": {"endpoints": ["bogus"]}}, "mavlink.endpoints[0]"),
    ({"mavlink": {"endpoints": ["udpout:127.0.0.1:99999"]}}, "mavlink.endpoints[0]"),
    ({"mavlink": {"endpoints": []}}, "mavlink.endpoints"),
    ({"mavlink": {"endpoints": ["udpin:127.0.0.1:14551", "udpin:127.0.0.1:14551"]}}, "mavlink.endpoints"),
    ({"source": {"board_options": {"gyro_range_dps": 1234}}}, "source.board_options"),
    ({"source": {"board_options": {"gyro_address": "x"}}}, "source.board_options.gyro_address"),
    ({"source": {"board_options": {"gyro_rate_hz": float("nan")}}}, "source.board_options.gyro_rate_hz"),
    ({"source": {"type": "recorded", "recorded_path": "/nope/none.mcap"}}, "source.recorded_path"),
    ({"estimator": {"params": {"beta": float("inf")}}}, "estimator.params.beta"),
    ({"estimator": {"name": "madgwick", "params": {"beta": 1e300}}}, "estimator.params.beta"),
    ({"log": {"directory": ""}}, "log.directory"),
    ({"calibration": {"gyro_bias": [1e300, 0.0, 0.0]}}, "calibration.gyro_bias"),
])
def test_defects_of_the_issue_are_refused_naming_the_key(doc, key):
    with pytest.raises(config_mod.ConfigError) as exc:
        config_mod.validate(doc)
    assert str(exc.value).startswith(key), str(exc.value)


def test_estimator_params_within_a_million_times_their_default_or_paper_value_pass():
    from ahrs_service import estimators
    from ahrs_service.estimators.presets import load_preset

    # the reference is the larger of the default and the paper's value
    beta = max(estimators.create("madgwick").get_params()["beta"], load_preset("madgwick", "paper")["beta"])
    for value in (0.0, beta * 0.5, beta * 999_999.0):
        cfg = config_mod.validate({"estimator": {"name": "madgwick", "params": {"beta": value}}})
        assert cfg.estimator["params"]["beta"] == value
    with pytest.raises(config_mod.ConfigError, match=r"estimator\.params\.beta = .*1e\+06 × its default"):
        config_mod.validate({"estimator": {"name": "madgwick", "params": {"beta": beta * 1.01e6}}})


def test_valid_endpoints_pass():
    cfg = config_mod.validate({"mavlink": {"endpoints": ["udpout:127.0.0.1:14550", "udpin:0.0.0.0:14551",
                                                         "tcp:127.0.0.1:5760", "/dev/ttyUSB0,921600"]}})
    assert len(cfg.mavlink["endpoints"]) == 4


def _check(path, capsys) -> tuple[int, str]:
    rc = cli.main(["config", "--check", str(path)])
    err = capsys.readouterr().err
    return rc, err


@pytest.mark.parametrize("kind", ["directory", "not_utf8", "no_permission", "missing"])
def test_unreadable_files_are_one_clean_line_in_check_and_run(tmp_path, capsys, kind):
    path = tmp_path / "ahrs.toml"
    if kind == "directory":
        path.mkdir()
    elif kind == "not_utf8":
        path.write_bytes(b'[estimator]\nname = "robust"\n# caf\xe9\n')
    elif kind == "no_permission":
        path.write_text("[estimator]\n")
        path.chmod(0)
        if os.access(path, os.R_OK):
            pytest.skip("running as root: permissions are not enforced")
    for argv in (["config", "--check", str(path)], ["run", "-c", str(path), "--no-log", "--duration", "0.1"]):
        rc = cli.main(argv)
        err = capsys.readouterr().err
        assert rc == 2
        assert err.count("\n") == 1 and "Traceback" not in err
        assert str(path) in err


def test_check_and_run_refuse_the_same_file(tmp_path, capsys):
    path = tmp_path / "ahrs.toml"
    path.write_text('[mavlink]\nendpoints = ["udpout:127.0.0.1:99999"]\n')
    rc, err = _check(path, capsys)
    assert rc == 2 and "mavlink.endpoints[0]" in err
    rc = cli.main(["run", "-c", str(path), "--no-log", "--duration", "0.1"])
    err = capsys.readouterr().err
    assert rc == 2 and "mavlink.endpoints[0]" in err


def _calibration_keys():
    """Every key of the free-form [calibration] section: SensorCalibration's fields (read from
    the dataclass, not listed by hand) and the Euler form of the mounting."""
    import dataclasses

    import numpy as np

    from ahrs_service.drivers.calibration import SensorCalibration

    default = SensorCalibration()
    for f in dataclasses.fields(SensorCalibration):
        yield f.name, np.shape(getattr(default, f.name))
    yield "mounting_rpy_deg", (3,)


@pytest.mark.parametrize("key,shape", list(_calibration_keys()))
def test_every_calibration_key_refuses_hostile_values_with_one_line_naming_it(key, shape):
    import numpy as np

    hostile = [np.full(shape, v).tolist() for v in (float("nan"), float("inf"), float("-inf"))]
    hostile += [np.full(shape, 1e300).tolist(), "text", True, 1.0, [1.0, 2.0], [[1.0, 2.0]], {"a": 1}]
    if len(shape) == 2:
        hostile.append(np.zeros(shape).tolist())  # a singular matrix
    for value in hostile:
        with pytest.raises(config_mod.ConfigError) as exc:
            config_mod.validate({"calibration": {key: value}})
        msg = str(exc.value)
        assert "\n" not in msg and msg.startswith("calibration") and repr(key) in msg, (value, msg)


@pytest.mark.parametrize("value,key", [
    ({"rate_hz": 0.5}, "mavlink.odometry.rate_hz"),  # 0 (off) or 1..200 Hz
    ({"rate_hz": 201.0}, "mavlink.odometry.rate_hz"),
    ({"rate_hz": float("nan")}, "mavlink.odometry.rate_hz"),
    ({"rules": "inav"}, "mavlink.odometry.rules"),
    ({"rate": 10.0}, "mavlink.odometry.rate"),
    ("px4", "mavlink.odometry"),
])
def test_a_sub_table_s_keys_are_checked_like_a_section_s(value, key):
    with pytest.raises(config_mod.ConfigError) as exc:
        config_mod.validate({"mavlink": {"odometry": value}})
    assert str(exc.value).startswith(key + ":"), str(exc.value)


def test_a_sub_table_fills_in_its_defaults():
    assert config_mod.validate({"mavlink": {"odometry": {"rate_hz": 30}}}).mavlink["odometry"] == {"rate_hz": 30.0, "rules": "px4"}
    assert config_mod.validate({}).mavlink["odometry"] == {"rate_hz": 0.0, "rules": "px4"}
