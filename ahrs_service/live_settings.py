"""The ``[live]`` section of the configuration: the Foxglove WebSocket live view (docs/live.md).

Apart from :mod:`ahrs_service.live_view`, which imports the estimation pipeline and the log's
schemas, so that composing the configuration does not load the view's machinery.
"""

from __future__ import annotations

import ipaddress
from typing import Any

from ahrs_service.core.settings import ConfigError, Section, boolean, number, string

#: where the view listens by default: this computer only (a viewer elsewhere sets ``live.host``)
DEFAULT_HOST = "127.0.0.1"
#: Foxglove's own default WebSocket port
DEFAULT_PORT = 8765
#: the default of ``live.rate_hz``, Hz
DEFAULT_RATE_HZ = 30.0
#: the default of ``live.max_connections``: clients connected (or connecting) at once
DEFAULT_MAX_CONNECTIONS = 16
#: the default of ``live.handshake_timeout_s``: how long a client has to send its upgrade request, s
DEFAULT_HANDSHAKE_TIMEOUT_S = 5.0
#: the shortest token accepted (``openssl rand -hex 16`` gives 32 characters)
MIN_TOKEN_CHARS = 16
#: characters a token may hold: those a URL carries unescaped (it travels as ``?token=…``)
TOKEN_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-._~")

#: ``[live]``: the view's server and its publishing rate
LIVE: Section = {
    "enabled": (False, boolean),
    "host": (DEFAULT_HOST, string),
    "port": (DEFAULT_PORT, number(0, 65535, integer=True)),
    # viewers get the per-sample channels (/imu/raw, /attitude, /tf) at most this often, Hz
    "rate_hz": (DEFAULT_RATE_HZ, number(1.0, 200.0)),
    # false: view-only, every client's parameter set is refused (or a token: beside a non-loopback host)
    "allow_remote_control": (True, boolean),
    # a secret every client must send as ws://host:port/?token=…; "" admits every client
    "token": ("", string),
    # connections open at once; one more is closed as soon as it is accepted
    "max_connections": (DEFAULT_MAX_CONNECTIONS, number(1, 1024, integer=True)),
    # a client that has not sent its complete upgrade request this long after connecting is closed, s
    "handshake_timeout_s": (DEFAULT_HANDSHAKE_TIMEOUT_S, number(0.1, 60.0)),
}


def is_loopback(host: str) -> bool:
    """Whether ``host`` is this computer only: ``localhost`` or a loopback address (127.0.0.0/8,
    ``::1``). Any other name counts as reachable from the network (no DNS lookup here)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_live_section(section: dict[str, Any]) -> None:
    """The checked ``[live]`` section as a whole: a view other computers can reach must ask its
    clients for a token or be view-only. The token is never quoted in an error."""
    host = section["host"]
    if not host.strip():
        raise ConfigError("live.host: '' is empty; accepted: an address or host name (127.0.0.1 by default)")
    token = section["token"]
    if token and (len(token) < MIN_TOKEN_CHARS or not set(token) <= TOKEN_CHARS):
        raise ConfigError(f"live.token: not accepted (value not shown); accepted: at least {MIN_TOKEN_CHARS} "
                          "characters among letters, digits and - . _ ~ (e.g. the output of openssl rand -hex 16)")
    if not is_loopback(host) and section["allow_remote_control"] and not token:
        raise ConfigError(f"live.host: {host!r} is reachable from the network and any client there could set the "
                          "estimator's gains; set live.token (clients then connect to ws://host:port/?token=…) or "
                          "live.allow_remote_control = false (view-only), or keep a loopback host and reach it "
                          "through an SSH tunnel (docs/live.md, Security)")
