"""Service configuration: TOML file → validated, typed settings with the embedded defaults.

Every key has a default (the embedded default runs a simulated GY-80 flying the first paper's
validation manoeuvre, publishing over UDP to 127.0.0.1:14550 and logging to ./flight-logs).
A malformed file stops the start with a :class:`ConfigError` naming the key and what it
accepts. ``ahrs-service config --print-default`` prints the full default file.

One validation path: ``config --check``, ``run`` and a reload (SIGHUP) all go through
:func:`load` → :func:`validate`, so a file ``--check`` passes is one ``run`` starts with, and a
file a reload refuses leaves the running configuration as it was. Every error is one line:
``section.key: <value> ... <what is accepted>``.

Adding a key is one declaration in :data:`SCHEMA`: ``"name": (default, checker)`` in its
section, the checker built from the factories below (they never let NaN or ±inf through):

* ``_number(lo, hi)`` / ``_number(lo, hi, integer=True)`` — a finite number (int or float;
  bool refused) in [lo, hi] (``None`` = unbounded on that side);
* ``_stream_rate(hi)`` — a MAVLink stream rate: 0 (off) or [0.01, hi] Hz (``lo=``: another floor);
* ``_choice(("a", "b"))``, ``_string``, ``_boolean``, ``_string_list``, ``_table``;
* ``_subtable(KEYS)`` — a sub-table ``[section.key]`` whose own keys are declared like a
  section's (``{"name": (default, checker)}``), e.g. ``mavlink.odometry``;
* ``_optional(checker)`` — the key may be unset (default ``None``);
* ``_endpoints`` — a non-empty list of distinct MAVLink connection strings, each parsed
  (scheme, host, port 1..65535 or a serial device and baud);
* ``_path(must_exist=True)`` — a string naming a path; checked against the file system only when
  a rule in :func:`_check_source` (or your own cross-key check) needs it.

Cross-key rules (board options against the board, a path required by ``source.type``) go in
:func:`_check_source` or a ``_check_*`` function called from :func:`validate`; raise
:class:`ConfigError` with the key's dotted name first. ``tests/test_config.py`` feeds every key
NaN, ±inf, wrong types and out-of-range values: a new key is covered without a new test.
"""

from __future__ import annotations

import copy
import inspect
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

SOURCE_TYPES = ("simulated_i2c", "simulated_spi", "simulated_can", "simulated", "i2c", "spi", "can", "recorded",
                "mavlink")
