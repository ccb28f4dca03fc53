"""HIGHRES_IMU (message 105) encoder: the calibrated IMU readings in the body frame (FRD).

MAVLink units: acceleration m/s² (specific force, as the service uses), angular rate rad/s,
magnetic field **gauss** (1 G = 100 µT, so µT are divided by 100), temperature °C.
``fields_updated`` marks only the fields that carry a fresh value; the others are sent as 0.
The pressure fields are never set (the service has no barometer).
"""

from __future__ import annotations

from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.telemetry import Telemetry

UT_PER_GAUSS = 100.0

ACC_UPDATED = mavlink.HIGHRES_IMU_UPDATED_XACC | mavlink.HIGHRES_IMU_UPDATED_YACC | mavlink.HIGHRES_IMU_UPDATED_ZACC
GYRO_UPDATED = mavlink.HIGHRES_IMU_UPDATED_XGYRO | mavlink.HIGHRES_IMU_UPDATED_YGYRO | mavlink.HIGHRES_IMU_UPDATED_ZGYRO
MAG_UPDATED = mavlink.HIGHRES_IMU_UPDATED_XMAG | mavlink.HIGHRES_IMU_UPDATED_YMAG | mavlink.HIGHRES_IMU_UPDATED_ZMAG
TEMPERATURE_UPDATED = mavlink.HIGHRES_IMU_UPDATED_TEMPERATURE


def encode_highres_imu(t: Telemetry, imu_id: int = 0) -> "mavlink.MAVLink_highres_imu_message":
    """HIGHRES_IMU of the raw calibrated readings in ``t``; ``imu_id`` 0 is IMU1."""
    updated = 0
    acc = gyr = mag = (0.0, 0.0, 0.0)
    if t.acc is not None:
        acc = tuple(float(v) for v in t.acc)
        updated |= ACC_UPDATED
    if t.gyr is not None:
        gyr = tuple(float(v) for v in t.gyr)
        updated |= GYRO_UPDATED
    if t.mag is not None:
        mag = tuple(float(v) / UT_PER_GAUSS for v in t.mag)
        if t.mag_new:
            updated |= MAG_UPDATED
    temperature = 0.0
    if t.temperature_c is not None:
        temperature = float(t.temperature_c)
        updated |= TEMPERATURE_UPDATED
    time_usec = int(t.time_usec) if t.time_usec is not None else int(t.time_boot_ms) * 1000
    return mavlink.MAVLink_highres_imu_message(
        time_usec, *acc, *gyr, *mag, 0.0, 0.0, 0.0, temperature, updated, imu_id
    )
