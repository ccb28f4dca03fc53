"""The service's MAVLink side (MAVLink 2, dialect common, via pymavlink).

* ``identity``  — who we are on the network (standalone vehicle or companion IMU component);
* ``telemetry`` — the snapshot the service hands over at each publish;
* ``attitude``  — ATTITUDE and ATTITUDE_QUATERNION encoders;
* ``imu``       — HIGHRES_IMU encoder;
* ``health``    — SYS_STATUS and STATUSTEXT encoders;
* ``params``    — the parameter protocol (ParameterTable);
* ``commands``  — COMMAND_LONG handling (CommandTable, calibration handler);
* ``signing``   — MAVLink 2 signing policy and key helpers;
* ``timesync``  — TIMESYNC: the autopilot's clock offset and drift (TimeSync);
* ``endpoints`` — one link opened from a pymavlink connection string;
* ``component`` — MavlinkComponent, which ties them together. See docs/mavlink.md.
"""

from ahrs_service.protocols.mavlink.commands import Command, CommandResult, CommandTable
from ahrs_service.protocols.mavlink.component import DEFAULT_RATES, MavlinkComponent, MavlinkStats
from ahrs_service.protocols.mavlink.identity import COMPANION, STANDALONE, Identity
from ahrs_service.protocols.mavlink.params import ParameterTable
from ahrs_service.protocols.mavlink.signing import key_from_passphrase
from ahrs_service.protocols.mavlink.telemetry import SensorStatus, Telemetry

__all__ = [
    "COMPANION", "Command", "CommandResult", "CommandTable", "DEFAULT_RATES", "Identity",
    "MavlinkComponent", "MavlinkStats", "ParameterTable", "STANDALONE", "SensorStatus", "Telemetry",
    "key_from_passphrase",
]
