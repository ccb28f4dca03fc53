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

    from ahrs_service.core.calibration import SensorCalibration

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
    sets = {"fallback_source_set": 2, "primary_source_set": 1}
    assert config_mod.validate({"mavlink": {"odometry": {"rate_hz": 30}}}).mavlink["odometry"] == {"rate_hz": 30.0, "rules": "px4", **sets}
    assert config_mod.validate({}).mavlink["odometry"] == {"rate_hz": 0.0, "rules": "px4", **sets}


# --- re-probe of issue 14 (probe14): what `config --check` still passed and `run` refused -----


def _check_and_run(path, capsys) -> list[tuple[int, str]]:
    """``config --check`` then ``run`` of ``path``: (exit code, stderr) of each."""
    out = []
    for argv in (["config", "--check", str(path)], ["run", "-c", str(path), "--no-log", "--duration", "0.1"]):
        rc = cli.main(argv)
        out.append((rc, capsys.readouterr().err))
    return out


def _refused_by_check_and_run(path, capsys) -> list[str]:
    """The stderr of ``config --check`` and of ``run`` of ``path``, each asserted to be a
    refusal: exit 2, one line, no traceback."""
    errors = []
    for rc, err in _check_and_run(path, capsys):
        assert rc == 2, err
        assert err.count("\n") == 1 and "Traceback" not in err
        errors.append(err)
    return errors


@pytest.mark.parametrize("kind", ["directory", "not_a_log", "not_hdf5"])
def test_a_recorded_path_that_is_no_log_is_refused_by_check_and_run_naming_the_key(tmp_path, capsys, kind):
    """A directory was passed by `config --check` and `run` said only "cannot start: [Errno 21]
    Is a directory" (exit 1); a file that is no MCAP log was passed by both, and `run` played
    nothing and exited 0 ("samples 0")."""
    if kind == "directory":
        recorded = tmp_path / "flights"
        recorded.mkdir()
        want = "is a directory"
    elif kind == "not_a_log":
        recorded = tmp_path / "notes.mcap"
        recorded.write_text("not a flight log\n")
        want = "not an MCAP log"
    else:
        recorded = tmp_path / "trial.hdf5"
        recorded.write_bytes(b"\x89MCAP0\r\n" + bytes(600))
        want = "not an HDF5 file"
    path = tmp_path / "ahrs.toml"
    path.write_text(f'[source]\ntype = "recorded"\nrecorded_path = "{recorded}"\n'
                    '[mavlink]\nendpoints = ["udpout:127.0.0.1:15599"]\n')
    for err in _refused_by_check_and_run(path, capsys):
        assert "source.recorded_path" in err and want in err and str(recorded) in err


def test_an_mcap_log_and_a_broad_file_pass_as_recorded_path(tmp_path):
    mcap = tmp_path / "flight.mcap"
    mcap.write_bytes(b"\x89MCAP0\r\n")  # truncated after the magic: the reader reports the damage
    cfg = config_mod.validate({"source": {"type": "recorded", "recorded_path": str(mcap)}})
    assert cfg.source["recorded_path"] == str(mcap)
    h5 = tmp_path / "trial.h5"
    h5.write_bytes(bytes(512) + b"\x89HDF\r\n\x1a\n" + bytes(64))  # after a 512-byte user block
    assert config_mod.validate({"source": {"type": "recorded", "recorded_path": str(h5)}}).source["recorded_path"] == str(h5)


@pytest.mark.parametrize("kind", ["can", "simulated_can"])
def test_an_unknown_can_interface_is_refused_by_check_and_run_naming_the_key(tmp_path, capsys, kind):
    """`config --check` passed can_interface = "x"; `run` said "cannot start: cannot open CAN bus
    interface='x' …: Unknown interface type" (exit 1, no key)."""
    path = tmp_path / "ahrs.toml"
    path.write_text(f'[source]\ntype = "{kind}"\ncan_interface = "x"\n'
                    '[mavlink]\nendpoints = ["udpout:127.0.0.1:15599"]\n')
    for err in _refused_by_check_and_run(path, capsys):
        assert "source.can_interface: 'x'" in err and "socketcan" in err