#: source.mavlink_imu: the autopilot's IMU message (drivers/mavlink_imu.py, IMU_MESSAGES)
MAVLINK_IMUS = ("highres", "scaled", "scaled2", "scaled3", "raw")
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
        kind = "an integer" if integer else "a number"
        accepted = f"{kind} in [{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
        if isinstance(v, bool) or not ok_type:
            raise ConfigError(f"{key}: {v!r} is not {kind}; accepted: {accepted}")
        if not math.isfinite(v):
            raise ConfigError(f"{key}: {v!r} is not a finite number; accepted: {accepted}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ConfigError(f"{key}: {v!r} is out of range; accepted: {accepted}")
        return int(v) if integer else float(v)

    return check


MIN_STREAM_HZ = 0.01  # protocols.mavlink.component.MIN_RATE_HZ: an interval MESSAGE_INTERVAL can carry


def _stream_rate(hi: float, lo: float = MIN_STREAM_HZ) -> Checker:
    """A MAVLink stream rate, Hz: 0 (off) or [lo, hi]."""
    number = _number(0.0, hi)

    def check(key: str, v: Any) -> float:
        v = number(key, v)
        if 0.0 < v < lo:
            raise ConfigError(f"{key}: {v!r} is too slow; accepted: 0 (off) or a number in [{lo}, {hi}]")
        return v

    return check


def _choice(options: tuple[str, ...]) -> Checker:
    def check(key: str, v: Any) -> Any:
        if not isinstance(v, str) or v not in options:
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


def _path(must_exist: bool = False) -> Checker:
    """A path string; with ``must_exist`` an empty string is allowed (unset) but a given path must
    exist (cross-key rules decide when an empty one is an error)."""
    def check(key: str, v: Any) -> str:
        v = _string(key, v)
        if "\x00" in v:
            raise ConfigError(f"{key}: {v!r} contains a NUL character; accepted: a file path")
        if must_exist and v and not Path(v).exists():
            raise ConfigError(f"{key}: {v!r} does not exist; accepted: an existing file")
        return v

    return check


def _directory(key: str, v: Any) -> str:
    """A folder to write into: a non-empty path (made if missing; one that cannot be written
    is the writer's to report and retry at run time, the service runs on meanwhile)."""
    v = _path()(key, v)
    if not v.strip():
        raise ConfigError(f"{key}: {v!r} is empty; accepted: a folder path (e.g. \"flight-logs\")")
    return v


_ENDPOINT_HELP = ("udpout:HOST:PORT, udpin:HOST:PORT, udp:HOST:PORT, udpbcast:HOST:PORT, tcp:HOST:PORT, "
                  "tcpin:HOST:PORT (PORT 1..65535) or a serial device by absolute path /dev/NAME[,BAUD]")


def _endpoint(key: str, v: Any) -> str:
    """One pymavlink connection string, parsed the way mavutil will open it."""
    if not isinstance(v, str) or not v.strip():
        raise ConfigError(f"{key}: {v!r} is not a connection string; accepted: {_ENDPOINT_HELP}")
    scheme, sep, rest = v.partition(":")
    if sep and scheme in ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin"):
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ConfigError(f"{key}: {v!r} has no valid HOST:PORT; accepted: {_ENDPOINT_HELP}")
        return v
    # an absolute path: /dev/ttyAMA0, a udev link /dev/serial/by-id/..., a pty link elsewhere
    if v.startswith("/") or v.upper().startswith("COM"):
        device, sep, baud = v.partition(",")
        if sep and (not baud.isdigit() or not 50 <= int(baud) <= 20_000_000):
            raise ConfigError(f"{key}: {v!r} has baud {baud!r}; accepted: {_ENDPOINT_HELP}")
        return v
    raise ConfigError(f"{key}: {v!r} is not a connection string; accepted: {_ENDPOINT_HELP}")


def _endpoints(key: str, v: Any) -> list[str]:
    """A non-empty list of distinct connection strings (two links on one port fight over it)."""
    if not isinstance(v, list):
        raise ConfigError(f"{key}: {v!r} is not a list; accepted: a non-empty list of {_ENDPOINT_HELP}")
    if not v:
        raise ConfigError(f"{key}: [] is empty; accepted: a non-empty list of {_ENDPOINT_HELP}")
    out = [_endpoint(f"{key}[{i}]", x) for i, x in enumerate(v)]
    seen: dict[Any, str] = {}
    for x in out:
        if x in seen.values():
            raise ConfigError(f"{key}: {x!r} is listed twice; accepted: distinct endpoints")
        port = _listening_port(x)
        if port is not None and port in seen:
            raise ConfigError(f"{key}: {x!r} listens on the same port as {seen[port]!r}; accepted: "
                              f"one listening endpoint per port")
        seen[port if port is not None else x] = x
    return out


def check_endpoint_hosts(cfg: "Config") -> list[str]:
    """``config --check``'s look at the hosts of ``mavlink.endpoints`` now (a DNS lookup:
    never done by :func:`validate`, which ``run`` and reloads use). A listening endpoint
    (``udpin``, ``udp``, ``tcpin``) whose host does not resolve, or is not an address of this
    computer, is a :class:`ConfigError`: ``run`` cannot bind it either. A destination
    (``udpout``, ``udpbcast``, ``tcp``) that does not resolve *now* is a warning, returned as
    one line each: a companion may start before DNS is up; ``run`` then resolves a
    ``udpout``/``udpbcast`` name off the loop and retries (docs/mavlink.md, "Connection
    strings"), while ``tcp`` connects once at start. A
    serial device that does not exist now is a warning too (``run`` opens it once at start).
    The autopilot link (``source.mavlink_connection``, with ``source.type = "mavlink"``) is
    looked at the same way."""
    from ahrs_service.protocols.mavlink.endpoints import destination_host, is_numeric, resolve

    warnings = []
    links = [(f"mavlink.endpoints[{i}]", url) for i, url in enumerate(cfg.mavlink["endpoints"])]
    if cfg.source["type"] == "mavlink":
        links.append(("source.mavlink_connection", cfg.source["mavlink_connection"]))
    for key, url in links:
        scheme, _, rest = url.partition(":")
        device = url.partition(",")[0]
        if device.startswith("/") and not Path(device).exists():
            # a USB adapter udev has not named yet at boot: like a name DNS does not know yet
            warnings.append(f"{key}: {url!r}: serial device {device} does not exist now; run opens it once at "
                            f"start and exits with an error while it is missing")
            continue
        dest = destination_host(url)
        host = dest[0] if dest is not None else (rest.rpartition(":")[0] if scheme in ("udpin", "udp", "tcpin") else "")
        if not host:
            continue
        try:
            address = host if is_numeric(host) else resolve(host)
            if dest is None:  # a listening endpoint: an address this computer has
                _check_local_address(key, url, address)
        except OSError as exc:
            why = getattr(exc, "strerror", None) or str(exc)
            if dest is None:
                raise ConfigError(f"{key}: {url!r}: host {host!r} does not resolve ({why}); accepted: a local "
                                  f"address to listen on (0.0.0.0, 127.0.0.1, this computer's name)") from None
            then = ("run starts anyway, retries resolving it and sends nothing to it meanwhile" if scheme != "tcp"
                    else "run connects once at start and exits with an error while it does not resolve")
            warnings.append(f"{key}: {url!r}: host {host!r} does not resolve now ({why}); {then}")
    return warnings


def _check_local_address(key: str, url: str, address: str) -> None:
    """A listening endpoint's address must be one this computer has: a bind to it (on a port
    the system picks, closed at once) that fails with EADDRNOTAVAIL is what ``run`` meets."""
    import errno
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((address, 0))
        except OSError as exc:
            if exc.errno != errno.EADDRNOTAVAIL:
                return  # not the address's fault: run reports what it meets
            raise ConfigError(f"{key}: {url!r}: {address} is not an address of this computer ({exc.strerror}); "
                              f"accepted: a local address to listen on (0.0.0.0, 127.0.0.1, this computer's "
                              f"name)") from None


def _check_listening_ports(source: dict[str, Any], endpoints: list[str]) -> None:
    """The autopilot link (``source.mavlink_connection``, ``source.type = "mavlink"``) and the
    ground links must not listen on one port: both sockets bind it (SO_REUSEADDR) and each gets
    part of the datagrams, so the IMU stream or the ground station's messages go missing."""
    if source["type"] != "mavlink":
        return
    connection = source["mavlink_connection"]
    port = _listening_port(connection)
    for i, url in enumerate(endpoints):
        if port is not None and _listening_port(url) == port:
            raise ConfigError(f"source.mavlink_connection: {connection!r} listens on the same port as "
                              f"mavlink.endpoints[{i}] {url!r}; accepted: one listening endpoint per port")


def _listening_port(endpoint: str) -> tuple[str, int] | None:
    """("udp", PORT) or ("tcp", PORT) for an endpoint that binds a local port (``udpin``, and
    ``udp``, which mavutil opens as udpin; ``tcpin``), whatever its host: two of them on one port
    share it with SO_REUSEADDR, and each gets part of the datagrams."""
    scheme, _, rest = endpoint.partition(":")
    proto = {"udpin": "udp", "udp": "udp", "tcpin": "tcp"}.get(scheme)
    return None if proto is None else (proto, int(rest.rpartition(":")[2]))


def _check_keys(prefix: str, keys: dict[str, tuple[Any, Checker]], given: dict[str, Any], out: dict[str, Any]) -> None:
    """Each key of ``given`` through its checker in ``keys`` into ``out`` (a section, or a
    sub-table of :func:`_subtable`); an unknown key names the accepted ones."""
    for key, value in given.items():
        if key not in keys:
            raise ConfigError(f"{prefix}.{key}: unknown key; accepted keys: {', '.join(keys)}")
        out[key] = keys[key][1](f"{prefix}.{key}", value)


def _defaults_of(keys: dict[str, tuple[Any, Checker]]) -> dict[str, Any]:
    return {k: copy.deepcopy(d) for k, (d, _) in keys.items()}


def _subtable(keys: dict[str, tuple[Any, Checker]]) -> Checker:
    """A sub-table (``[section.key]``) with keys of its own, declared like a section's."""
    def check(key: str, v: Any) -> dict:
        out = _defaults_of(keys)
        _check_keys(key, keys, _table(key, v), out)
        return out

    return check


#: [mavlink.odometry]: ODOMETRY out for an autopilot (protocols/mavlink/odometry.py, docs/autopilot.md)
ODOMETRY_RULES = ("px4", "ardupilot")
ODOMETRY = {
    "rate_hz": (0.0, _stream_rate(200.0, lo=1.0)),  # 0 (off) or 1..200 Hz
    "rules": ("px4", _choice(ODOMETRY_RULES)),  # which autopilot's handler the fields follow
}


def _finite_table(key: str, v: Any) -> dict:
    """A table whose numbers are all finite (estimator parameters, board options)."""
    v = _table(key, v)
    for k, x in v.items():
        if isinstance(x, float) and not math.isfinite(x):
            raise ConfigError(f"{key}.{k}: {x!r} is not a finite number")
    return v


def _vector3(lo: float, hi: float) -> Checker:
    """Three finite numbers, each in [lo, hi]."""
    number = _number(lo, hi)

    def check(key: str, v: Any) -> list[float]:
        if not isinstance(v, list) or len(v) != 3:
            raise ConfigError(f"{key}: {v!r} is not a list of 3 numbers; accepted: 3 numbers in [{lo}, {hi}]")
        return [number(f"{key}[{i}]", x) for i, x in enumerate(v)]

    return check


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
        "board_options": ({}, _finite_table),
        "profile": ("validation", _choice(PROFILES)),
        "loop_profile": (True, _boolean),
        "sensor_errors": (True, _boolean),
        # simulated sources: a sinusoidal vibration of the airframe, m/s² per body axis, at
        # vibration_hz (0: none): what VIBRATION measures (docs/simulator.md)
        "vibration_mss": ([0.0, 0.0, 0.0], _vector3(0.0, 1000.0)),
        "vibration_hz": (0.0, _number(0.0, 10_000.0)),
        "seed": (0, _number(0, None, integer=True)),
        "can_interface": ("virtual", _string),
        "can_channel": ("ahrs", _string),
        "can_bitrate": (1_000_000, _number(10_000, 8_000_000, integer=True)),
        "can_node_id": (0, _number(0, 127, integer=True)),
        "recorded_path": ("", _path(must_exist=True)),
        "recorded_realtime": (True, _boolean),
        # source.type = "mavlink": the autopilot's IMU over its link (docs/autopilot.md); the
        # same connection carries TIMESYNC, ODOMETRY and the attitude monitor
        "mavlink_connection": ("udpin:127.0.0.1:14540", _endpoint),
        "mavlink_imu": ("highres", _choice(MAVLINK_IMUS)),
        "mavlink_imu_hz": (200.0, _number(1.0, 2000.0)),
        # RAW_IMU counts -> m/s2, rad/s, uT per count; unset keys: ArduPilot's (mG, mrad/s, mgauss)
        "mavlink_raw_scale": ({}, _finite_table),
    },
    "estimator": {
        "name": ("robust", _estimator_name),
        "params": ({}, _finite_table),
        # "" = the tuned defaults; "paper" = the source paper's values; else a preset file
        # (ahrs-service tune): its values sit under estimator.params, which override them
        "preset": ("", _string),
        "mag_timeout_s": (0.5, _number(0.01, 60.0)),
        "declination_deg": (0.0, _number(-180.0, 180.0)),
    },
    "rates": {
        "estimation_hz": (200.0, _number(10.0, 2000.0)),
        "heartbeat_hz": (1.0, _stream_rate(10.0)),
        "attitude_hz": (50.0, _stream_rate(1000.0)),
        "attitude_quaternion_hz": (50.0, _stream_rate(1000.0)),
        "highres_imu_hz": (0.0, _stream_rate(1000.0)),
        "sys_status_hz": (1.0, _stream_rate(50.0)),
        "vibration_hz": (2.0, _stream_rate(50.0)),
    },
    "mounting": {
        "roll_deg": (0.0, _number(-180.0, 180.0)),
        "pitch_deg": (0.0, _number(-180.0, 180.0)),
        "yaw_deg": (0.0, _number(-180.0, 180.0)),
    },
    "calibration": {},  # free-form: validated by drivers.calibration.SensorCalibration.from_dict
    "mavlink": {
        "endpoints": (["udpout:127.0.0.1:14550"], _endpoints),
        "identity": ("standalone", _choice(IDENTITIES)),
        "system_id": (1, _number(1, 255, integer=True)),
        "signing_key": ("", _signing_key),
        "odometry": (_defaults_of(ODOMETRY), _subtable(ODOMETRY)),
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
        "directory": ("flight-logs", _directory),
        "rotate_mb": (0.0, _number(0.0, 1_000_000.0)),  # 0 = no size rotation; at most 1 TB
        "rotate_minutes": (0.0, _number(0.0, 525_600.0)),  # 0 = no time rotation; at most a year
        # the estimator's diagnostics (rest, rejections, form) in /attitude this often, Hz
        "diagnostics_hz": (10.0, _number(0.0, 1000.0)),
        # samples faster than this are logged one message per FIFO burst (/imu/raw_block,
        # /attitude_block) instead of one per sample, Hz; 0: always (docs/logs.md)
        "block_messages_above_hz": (1500.0, _number(0.0, 1_000_000.0)),
        # the simulator's ground truth (/attitude/truth) when the source has one: false logs
        # what a real sensor's log holds (raw + estimate)
        "truth": (True, _boolean),
    },
    # the autopilot's attitude against ours when an autopilot link is up (docs/autopilot.md)
    "monitor": {
        "enabled": (True, _boolean),
        "threshold_deg": (5.0, _number(0.1, 180.0)),
        "hold_s": (2.0, _number(0.0, 600.0)),
        "rate_hz": (5.0, _number(0.1, 50.0)),  # NAMED_VALUE_FLOAT of the disagreement, Hz
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
    return {sec: _defaults_of(keys) for sec, keys in SCHEMA.items()}


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
        _check_keys(section, keys, given, out[section])
    _check_estimator_params(out["estimator"])
    if (out["location"]["latitude_deg"] is None) != (out["location"]["longitude_deg"] is None):
        raise ConfigError("location: give both latitude_deg and longitude_deg, or neither")
    _check_source(out["source"])
    _check_listening_ports(out["source"], out["mavlink"]["endpoints"])
    return Config(out)


def load(path: str | Path | None, overrides: dict[str, dict[str, Any]] | None = None) -> Config:
    """Reads and validates a TOML file; None gives the embedded default.

    ``overrides`` ({section: {key: value}}, e.g. from command-line options) replace the file's
    values and are validated with them; the Config keeps them so that a reload applies them again.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        data = read_toml(path)
    for section, values in (overrides or {}).items():
        data[section] = {**data.get(section, {}), **values}
    cfg = validate(data)
    cfg.path = path
    cfg.overrides = overrides
    return cfg


def _short(value: str, limit: int = 80) -> str:
    """``repr(value)``, cut to about ``limit`` characters (a 5000-character path in an error)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 5]}…{text[-4:]} ({len(value)} characters)"


