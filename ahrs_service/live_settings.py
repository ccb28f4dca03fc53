"""The ``[live]`` section of the configuration: the Foxglove WebSocket live view (docs/live.md).

Apart from :mod:`ahrs_service.live_view`, which imports the estimation pipeline and the log's
schemas, so that composing the configuration does not load the view's machinery.
"""

from __future__ import annotations

from ahrs_service.core.settings import Section, boolean, number, string

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
}
