"""The ``[mavlink]`` section of the configuration, and the checks of MAVLink connection strings.

Every connection string is parsed the way pymavlink's ``mavutil`` will open it (scheme, host,
port 1..65535, or a serial device and baud), so a typo stops the start with one line naming
the key. Looking the hosts up (DNS, the computer's own addresses) is separate:
:func:`check_link_hosts`, for ``config --check`` only, never for ``run`` or a reload.
"""

from __future__ import annotations

import errno
import socket
from pathlib import Path
from typing import Any, Sequence

from ahrs_service.core.settings import (
    Checker,
    ConfigError,
    Section,
    boolean,
    choice,
    defaults_of,
    number,
    rate_or_off,
    string,
    subtable,
)
from ahrs_service.protocols.mavlink import endpoints
from ahrs_service.protocols.mavlink.component import MIN_RATE_HZ
from ahrs_service.protocols.mavlink.identity import COMPANION, STANDALONE
from ahrs_service.protocols.mavlink.odometry import MAX_RATE_HZ as ODOMETRY_MAX_HZ
from ahrs_service.protocols.mavlink.odometry import MIN_RATE_HZ as ODOMETRY_MIN_HZ
from ahrs_service.protocols.mavlink.odometry import RULES

IDENTITIES = (STANDALONE, COMPANION)
#: [mavlink.odometry] rules: the autopilots whose ODOMETRY handler the fields can follow
ODOMETRY_RULE_NAMES = tuple(RULES)


def stream_rate(hi: float, lo: float = MIN_RATE_HZ) -> Checker:
    """A MAVLink stream rate, Hz: 0 (off) or [lo, hi]; the floor is the slowest interval
    MESSAGE_INTERVAL can carry unless ``lo`` says otherwise."""
    return rate_or_off(hi, lo)


ENDPOINT_HELP = ("udpout:HOST:PORT, udpin:HOST:PORT, udp:HOST:PORT, udpbcast:HOST:PORT, tcp:HOST:PORT, "
                 "tcpin:HOST:PORT (PORT 1..65535) or a serial device by absolute path /dev/NAME[,BAUD]")


def endpoint(key: str, v: Any) -> str:
    """One pymavlink connection string, parsed the way mavutil will open it."""
    if not isinstance(v, str) or not v.strip():
        raise ConfigError(f"{key}: {v!r} is not a connection string; accepted: {ENDPOINT_HELP}")
    scheme, sep, rest = v.partition(":")
    if sep and scheme in ("udp", "udpin", "udpout", "udpbcast", "tcp", "tcpin"):
        host, sep, port = rest.rpartition(":")
        if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
            raise ConfigError(f"{key}: {v!r} has no valid HOST:PORT; accepted: {ENDPOINT_HELP}")
        return v
    # an absolute path: /dev/ttyAMA0, a udev link /dev/serial/by-id/..., a pty link elsewhere
    if v.startswith("/") or v.upper().startswith("COM"):
        device, sep, baud = v.partition(",")
        if sep and (not baud.isdigit() or not 50 <= int(baud) <= 20_000_000):
            raise ConfigError(f"{key}: {v!r} has baud {baud!r}; accepted: {ENDPOINT_HELP}")
        return v
    raise ConfigError(f"{key}: {v!r} is not a connection string; accepted: {ENDPOINT_HELP}")


def endpoint_list(key: str, v: Any) -> list[str]:
    """A non-empty list of distinct connection strings (two links on one port fight over it)."""
    if not isinstance(v, list):
        raise ConfigError(f"{key}: {v!r} is not a list; accepted: a non-empty list of {ENDPOINT_HELP}")
    if not v:
        raise ConfigError(f"{key}: [] is empty; accepted: a non-empty list of {ENDPOINT_HELP}")
    out = [endpoint(f"{key}[{i}]", x) for i, x in enumerate(v)]
    seen: dict[Any, str] = {}
    for x in out:
        if x in seen.values():
            raise ConfigError(f"{key}: {x!r} is listed twice; accepted: distinct endpoints")
        port = listening_port(x)
        if port is not None and port in seen:
            raise ConfigError(f"{key}: {x!r} listens on the same port as {seen[port]!r}; accepted: "
                              f"one listening endpoint per port")
        seen[port if port is not None else x] = x
    return out


def listening_port(url: str) -> tuple[str, int] | None:
    """("udp", PORT) or ("tcp", PORT) for an endpoint that binds a local port (``udpin``, and
    ``udp``, which mavutil opens as udpin; ``tcpin``), whatever its host: two of them on one port
    share it with SO_REUSEADDR, and each gets part of the datagrams."""
    scheme, _, rest = url.partition(":")
    proto = {"udpin": "udp", "udp": "udp", "tcpin": "tcp"}.get(scheme)
    return None if proto is None else (proto, int(rest.rpartition(":")[2]))


def signing_key(key: str, v: Any) -> str:
    """"" (no signing) or a 32-byte key as 64 hexadecimal digits."""
    v = string(key, v)
    if v:
        try:
            raw = bytes.fromhex(v)
        except ValueError:
            raise ConfigError(f"{key}: expected 64 hexadecimal digits (a 32-byte key), got {v!r}") from None
        if len(raw) != 32:
            raise ConfigError(f"{key}: expected 64 hexadecimal digits (a 32-byte key), got {len(raw)} bytes")
    return v


