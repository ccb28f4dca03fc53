"""The one MAVLink dialect this package speaks: ``common``, MAVLink 2.

Every module imports the generated pymavlink module from here, so the wire version never
depends on whether ``MAVLINK20`` was set before some other code imported ``mavutil`` (that
environment variable switches a process-wide global in pymavlink; using the v20 module
explicitly does not).
"""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mavlink

__all__ = ["mavlink", "message_id", "message_name"]


def message_id(name: str) -> int | None:
    """MAVLink message id of a message name such as ``"ATTITUDE"``; None if unknown."""
    cls = getattr(mavlink, f"MAVLink_{name.lower()}_message", None)
    return None if cls is None else int(cls.id)


def message_name(msg_id: int) -> str | None:
    """Message name of a MAVLink message id in the common dialect; None if unknown."""
    cls = mavlink.mavlink_map.get(int(msg_id))
    return None if cls is None else str(cls.msgname)
