"""ATTITUDE (message 30) and ATTITUDE_QUATERNION (message 31) encoders.

Both carry the attitude of the body (FRD) against the earth (NED) — MAVLink's "aeronautical
frame". ATTITUDE holds ZYX Euler angles (rad); ATTITUDE_QUATERNION holds q1..q4 = w, x, y, z
of q_earth←body, the project's own order and meaning, so no conversion is needed. The
*speed fields carry the bias-corrected body rates p, q, r (rad/s about FRD x, y, z), as PX4
and ArduPilot fill them.
"""

from __future__ import annotations

from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.frames import PackedMessage
from ahrs_service.protocols.mavlink.telemetry import Telemetry

# The service never rotates its reference frame for display, so the representation offset is
# the identity rotation ([0, 0, 0, 0] would mean "field not supported").
REPR_OFFSET_Q = [1.0, 0.0, 0.0, 0.0]


def _time_ms(t: Telemetry) -> int:
    # uint32 on the wire: wraps after ~49.7 days, as on autopilots
    return int(t.time_boot_ms) & 0xFFFFFFFF


def _attitude_fields(t: Telemetry) -> tuple[int, float, float, float, float, float, float]:
    p, q, r = t.body_rate
    return _time_ms(t), float(t.roll), float(t.pitch), float(t.yaw), float(p), float(q), float(r)


def _attitude_quaternion_fields(t: Telemetry) -> tuple[int, float, float, float, float, float, float, float]:
    w, x, y, z = t.q
    p, q, r = t.body_rate
    return _time_ms(t), float(w), float(x), float(y), float(z), float(p), float(q), float(r)


def encode_attitude(t: Telemetry) -> "mavlink.MAVLink_attitude_message":
    """ATTITUDE: time_boot_ms, roll/pitch/yaw (rad), rollspeed/pitchspeed/yawspeed (rad/s)."""
    return mavlink.MAVLink_attitude_message(*_attitude_fields(t))


def encode_attitude_quaternion(t: Telemetry) -> "mavlink.MAVLink_attitude_quaternion_message":
    """ATTITUDE_QUATERNION: time_boot_ms, q1..q4 = w, x, y, z, body rates (rad/s), repr_offset_q."""
    return mavlink.MAVLink_attitude_quaternion_message(*_attitude_quaternion_fields(t), REPR_OFFSET_Q)


# The streamed path: the same fields packed once with pymavlink's own layouts (see ``frames``).
_ATTITUDE = mavlink.MAVLink_attitude_message
_ATTITUDE_QUATERNION = mavlink.MAVLink_attitude_quaternion_message


def attitude_frame(t: Telemetry) -> PackedMessage:
    """ATTITUDE as ``encode_attitude`` fills it, payload packed for an unsigned link."""
    return PackedMessage(_ATTITUDE, _ATTITUDE.unpacker.pack(*_attitude_fields(t)))


def attitude_quaternion_frame(t: Telemetry) -> PackedMessage:
    """ATTITUDE_QUATERNION as ``encode_attitude_quaternion`` fills it, payload packed for an
    unsigned link."""
    return PackedMessage(
        _ATTITUDE_QUATERNION, _ATTITUDE_QUATERNION.unpacker.pack(*_attitude_quaternion_fields(t), *REPR_OFFSET_Q)
    )
