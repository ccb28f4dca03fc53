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

#: ``[live]``: the view's server and its publishing rate
LIVE: Section = {
    "enabled": (False, boolean),
    "host": (DEFAULT_HOST, string),
    "port": (DEFAULT_PORT, number(0, 65535, integer=True)),
    # viewers get the per-sample channels (/imu/raw, /attitude, /tf) at most this often, Hz
    "rate_hz": (DEFAULT_RATE_HZ, number(1.0, 200.0)),
    # false: view-only, every client's parameter set is refused (required beside a non-loopback host)
    "allow_remote_control": (True, boolean),
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
    """The checked ``[live]`` section as a whole: the Foxglove WebSocket protocol has no way to
    authenticate a client, so a view other computers can reach must be view-only."""
    host = section["host"]
    if not host.strip():
        raise ConfigError("live.host: '' is empty; accepted: an address or host name (127.0.0.1 by default)")
    if not is_loopback(host) and section["allow_remote_control"]:
        raise ConfigError(f"live.host: {host!r} is reachable from the network and any client there could set the "
                          "estimator's gains; set live.allow_remote_control = false (view-only) or keep a loopback "
                          "host and reach it through an SSH tunnel (docs/live.md, Security)")