#: [mavlink.odometry]: ODOMETRY out for an autopilot (odometry.py, docs/autopilot.md)
ODOMETRY: Section = {
    "rate_hz": (0.0, stream_rate(ODOMETRY_MAX_HZ, lo=ODOMETRY_MIN_HZ)),
    "rules": ("px4", choice(ODOMETRY_RULE_NAMES)),
    # ArduPilot's EKF source sets (ekf_source.py): with rules = "ardupilot" only; 0 = never asked
    "fallback_source_set": (2, number(0, 3, integer=True)),
    "primary_source_set": (1, number(0, 3, integer=True)),
}

#: the streams the component sends unasked, each at its ``[rates]`` key's rate until a ground
#: station's SET_MESSAGE_INTERVAL changes it: message name → key
RATE_CONFIG_KEYS = {
    "HEARTBEAT": "heartbeat_hz",
    "ATTITUDE": "attitude_hz",
    "ATTITUDE_QUATERNION": "attitude_quaternion_hz",
    "HIGHRES_IMU": "highres_imu_hz",
    "SYS_STATUS": "sys_status_hz",
    "VIBRATION": "vibration_hz",
}

#: the stream keys of the ``[rates]`` section (the section's loop rate is the service's own)
STREAM_RATES: Section = {
    "heartbeat_hz": (1.0, stream_rate(10.0)),
    "attitude_hz": (50.0, stream_rate(1000.0)),
    "attitude_quaternion_hz": (50.0, stream_rate(1000.0)),
    "highres_imu_hz": (0.0, stream_rate(1000.0)),
    "sys_status_hz": (1.0, stream_rate(50.0)),
    "vibration_hz": (2.0, stream_rate(50.0)),
}

MAVLINK: Section = {
    "endpoints": (["udpout:127.0.0.1:14550"], endpoint_list),
    "identity": (STANDALONE, choice(IDENTITIES)),
    "system_id": (1, number(1, 255, integer=True)),
    "signing_key": ("", signing_key),
    "require_signing_for_writes": (False, boolean),
    "odometry": (defaults_of(ODOMETRY), subtable(ODOMETRY)),
}


def check_mavlink_section(section: dict[str, Any]) -> None:
    """The checked ``[mavlink]`` section as a whole: requiring signed writes without a key
    would leave every write open, the opposite of what was asked; a fallback source set that
    is the primary one would switch nothing."""
    odometry = section["odometry"]
    fallback, primary = odometry["fallback_source_set"], odometry["primary_source_set"]
    if fallback and fallback == primary:
        raise ConfigError(f"mavlink.odometry.fallback_source_set: {fallback} is also primary_source_set; accepted: "
                          f"another set 1..3, or 0 (no fallback asked for)")
    if section["require_signing_for_writes"] and not section["signing_key"]:
        raise ConfigError("mavlink.require_signing_for_writes: true needs mavlink.signing_key (64 hexadecimal "
                          "digits, a 32-byte key); accepted: a signing key, or require_signing_for_writes = false")


def check_link_hosts(links: Sequence[tuple[str, str]]) -> list[str]:
    """``config --check``'s look at the hosts of ``links`` ((dotted key, connection string))
    now: a DNS lookup. A listening endpoint (``udpin``, ``udp``, ``tcpin``) whose host does not
    resolve, or is not an address of this computer, is a :class:`ConfigError`: ``run`` cannot
    bind it either. A destination (``udpout``, ``udpbcast``, ``tcp``) that does not resolve
    *now* is a warning, returned as one line each: a companion may start before DNS is up;
    ``run`` then resolves a ``udpout``/``udpbcast`` name off the loop and retries
    (docs/mavlink.md, "Connection strings"), while ``tcp`` connects once at start. A serial
    device that does not exist now is a warning too (``run`` opens it once at start)."""
    warnings = []
    for key, url in links:
        scheme, _, rest = url.partition(":")
        device = url.partition(",")[0]
        if device.startswith("/") and not Path(device).exists():
            # a USB adapter udev has not named yet at boot: like a name DNS does not know yet
            warnings.append(f"{key}: {url!r}: serial device {device} does not exist now; run opens it once at "
                            f"start and exits with an error while it is missing")
            continue
        dest = endpoints.destination_host(url)
        host = dest[0] if dest is not None else (rest.rpartition(":")[0] if scheme in ("udpin", "udp", "tcpin") else "")
        if not host:
            continue
        try:
            address = host if endpoints.is_numeric(host) else endpoints.resolve(host)
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
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((address, 0))
        except OSError as exc:
            if exc.errno != errno.EADDRNOTAVAIL:
                return  # not the address's fault: run reports what it meets
            raise ConfigError(f"{key}: {url!r}: {address} is not an address of this computer ({exc.strerror}); "
                              f"accepted: a local address to listen on (0.0.0.0, 127.0.0.1, this computer's "
                              f"name)") from None