def _unreadable(exc: OSError) -> str:
    """What is wrong with a path that could not be read, as a phrase after its name."""
    if isinstance(exc, FileNotFoundError):
        return "does not exist"
    if isinstance(exc, IsADirectoryError):
        return "is a directory, not a file"
    if isinstance(exc, PermissionError):
        return "is not readable: permission denied"
    return f"cannot be read: {exc.strerror or exc}"


def read_toml(path: Path) -> dict[str, Any]:
    """The parsed TOML document at ``path``; every way of not being readable is a one-line
    :class:`ConfigError` (missing, a directory, a FIFO or device, no permission, not UTF-8,
    not TOML): a FIFO would block a reload, and with it the service's loop."""
    from ahrs_service.paths import regular_file

    try:
        text = regular_file(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"configuration file {path}: not UTF-8 text (byte {exc.start}: "
                          f"{exc.object[exc.start:exc.start + 1]!r}); TOML files are UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"configuration file {path} {_unreadable(exc)}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


def _check_estimator_params(section: dict[str, Any]) -> None:
    from ahrs_service import estimators
    from ahrs_service.estimators.presets import has_paper_preset, load_preset

    try:
        # the values a parameter's range is taken from (_check_param_ranges)
        references = [estimators.create(section["name"]).get_params()]
        if has_paper_preset(estimators.get(section["name"]).Params):
            references.append(load_preset(section["name"], "paper"))
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(f"estimator.params: {exc}") from None
    if section["preset"]:
        try:
            preset = load_preset(section["name"], section["preset"])
            estimators.create(section["name"], **preset)
        except (ValueError, TypeError, OverflowError) as exc:
            raise ConfigError(f"estimator.preset: {exc}") from None
        except OSError as exc:  # a name too long for the file system, a folder not searchable …
            raise ConfigError(f"estimator.preset: {_short(section['preset'])} cannot be read: "
                              f"{exc.strerror or exc}; accepted: 'paper' or a preset file") from None
        references.append(preset)
        # what runs is the preset with the table's own values over it (service, reload, live)
        section["params"] = {**preset, **section["params"]}
    try:
        estimators.create(section["name"], **section["params"])
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(f"estimator.params: {exc}") from None
    _check_param_ranges(section["params"], references)


def _check_param_ranges(params: dict[str, Any], references: list[dict[str, Any]],
                        label: str = "estimator.params.{}") -> None:
    """Each numeric value within ``CONFIG_RANGE_FACTOR`` of its reference: the largest of its
    default, its paper value (a paper's 1e9 for "gate off") and its preset's, with mavlink_bridge's
    bounds. A finite 1e300 passes the estimator's own checks and overflows inside it. ``label``
    names a parameter in the error (``"--param {}"`` on the command line)."""
    from ahrs_service.mavlink_bridge import CONFIG_RANGE_FACTOR, estimator_param_bounds

    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    for name, value in params.items():
        refs = [r[name] for r in references if number(r.get(name))]
        if not number(value) or not refs:
            continue
        reference = max(refs, key=abs)
        lo, hi = estimator_param_bounds(float(reference), CONFIG_RANGE_FACTOR)
        if not lo <= value <= hi:
            raise ConfigError(f"{label.format(name)} = {value!r}: must be within {lo:g} … {hi:g} "
                              f"({CONFIG_RANGE_FACTOR:g} × its default {reference:g})")


def check_estimator_params(name: str, params: dict[str, Any], label: str = "--param {}") -> None:
    """The configuration file's check of ``estimator.params`` for parameters given elsewhere
    (``replay --param``, ``evaluate --param``): each a parameter of estimator ``name``, accepted
    by its ``Params`` and within the same ranges as in the file (``_check_param_ranges``).
    Raises :class:`ConfigError` naming the parameter with ``label``."""
    from ahrs_service import estimators
    from ahrs_service.estimators.presets import has_paper_preset, load_preset

    try:
        references = [estimators.create(name).get_params()]
        if has_paper_preset(estimators.get(name).Params):
            references.append(load_preset(name, "paper"))
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(str(exc)) from None  # an unknown estimator: its own message names it
    try:  # its own checks first (finite, positive …), then the ranges, as for the file
        estimators.create(name, **params)
    except (ValueError, TypeError, OverflowError) as exc:
        raise ConfigError(str(exc)) from None  # Params' own message names the parameter
    _check_param_ranges(params, references, label)


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
        _check_board_options(section["board"], dict(section["board_options"]), section["i2c_speed_hz"])
    if section["mavlink_raw_scale"]:
        from ahrs_service.drivers.mavlink_imu import parse_raw_scale

        try:
            parse_raw_scale(section["mavlink_raw_scale"])
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    if section["type"] == "recorded":
        _check_recorded_path(section["recorded_path"])
    if section["type"] in ("can", "simulated_can"):
        _check_can_interface(section["can_interface"])


#: the first bytes of an MCAP file (logs/recover.py's MAGIC) and of an HDF5 file at offset 0
_MCAP_MAGIC = b"\x89MCAP0\r\n"
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_RECORDED_HELP = "accepted: an .mcap flight log or a BROAD .hdf5 file"


def _check_recorded_path(path: str) -> None:
    """``source.recorded_path`` for ``source.type = "recorded"``: a readable regular file that
    starts like the format its suffix names (MCAP magic; HDF5 signature for .hdf5/.h5), so a
    directory or a file that is no log is refused here, not at start or by a run that plays
    nothing and exits 0."""
    key = "source.recorded_path"
    if not path:
        raise ConfigError(f"{key}: required when source.type = 'recorded'; {_RECORDED_HELP}")
    p = Path(path)
    hdf5 = p.suffix.lower() in (".hdf5", ".h5")
    from ahrs_service.paths import regular_file

    try:
        with regular_file(p).open("rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise ConfigError(f"{key}: {path!r} {_unreadable(exc)}; {_RECORDED_HELP}") from None
    if not p.is_file():
        raise ConfigError(f"{key}: {path!r} is not a regular file; {_RECORDED_HELP}")
    if hdf5 and not _has_hdf5_signature(p, head):
        raise ConfigError(f"{key}: {path!r} is not an HDF5 file (no HDF5 signature); {_RECORDED_HELP}")
    if not hdf5 and head != _MCAP_MAGIC:
        raise ConfigError(f"{key}: {path!r} is not an MCAP log (bad magic); {_RECORDED_HELP}")


def _has_hdf5_signature(path: Path, head: bytes) -> bool:
    """The HDF5 signature at offset 0 (``head``) or after a user block (512, 1024, 2048 … bytes)."""
    if head == _HDF5_MAGIC:
        return True
    size = path.stat().st_size
    with path.open("rb") as f:
        offset = 512
        while offset + 8 <= size:
            f.seek(offset)
            if f.read(8) == _HDF5_MAGIC:
                return True
            offset *= 2
    return False


def _check_can_interface(name: str) -> None:
    """``source.can_interface``: one of python-can's interface names (what ``can.Bus`` opens)."""
    from can.interfaces import VALID_INTERFACES

    if name not in VALID_INTERFACES:
        raise ConfigError(f"source.can_interface: {name!r} is not a python-can interface; accepted: "
                          f"{', '.join(sorted(VALID_INTERFACES))}")


def _option_kind(param: inspect.Parameter) -> str | None:
    """"an integer" or "a number" for a board option whose signature says so (its annotation,
    ``int | None`` included, else the type of its default); None for any other option."""
    annotation = param.annotation
    if isinstance(annotation, str):
        annotation = annotation.replace(" ", "").removesuffix("|None").removeprefix("None|")
    if annotation in (int, "int"):
        return "an integer"
    if annotation in (float, "float"):
        return "a number"
    default = param.default
    if isinstance(default, (int, float)) and not isinstance(default, bool):
        return "an integer" if isinstance(default, int) else "a number"
    return None


def _check_option_types(board: str, options: dict[str, Any], inits: tuple[Callable, ...]) -> None:
    """Each option's type against the board constructors' signatures (``inits``, later ones
    first): ``source.board_options.NAME: VALUE is not a number`` before any driver divides by it.
    Unknown names are left to the board's own check, which lists the valid ones."""
    params: dict[str, inspect.Parameter] = {}
    for init in inits:
        params.update(inspect.signature(init).parameters)
    for name, value in options.items():
        kind = _option_kind(params[name]) if name in params else None
        if kind is None:
            continue
        integer = kind == "an integer"
        if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
            raise ConfigError(f"source.board_options.{name}: {value!r} is not {kind} (board {board!r})")


def _check_board_options(board: str, options: dict[str, Any], i2c_speed_hz: float = 400_000) -> None:
    """Each option's type against the board's signature, then its value by building the board's
    drivers (on no bus: their constructors only check and store), so that a range or rate the
    part does not have is refused here rather than at start."""
    from ahrs_service.drivers.i2c.boards import I2CBoard, board_class

    try:
        cls = board_class(board, options)
    except ValueError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None
    _check_option_types(board, options, (I2CBoard.__init__, cls.__init__))
    try:
        cls(None, i2c_speed_hz=i2c_speed_hz, **options)  # type: ignore[arg-type]
    except (ValueError, TypeError, OverflowError) as exc:
        msg = str(exc)  # the rate checks name their key already (odr_hz, acc_rate_hz …)
        raise ConfigError(msg if msg.startswith("source.") else f"source.board_options = {options!r}: {msg}") from None


def _check_fifo_board(section: dict[str, Any], bus: str) -> None:
    """Options and the bus-rate check of a FIFO board, on a simulated bus of the configured clock."""
    from ahrs_service.drivers.boards import make_transport_board
    from ahrs_service.drivers.sim.clock import ManualClock

    class _Quiet:  # a simulated part that only has to exist for the checks
        clock = ManualClock()

        @staticmethod
        def physics(t: float) -> dict:
            return {"gyr": (0.0, 0.0, 0.0), "acc": (0.0, 0.0, 0.0), "mag": (0.0, 0.0, 0.0)}

    from ahrs_service.drivers.boards import transport_board_class
    from ahrs_service.drivers.imu.boards import FifoBoard

    options = dict(section["board_options"])
    try:
        cls = transport_board_class(section["board"], options)
    except ValueError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None
    _check_option_types(section["board"], options, (FifoBoard.__init__, cls.__init__))
    cs = options.get("gyro_spi_device")  # bmi088's second chip select: an integer, like spi_device
    if cs is not None and (isinstance(cs, bool) or not isinstance(cs, int)):
        raise ConfigError(f"source.board_options.gyro_spi_device: {cs!r} is not an integer (board {section['board']!r})")
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


#: the largest magnitude of each [calibration] value that a real sensor's calibration can
#: have (the terms are offsets of a few units and near-identity matrices); beyond it a value is
#: a typo, and a finite but absurd one (1e300 rad/s of gyro bias) would overflow the estimate
CALIBRATION_LIMITS = {
    "gyro_bias": 10.0,  # rad/s (a gyro off by ~570 °/s is broken, not biased)
    "acc_bias": 50.0,  # m/s²
    "acc_scale": 10.0,  # each matrix element
    "mag_hard_iron": 5000.0,  # µT (the earth field is 25–65 µT; a nearby magnet may add hundreds)
    "mag_soft_iron": 100.0,  # each matrix element
    "mounting": 1.0,  # each element of a rotation matrix
    "mounting_rpy_deg": 360.0,  # each angle, degrees
}


def _check_calibration(given: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from ahrs_service.drivers.calibration import SensorCalibration

    for key, value in given.items():  # before from_dict: its matrix checks would overflow on 1e300
        limit = CALIBRATION_LIMITS.get(key)
        try:
            values = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            continue  # not numbers: from_dict names the key and the shape it wants
        if limit is not None and values.size and np.isfinite(values).all() and np.abs(values).max() > limit * (1 + 1e-9):
            raise ConfigError(f"calibration.{key}: {value!r} is out of range; accepted: each value within "
                              f"±{limit:g} (calibration key {key!r})")
    try:
        SensorCalibration.from_dict(given)
    except ValueError as exc:
        raise ConfigError(str(exc) if str(exc).startswith("calibration") else f"calibration: {exc}") from None
    return dict(given)


def to_toml(cfg: dict[str, dict[str, Any]]) -> str:
    """A TOML rendering of a configuration dict (``run --print-default``, ``calibrate``'s
    printout): :func:`ahrs_service.config_file.render`."""
    from ahrs_service.config_file import render  # config_file imports this module

    return render(cfg)
