"""Service configuration: TOML file → validated, typed settings with the embedded defaults.

Every key has a default (the embedded default runs a simulated GY-80 flying the first paper's
validation manoeuvre, publishing over UDP to 127.0.0.1:14550 and logging to ./flight-logs).
A malformed file stops the start with a :class:`ConfigError` naming the key and what it
accepts. ``ahrs-service config --print-default`` prints the full default file.
"""

from __future__ import annotations

import copy
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

SOURCE_TYPES = ("simulated_i2c", "simulated_spi", "simulated_can", "simulated", "i2c", "spi", "can", "recorded")
BOARDS = ("gy80", "minimu9v2", "mpu9250", "icm42688p", "icm20948", "bmi088")
PROFILES = ("static", "validation", "figure8")
IDENTITIES = ("standalone", "companion")


class ConfigError(ValueError):
    """A configuration problem; the message names the key and the accepted values."""


# key -> (default, checker). A checker returns the cleaned value or raises ConfigError.
Checker = Callable[[str, Any], Any]


def _number(lo: float | None = None, hi: float | None = None, integer: bool = False) -> Checker:
    def check(key: str, v: Any) -> Any:
        ok_type = isinstance(v, int) if integer else isinstance(v, (int, float))
        if isinstance(v, bool) or not ok_type:
            kind = "an integer" if integer else "a number"
            raise ConfigError(f"{key}: expected {kind}, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ConfigError(f"{key}: {v!r} is out of range [{lo}, {hi}]")
        return int(v) if integer else float(v)

    return check


def _choice(options: tuple[str, ...]) -> Checker:
    def check(key: str, v: Any) -> Any:
        if v not in options:
            raise ConfigError(f"{key}: {v!r} is not one of {', '.join(options)}")
        return v

    return check


def _string(key: str, v: Any) -> str:
    if not isinstance(v, str):
        raise ConfigError(f"{key}: expected a string, got {v!r}")
    return v


def _boolean(key: str, v: Any) -> bool:
    if not isinstance(v, bool):
        raise ConfigError(f"{key}: expected true or false, got {v!r}")
    return v


def _string_list(key: str, v: Any) -> list[str]:
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{key}: expected a list of strings, got {v!r}")
    return list(v)


def _table(key: str, v: Any) -> dict:
    if not isinstance(v, dict):
        raise ConfigError(f"{key}: expected a table, got {v!r}")
    return dict(v)


def _optional(check: Checker) -> Checker:
    return lambda key, v: None if v is None else check(key, v)


def _estimator_name(key: str, v: Any) -> str:
    from ahrs_service import estimators

    if v not in estimators.names():
        raise ConfigError(f"{key}: {v!r} is not one of {', '.join(estimators.names())}")
    return v


def _signing_key(key: str, v: Any) -> str:
    v = _string(key, v)
    if v:
        try:
            raw = bytes.fromhex(v)
        except ValueError:
            raise ConfigError(f"{key}: expected 64 hexadecimal digits (a 32-byte key), got {v!r}") from None
        if len(raw) != 32:
            raise ConfigError(f"{key}: expected 64 hexadecimal digits (a 32-byte key), got {len(raw)} bytes")
    return v


SCHEMA: dict[str, dict[str, tuple[Any, Checker]]] = {
    "source": {
        "type": ("simulated_i2c", _choice(SOURCE_TYPES)),
        "board": ("gy80", _choice(BOARDS)),
        "i2c_bus": (1, _number(0, 255, integer=True)),
        # the I2C clock the rate check assumes (FIFO boards): 100 kHz standard, 400 kHz fast mode
        "i2c_speed_hz": (400_000, _number(10_000, 3_400_000, integer=True)),
        # SPI boards: /dev/spidev<spi_bus>.<spi_device>, clock mode 0-3, clock in Hz
        "spi_bus": (0, _number(0, 255, integer=True)),
        "spi_device": (0, _number(0, 255, integer=True)),
        "spi_mode": (3, _number(0, 3, integer=True)),
        "spi_speed_hz": (8_000_000, _number(10_000, 50_000_000, integer=True)),
        # FIFO watermark interrupt line "<chip>:<line>", e.g. "gpiochip0:17"; "" = timer polling
        "drdy_gpio": ("", _string),
        # board options (addresses, ranges, rates), e.g. {gyro_rate_hz = 800}: docs/drivers.md
        "board_options": ({}, _table),
        "profile": ("validation", _choice(PROFILES)),
        "loop_profile": (True, _boolean),
        "sensor_errors": (True, _boolean),
        "seed": (0, _number(0, None, integer=True)),
        "can_interface": ("virtual", _string),
        "can_channel": ("ahrs", _string),
        "can_bitrate": (1_000_000, _number(10_000, 8_000_000, integer=True)),
        "can_node_id": (0, _number(0, 127, integer=True)),
        "recorded_path": ("", _string),
        "recorded_realtime": (True, _boolean),
    },
    "estimator": {
        "name": ("robust", _estimator_name),
        "params": ({}, _table),
        "mag_timeout_s": (0.5, _number(0.01, 60.0)),
        "declination_deg": (0.0, _number(-180.0, 180.0)),
    },
    "rates": {
        "estimation_hz": (200.0, _number(10.0, 2000.0)),
        "heartbeat_hz": (1.0, _number(0.0, 10.0)),
        "attitude_hz": (50.0, _number(0.0, 1000.0)),
        "attitude_quaternion_hz": (50.0, _number(0.0, 1000.0)),
        "highres_imu_hz": (0.0, _number(0.0, 1000.0)),
        "sys_status_hz": (1.0, _number(0.0, 50.0)),
    },
    "mounting": {
        "roll_deg": (0.0, _number(-180.0, 180.0)),
        "pitch_deg": (0.0, _number(-180.0, 180.0)),
        "yaw_deg": (0.0, _number(-180.0, 180.0)),
    },
    "calibration": {},  # free-form: validated by drivers.calibration.SensorCalibration.from_dict
    "mavlink": {
        "endpoints": (["udpout:127.0.0.1:14550"], _string_list),
        "identity": ("standalone", _choice(IDENTITIES)),
        "system_id": (1, _number(1, 255, integer=True)),
        "signing_key": ("", _signing_key),
    },
    # where the vehicle flies: when latitude and longitude are set, the magnetic declination
    # comes from the World Magnetic Model for today (it replaces estimator.declination_deg)
    "location": {
        "latitude_deg": (None, _optional(_number(-90.0, 90.0))),
        "longitude_deg": (None, _optional(_number(-180.0, 180.0))),
        "altitude_km": (0.0, _number(-1.0, 850.0)),
    },
    "log": {
        "enabled": (True, _boolean),
        "directory": ("flight-logs", _string),
        "rotate_mb": (0.0, _number(0.0, None)),
        "rotate_minutes": (0.0, _number(0.0, None)),
        # the estimator's diagnostics (rest, rejections, form) in /attitude this often, Hz
        "diagnostics_hz": (10.0, _number(0.0, 1000.0)),
    },
    # Foxglove WebSocket live view (extra "live"): docs/live.md
    "live": {
        "enabled": (False, _boolean),
        "host": ("127.0.0.1", _string),
        "port": (8765, _number(0, 65535, integer=True)),
        # viewers get the per-sample channels (/imu/raw, /attitude, /tf) at most this often, Hz
        "rate_hz": (30.0, _number(1.0, 200.0)),
    },
}


@dataclass
class Config:
    """Validated settings: ``cfg.section["key"]``; ``cfg.raw`` is the full effective dict."""

    raw: dict[str, dict[str, Any]]
    path: Path | None = None
    overrides: dict[str, dict[str, Any]] | None = None  # from the command line; kept for reloads

    def __getattr__(self, section: str) -> dict[str, Any]:
        try:
            return self.__dict__["raw"][section]
        except KeyError:
            raise AttributeError(section) from None


def defaults() -> dict[str, dict[str, Any]]:
    return {sec: {k: copy.deepcopy(d) for k, (d, _) in keys.items()} for sec, keys in SCHEMA.items()}


def validate(data: dict[str, Any]) -> Config:
    """Checks a parsed TOML document against the schema and fills in defaults."""
    if not isinstance(data, dict):
        raise ConfigError("the configuration must be a TOML table")
    unknown = sorted(set(data) - set(SCHEMA))
    if unknown:
        raise ConfigError(f"{unknown[0]}: unknown section; accepted sections: {', '.join(SCHEMA)}")
    out = defaults()
    for section, keys in SCHEMA.items():
        given = data.get(section, {})
        if not isinstance(given, dict):
            raise ConfigError(f"{section}: expected a table, got {given!r}")
        if section == "calibration":
            out[section] = _check_calibration(given)
            continue
        for key, value in given.items():
            if key not in keys:
                raise ConfigError(f"{section}.{key}: unknown key; accepted keys: {', '.join(keys)}")
            out[section][key] = keys[key][1](f"{section}.{key}", value)
    _check_estimator_params(out["estimator"])
    if (out["location"]["latitude_deg"] is None) != (out["location"]["longitude_deg"] is None):
        raise ConfigError("location: give both latitude_deg and longitude_deg, or neither")
    _check_source(out["source"])
    return Config(out)


def load(path: str | Path | None, overrides: dict[str, dict[str, Any]] | None = None) -> Config:
    """Reads and validates a TOML file; None gives the embedded default.

    ``overrides`` ({section: {key: value}}, e.g. from command-line options) replace the file's
    values and are validated with them; the Config keeps them so that a reload applies them again.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        try:
            with path.open("rb") as f:
                data = tomllib.load(f)
        except FileNotFoundError:
            raise ConfigError(f"configuration file {path} does not exist") from None
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    for section, values in (overrides or {}).items():
        data[section] = {**data.get(section, {}), **values}
    cfg = validate(data)
    cfg.path = path
    cfg.overrides = overrides
    return cfg


def _check_estimator_params(section: dict[str, Any]) -> None:
    from ahrs_service import estimators

    try:
        estimators.create(section["name"], **section["params"])
    except ValueError as exc:
        raise ConfigError(f"estimator.params: {exc}") from None


def _check_source(section: dict[str, Any]) -> None:
    from ahrs_service.drivers.boards import TRANSPORT_BOARDS, buses_of

    bus = section["type"].removeprefix("simulated_")
    if bus in ("i2c", "spi") and bus not in buses_of(section["board"]):
        raise ConfigError(f"source.board: {section['board']!r} cannot be wired on {bus}; "
                          f"it supports {', '.join(buses_of(section['board']))}")
    if section["drdy_gpio"]:
        from ahrs_service.drivers.gpio.drdy import parse_line_spec

        if section["board"] not in TRANSPORT_BOARDS or not TRANSPORT_BOARDS[section["board"]][0].HAS_WATERMARK_LINE:
            raise ConfigError(f"source.drdy_gpio: board {section['board']!r} has no FIFO watermark "
                              f"line; leave drdy_gpio empty (timer polling)")
        try:
            parse_line_spec(section["drdy_gpio"])
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    if section["board"] in TRANSPORT_BOARDS and bus in ("i2c", "spi"):
        _check_fifo_board(section, bus)
    elif section["board_options"] and section["type"] in ("i2c", "simulated_i2c"):
        from ahrs_service.drivers.i2c.boards import board_class

        try:
            board_class(section["board"], dict(section["board_options"]))
        except ValueError as exc:
            raise ConfigError(f"source.board_options: {exc}") from None
    if section["type"] == "recorded" and not section["recorded_path"]:
        raise ConfigError("source.recorded_path: required when source.type = 'recorded' (an .mcap log or a BROAD .hdf5 file)")


def _check_fifo_board(section: dict[str, Any], bus: str) -> None:
    """Options and the bus-rate check of a FIFO board, on a simulated bus of the configured clock."""
    from ahrs_service.drivers.boards import make_transport_board
    from ahrs_service.drivers.sim.clock import ManualClock

    class _Quiet:  # a simulated part that only has to exist for the checks
        clock = ManualClock()

        @staticmethod
        def physics(t: float) -> dict:
            return {"gyr": (0.0, 0.0, 0.0), "acc": (0.0, 0.0, 0.0), "mag": (0.0, 0.0, 0.0)}

    try:
        real = not section["type"].startswith("simulated")
        name = (f"/dev/spidev{section['spi_bus']}" if bus == "spi" else f"/dev/i2c-{section['i2c_bus']}")
        make_transport_board(section["board"], bus, simulated_imu=_Quiet(), sim_bus_name=name if real else None,
                             spi_bus=section["spi_bus"], spi_device=section["spi_device"],
                             spi_speed_hz=section["spi_speed_hz"],
                             i2c_speed_hz=section["i2c_speed_hz"], **dict(section["board_options"]))
    except ValueError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith("source.") else f"source.board_options: {msg}") from None
    except TypeError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None


def _check_calibration(given: dict[str, Any]) -> dict[str, Any]:
    from ahrs_service.drivers.calibration import SensorCalibration

    try:
        SensorCalibration.from_dict(given)
    except ValueError as exc:
        raise ConfigError(f"calibration.{exc}" if not str(exc).startswith("calibration") else str(exc)) from None
    return dict(given)


def to_toml(cfg: dict[str, dict[str, Any]]) -> str:
    """A TOML rendering of a configuration dict (for --print-default and saving calibration)."""
    lines: list[str] = []
    for section, keys in cfg.items():
        nested = {k: v for k, v in keys.items() if isinstance(v, dict)}
        lines.append(f"[{section}]")
        for k, v in keys.items():
            if v is None:
                lines.append(f"# {k} = (not set)")
            elif not isinstance(v, dict):
                lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")
        for k, v in nested.items():
            lines.append(f"[{section}.{k}]")
            lines.extend(f"{kk} = {_toml_value(vv)}" for kk, vv in v.items())
            lines.append("")
    return "\n".join(lines)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if hasattr(v, "tolist"):
        return _toml_value(v.tolist())
    return repr(v)