@pytest.mark.parametrize("board,options,key", [
    ("icm42688p", {"odr_hz": "x"}, "source.board_options.odr_hz"),
    ("icm42688p", {"watermark": 1.5}, "source.board_options.watermark"),
    ("icm42688p", {"fifo_read_hz": [100]}, "source.board_options.fifo_read_hz"),
    ("icm20948", {"gyro_range_dps": "2000"}, "source.board_options.gyro_range_dps"),
    ("bmi088", {"acc_odr_hz": {"a": 1}}, "source.board_options.acc_odr_hz"),
    ("bmi088", {"gyro_spi_device": "1"}, "source.board_options.gyro_spi_device"),
    ("icm42688p", {"retries": True}, "source.board_options.retries"),
])
def test_fifo_board_options_of_the_wrong_type_name_the_option(board, options, key):
    """A FIFO board's option of the wrong type gave "source.board_options: unsupported operand
    type(s) for /: 'str' and 'int'" (Python's words, no option named)."""
    with pytest.raises(config_mod.ConfigError) as exc:
        config_mod.validate({"source": {"type": "simulated_spi", "board": board, "board_options": options}})
    msg = str(exc.value)
    assert msg.startswith(key) and "is not" in msg and "\n" not in msg, msg


@pytest.mark.parametrize("endpoints", [
    ["udpin:127.0.0.1:14551", "udp:127.0.0.1:14551"],  # mavutil opens udp: as udpin
    ["udpin:0.0.0.0:14551", "udpin:127.0.0.1:14551"],
    ["tcpin:127.0.0.1:5760", "tcpin:0.0.0.0:5760"],
])
def test_two_listening_endpoints_on_one_port_are_refused(endpoints):
    """Two links bound to one port (SO_REUSEADDR) each get part of the datagrams; only the same
    string twice was refused."""
    with pytest.raises(config_mod.ConfigError, match=r"^mavlink\.endpoints: .* listens on the same port as"):
        config_mod.validate({"mavlink": {"endpoints": endpoints}})
    # one listener and one sender on a port, or UDP and TCP on the same number, are fine
    config_mod.validate({"mavlink": {"endpoints": ["udpin:127.0.0.1:14551", "udpout:127.0.0.1:14551",
                                                   "tcpin:127.0.0.1:14551"]}})


# --- re-probe of issue 14 (h14) ----------------------------------------------------------------


def test_the_autopilot_link_and_a_ground_link_listening_on_one_port_are_refused():
    """``source.mavlink_connection`` and a ``mavlink.endpoints`` entry on one listening port
    both bound it and `run` started: each link got part of the datagrams (IMU stream or ground
    station lost). Only two ground links on one port were refused."""
    source = {"type": "mavlink", "mavlink_connection": "udpin:127.0.0.1:14560"}
    with pytest.raises(config_mod.ConfigError) as exc:
        config_mod.validate({"source": source, "mavlink": {"endpoints": ["udpin:0.0.0.0:14560"]}})
    msg = str(exc.value)
    assert msg.startswith("source.mavlink_connection: 'udpin:127.0.0.1:14560' listens on the same port as "
                          "mavlink.endpoints[0] 'udpin:0.0.0.0:14560'"), msg
    # another port, a sender on the port, or a source that is not the autopilot: fine
    config_mod.validate({"source": source, "mavlink": {"endpoints": ["udpin:127.0.0.1:14561",
                                                                     "udpout:127.0.0.1:14560"]}})
    config_mod.validate({"mavlink": {"endpoints": ["udpin:127.0.0.1:14540"]}})


def test_a_listening_endpoint_on_an_address_this_computer_lacks_is_refused_by_check(tmp_path, capsys):
    """``udpin:192.0.2.1:14560`` (TEST-NET-1: never a local address) passed ``config --check``
    and ``run`` refused it ("cannot assign requested address")."""
    path = tmp_path / "c.toml"
    path.write_text('[mavlink]\nendpoints = ["udpout:127.0.0.1:14550", "udpin:192.0.2.1:14560"]\n')
    rc = cli.main(["config", "--check", str(path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert ("mavlink.endpoints[1]: 'udpin:192.0.2.1:14560': 192.0.2.1 is not an address of this computer"
            in err), err
    path.write_text('[mavlink]\nendpoints = ["udpin:127.0.0.1:14560", "tcpin:0.0.0.0:14561"]\n')
    assert cli.main(["config", "--check", str(path)]) == 0


def test_a_preset_path_the_file_system_cannot_take_names_the_key(tmp_path, capsys):
    """``estimator.preset`` of 5000 characters: "ahrs-service: aaaa…: File name too long" (the
    5000 characters, no key; a reload said "reload refused: [Errno 36] …")."""
    path = tmp_path / "c.toml"
    path.write_text(f'[estimator]\nname = "madgwick"\npreset = "{"a" * 5000}"\n')
    with pytest.raises(config_mod.ConfigError) as exc:
        config_mod.load(path)
    msg = str(exc.value)
    assert msg.startswith("estimator.preset: 'aaaa") and "(5000 characters) cannot be read: File name too long" in msg
    assert len(msg) < 200 and "\n" not in msg
