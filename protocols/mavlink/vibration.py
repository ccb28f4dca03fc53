"""VIBRATION (message 241) encoder: vibration levels per body axis and accelerometer clipping counts.

The values are ArduPilot's (``ahrs_service.core.vibration``, after
``AP_InertialSensor::calc_vibration_and_clipping``; sent as ``GCS_MAVLINK::send_vibration``
does): vibration_x/y/z the RMS specific force above ~5 Hz on body FRD x, y, z in m/s²,
clipping_0 the clipped samples of the (only) accelerometer since start, clipping_1/2 zero.
PX4 puts other metrics in the same fields (see ``ahrs_service/vibration.py``). ``time_usec``
is the newest sample's time in µs since the service started.
"""

from __future__ import annotations

from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.telemetry import Telemetry


def encode_vibration(t: Telemetry) -> "mavlink.MAVLink_vibration_message | None":
    """VIBRATION of ``t.vibration``; None when the telemetry carries no vibration levels."""
    v = t.vibration
    if v is None:
        return None
    time_usec = int(t.time_usec) if t.time_usec is not None else int(t.time_boot_ms) * 1000
    c0, c1, c2 = (min(int(c), 0xFFFFFFFF) for c in v.clipping)  # uint32 fields
    return mavlink.MAVLink_vibration_message(time_usec, float(v.x), float(v.y), float(v.z), c0, c1, c2)
