"""Who the service is on the MAVLink network: system id, component id, MAV_TYPE, MAV_AUTOPILOT.

Two modes:

``standalone`` (default) — no autopilot on the network (bench, rover, AUV logger). The service
    is the vehicle: component 1 (``MAV_COMP_ID_AUTOPILOT1``), because QGroundControl and
    MAVSDK only list a system whose heartbeat comes from component 1.
    ``MAV_TYPE_GENERIC`` with ``MAV_AUTOPILOT_GENERIC``: QGroundControl creates a vehicle for
    every MAV_TYPE except GCS, onboard controller, gimbal and ADS-B, and handles a generic
    autopilot with its generic firmware plugin (attitude instruments, parameters,
    STATUSTEXT). ``MAV_AUTOPILOT_INVALID`` would mark the heartbeat as "not a flight
    controller", which GCS discovery skips. Pass ``mav_type`` to describe the carrier
    (e.g. ``MAV_TYPE_GROUND_ROVER``, ``MAV_TYPE_SUBMARINE``).

``companion`` — beside an autopilot: the autopilot's system id, component
    ``MAV_COMP_ID_IMU`` (200), ``MAV_TYPE_IMU`` (40, present in pymavlink's common/minimal)
    and ``MAV_AUTOPILOT_INVALID`` (the MAVLink rule for components that are not flight
    controllers), so GCSs show it as a component of the autopilot's vehicle and never as a
    second vehicle.
"""

from __future__ import annotations

from dataclasses import dataclass

from ahrs_service.protocols.mavlink.dialect import mavlink

STANDALONE = "standalone"
COMPANION = "companion"


@dataclass(frozen=True)
class Identity:
    """MAVLink identity of the service.

    mode: ``"standalone"`` or ``"companion"``.
    system_id: 1..255. In companion mode, the autopilot's system id.
    component_id, mav_type, autopilot: None picks the mode's default (see module docstring).
    """

    mode: str = STANDALONE
    system_id: int = 1
    component_id: int | None = None
    mav_type: int | None = None
    autopilot: int | None = None

    def __post_init__(self) -> None:
        if self.mode not in (STANDALONE, COMPANION):
            raise ValueError(f"MAVLink identity mode must be 'standalone' or 'companion', got {self.mode!r}")
        if not 1 <= int(self.system_id) <= 255:
            raise ValueError(f"MAVLink system id must be 1..255, got {self.system_id}")
        standalone = self.mode == STANDALONE
        defaults = {
            "component_id": mavlink.MAV_COMP_ID_AUTOPILOT1 if standalone else mavlink.MAV_COMP_ID_IMU,
            "mav_type": mavlink.MAV_TYPE_GENERIC if standalone else mavlink.MAV_TYPE_IMU,
            "autopilot": mavlink.MAV_AUTOPILOT_GENERIC if standalone else mavlink.MAV_AUTOPILOT_INVALID,
        }
        for name, value in defaults.items():
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        object.__setattr__(self, "system_id", int(self.system_id))
        if not 1 <= int(self.component_id) <= 255:  # type: ignore[arg-type]
            raise ValueError(f"MAVLink component id must be 1..255, got {self.component_id}")

    @classmethod
    def standalone(cls, system_id: int = 1, mav_type: int | None = None) -> "Identity":
        """The service as the vehicle itself (component 1)."""
        return cls(STANDALONE, system_id, mav_type=mav_type)

    @classmethod
    def companion(cls, autopilot_system_id: int) -> "Identity":
        """The service as the IMU component (200) of the autopilot's system."""
        return cls(COMPANION, autopilot_system_id)


def encode_heartbeat(identity: Identity, system_status: int) -> "mavlink.MAVLink_heartbeat_message":
    """HEARTBEAT announcing ``identity``; ``system_status`` is a MAV_STATE value.

    base_mode and custom_mode are 0: the service has no flight modes and is never armed.
    """
    return mavlink.MAVLink_heartbeat_message(
        identity.mav_type, identity.autopilot, 0, 0, system_status, 3  # mavlink_version is 3 by definition
    )
