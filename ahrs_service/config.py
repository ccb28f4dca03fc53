"""Service configuration: TOML file → validated, typed settings with the embedded defaults.

Every key has a default (the embedded default runs a simulated GY-80 flying the first paper's
validation manoeuvre, publishing over UDP to 127.0.0.1:14550 and logging to ./flight-logs).
A malformed file stops the start with a :class:`ConfigError` naming the key and what it
accepts. ``ahrs-service config --print-default`` prints the full default file.

One validation path: ``config --check``, ``run`` and a reload (SIGHUP) all go through
:func:`load` → :func:`validate`, so a file ``--check`` passes is one ``run`` starts with, and a
file a reload refuses leaves the running configuration as it was. Every error is one line:
``section.key: <value> ... <what is accepted>``.

The configuration is composed from the sections its owners declare (:data:`SCHEMA`), each
beside the code that reads it:

==================  ==========================================================================
``[source]``        :mod:`ahrs_service.source_settings` (beside the wiring, ``sources.py``)
``[estimator]``     :mod:`ahrs_service.estimators.settings`
``[rates]``         the stream rates from :mod:`ahrs_service.protocols.mavlink.settings`; the
                    loop's ``estimation_hz`` here (:data:`LOOP_RATE`)
``[mounting]``,     :mod:`ahrs_service.core.calibration`
``[calibration]``
``[mavlink]``       :mod:`ahrs_service.protocols.mavlink.settings`
``[location]``      :mod:`ahrs_service.calibration.declination`
``[log]``           :mod:`ahrs_service.logs.settings`
``[monitor]``       :mod:`ahrs_service.attitude_monitor`
``[divergence]``    :mod:`ahrs_service.core.divergence`
``[live]``          :mod:`ahrs_service.live_settings`
==================  ==========================================================================

Adding a key is one declaration in its owner's section, ``"name": (default, checker)``, the
checker built from the factories of :mod:`ahrs_service.core.settings` (``number``,
``choice``, ``string``, ``boolean``, ``optional``, ``file_path``, ``subtable`` …; they never
let NaN or ±inf through) or its owner's own (``stream_rate``, ``endpoint`` of the MAVLink
settings).

Rules across the keys of one section (board options against the board, a path required by
``source.type``) are the owner's too, in its ``check_*_section`` function, listed in
:data:`SECTION_CHECKS`; only a rule that reads several owners' sections is stated here. Raise
:class:`ConfigError` with the key's dotted name first. ``tests/test_config.py`` feeds every key
NaN, ±inf, wrong types and out-of-range values: a new key is covered without a new test.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ahrs_service import _moved
from ahrs_service.attitude_monitor import MONITOR
from ahrs_service.calibration.declination import LOCATION, check_location_section

# declared here before their owners took them over; still importable from here
from ahrs_service.core.calibration import (
    CALIBRATION,
    CALIBRATION_LIMITS,  # noqa: F401
    MOUNTING,
    check_calibration_section,
)
from ahrs_service.core.divergence import DIVERGENCE
from ahrs_service.core.paths import regular_file
from ahrs_service.core.settings import ConfigError, Section, check_keys, defaults_of, number, render, unreadable
from ahrs_service.estimators.settings import ESTIMATOR, check_estimator_params, check_estimator_section
from ahrs_service.live_settings import LIVE, check_live_section
from ahrs_service.logs.redaction import redact_text, secret_values
from ahrs_service.logs.settings import LOG
from ahrs_service.protocols.mavlink.settings import (MAVLINK, STREAM_RATES, check_link_hosts, check_mavlink_section,
                                                    listening_port)
from ahrs_service.realtime import SERVICE
from ahrs_service.source_settings import BOARDS, MAVLINK_IMUS, PROFILES, SOURCE, SOURCE_TYPES, check_source_section  # noqa: F401

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["SCHEMA", "Config", "ConfigError", "check_endpoint_hosts", "check_estimator_params", "defaults", "load",
           "read_toml", "to_toml", "validate"]

#: the loop's tick, Hz: the service's own key (it paces a polled source and the estimator's
#: nominal step); declared here because the service module imports this one
LOOP_RATE: Section = {"estimation_hz": (200.0, number(10.0, 2000.0))}

#: the configuration, composed from the sections its owners declare, in the order of
#: ``config --print-default``
SCHEMA: dict[str, Section] = {
    "source": SOURCE,
    "estimator": ESTIMATOR,
    "rates": {**LOOP_RATE, **STREAM_RATES},
    "mounting": MOUNTING,
    "calibration": CALIBRATION,
    "mavlink": MAVLINK,
    "location": LOCATION,
    "log": LOG,
    "monitor": MONITOR,
    "divergence": DIVERGENCE,
    "live": LIVE,
    "service": SERVICE,
}

#: sections whose keys are not declared one by one: the owner's check takes the whole table
#: as read and returns it checked
FREE_FORM_SECTIONS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {
    "calibration": check_calibration_section,
}

#: each owner's rules across the keys of its own section, run in this order once every key
#: has passed its checker
SECTION_CHECKS: dict[str, Callable[[dict[str, Any]], None]] = {
    "estimator": check_estimator_section,
    "location": check_location_section,
    "mavlink": check_mavlink_section,
    "source": check_source_section,
    "live": check_live_section,
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
    return {sec: defaults_of(keys) for sec, keys in SCHEMA.items()}


def validate(data: dict[str, Any]) -> Config:
    """Checks a parsed TOML document against the schema and fills in defaults. An error that
    quotes a secret the file holds (``mavlink.signing_key`` …) quotes ``"<redacted>"``: a
    refused reload goes to STATUSTEXT and the journal."""
    try:
        return _validate(data)
    except ConfigError as exc:
        secrets = secret_values(data)
        if not secrets:
            raise
        raise ConfigError(redact_text(str(exc), secrets)) from None


def _validate(data: dict[str, Any]) -> Config:
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
        if section in FREE_FORM_SECTIONS:
            out[section] = FREE_FORM_SECTIONS[section](given)
            continue
        check_keys(section, keys, given, out[section])
    for section, check in SECTION_CHECKS.items():
        check(out[section])
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


def read_toml(path: Path) -> dict[str, Any]:
    """The parsed TOML document at ``path``; every way of not being readable is a one-line
    :class:`ConfigError` (missing, a directory, a FIFO or device, no permission, not UTF-8,
    not TOML): a FIFO would block a reload, and with it the service's loop."""
    try:
        text = regular_file(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"configuration file {path}: not UTF-8 text (byte {exc.start}: "
                          f"{exc.object[exc.start:exc.start + 1]!r}); TOML files are UTF-8") from None
    except OSError as exc:
        raise ConfigError(f"configuration file {path} {unreadable(exc)}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None


# Cross-section checks: each reads the sections of two owners (the autopilot link is a
# [source] key, the ground links are [mavlink]'s), so neither owner can state it alone.


def check_endpoint_hosts(cfg: "Config") -> list[str]:
    """``config --check``'s look at the hosts of ``mavlink.endpoints`` now (a DNS lookup:
    never done by :func:`validate`, which ``run`` and reloads use): warnings, one line each,
    or a :class:`ConfigError` for a listening endpoint ``run`` cannot bind
    (:func:`ahrs_service.protocols.mavlink.settings.check_link_hosts`). The autopilot link
    (``source.mavlink_connection``, with ``source.type = "mavlink"``) is looked at the same way:
    [source] and [mavlink] together."""
    links = [(f"mavlink.endpoints[{i}]", url) for i, url in enumerate(cfg.mavlink["endpoints"])]
    if cfg.source["type"] == "mavlink":
        links.append(("source.mavlink_connection", cfg.source["mavlink_connection"]))
    return check_link_hosts(links)


def _check_listening_ports(source: dict[str, Any], endpoints: list[str]) -> None:
    """The autopilot link (``source.mavlink_connection``, ``source.type = "mavlink"``) and the
    ground links (``mavlink.endpoints``) must not listen on one port: both sockets bind it
    (SO_REUSEADDR) and each gets part of the datagrams, so the IMU stream or the ground
    station's messages go missing. [source] and [mavlink] together."""
    if source["type"] != "mavlink":
        return
    connection = source["mavlink_connection"]
    port = listening_port(connection)
    for i, url in enumerate(endpoints):
        if port is not None and listening_port(url) == port:
            raise ConfigError(f"source.mavlink_connection: {connection!r} listens on the same port as "
                              f"mavlink.endpoints[{i}] {url!r}; accepted: one listening endpoint per port")


def to_toml(cfg: dict[str, dict[str, Any]]) -> str:
    """A TOML rendering of a configuration dict (``run --print-default``, ``calibrate``'s
    printout): :func:`ahrs_service.core.settings.render`."""
    return render(cfg)


def __getattr__(name: str):  # names that moved out of this module keep working for one release
    return _moved.moved_name(__name__, name)
