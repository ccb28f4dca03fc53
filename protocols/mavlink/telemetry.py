"""What the service hands the MAVLink component at each publish: one attitude snapshot.

Frames and units follow docs/design.md: q is q_earth←body, Hamilton [w, x, y, z], earth
NED, body FRD; Euler angles ZYX in rad with yaw in (−π, π]; body rates in rad/s about the FRD
axes (p, q, r), bias-corrected. Raw IMU values, when given, are calibrated and in the body
frame: gyroscope rad/s, specific force m/s², magnetic field µT, temperature °C.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

from ahrs_service.core.quaternion import euler_of
from ahrs_service.core.vibration import VibrationLevels

#: the streams an ``attitude_only`` :class:`Telemetry` can be published on
ATTITUDE_STREAMS = frozenset({"ATTITUDE", "ATTITUDE_QUATERNION"})


@dataclass(slots=True)
class SensorStatus:
    """One sensor's SYS_STATUS bits: present (fitted), enabled (used), healthy (no fault)."""

    present: bool = True
    enabled: bool = True
    healthy: bool = True


def _absent() -> SensorStatus:
    return SensorStatus(False, False, False)


@dataclass(slots=True)
class Telemetry:
    """One attitude snapshot as published on MAVLink.

    time_boot_ms: ms since the service started (MAVLink's "time since system boot").
    q: q_earth←body [w, x, y, z], unit norm.
    roll, pitch, yaw: ZYX Euler angles of ``q``, rad, yaw in (−π, π].
    body_rate: (p, q, r) rad/s about FRD x, y, z, gyro bias removed.
    gyr, acc, mag: calibrated body-frame readings (rad/s, m/s² specific force, µT) or None.
    mag_new: the magnetometer value is a fresh reading (HIGHRES_IMU marks only fresh fields
        as updated).
    temperature_c: IMU temperature (°C) or None.
    time_usec: sample time in µs since boot for HIGHRES_IMU; None uses time_boot_ms·1000.
    gyro, accel, mag_status: sensor present/enabled/healthy bits for SYS_STATUS.
    estimator: estimator name (for status texts and logs).
    ahrs_healthy: the estimator is initialised and its output is trustworthy.
    reduced_mode: heading is not observed (no magnetometer in use); the magnetometer is then
        reported as not enabled.
    overruns: estimator loop deadline misses since start.
    load_percent: estimator loop busy time as a percentage of its period (0..100).
    comm_errors: sensor bus errors since start (I2C/CAN), SYS_STATUS errors_comm.
    sensor_faults: rejected samples (saturated, not finite) since start.
    lost_samples: IMU samples that never reached the host since start (all causes),
        SYS_STATUS errors_count3.
    faults: other named fault counters (kept for logs; not all fit in SYS_STATUS).
    vibration: VIBRATION's levels and clipping counts (``ahrs_service.core.vibration``) or None.
    attitude_fresh: a sample was estimated recently; False (gyroscope gone, source silent)
        withholds ATTITUDE, ATTITUDE_QUATERNION, HIGHRES_IMU and VIBRATION — as PX4's streams, which send
        only on a new estimate — while HEARTBEAT (CRITICAL) and SYS_STATUS go on.
    attitude_only: only ``time_boot_ms``, the attitude (``q``, Euler angles, ``body_rate``)
        and ``attitude_fresh`` are set; the rest are defaults. Built when only the
        :data:`ATTITUDE_STREAMS` are due (most publishes at their usual rates): the health,
        readings and vibration snapshot is the costliest part of a publish.
    """

    time_boot_ms: int
    q: Sequence[float]
    roll: float
    pitch: float
    yaw: float
    body_rate: Sequence[float] = (0.0, 0.0, 0.0)
    gyr: Sequence[float] | None = None
    acc: Sequence[float] | None = None
    mag: Sequence[float] | None = None
    mag_new: bool = True
    temperature_c: float | None = None
    time_usec: int | None = None
    gyro: SensorStatus = field(default_factory=SensorStatus)
    accel: SensorStatus = field(default_factory=SensorStatus)
    mag_status: SensorStatus = field(default_factory=_absent)
    estimator: str = ""
    ahrs_healthy: bool = True
    reduced_mode: bool = False
    overruns: int = 0
    load_percent: float = 0.0
    comm_errors: int = 0
    sensor_faults: int = 0
    lost_samples: int = 0
    faults: Mapping[str, int] = field(default_factory=dict)
    vibration: VibrationLevels | None = None
    attitude_fresh: bool = True
    attitude_only: bool = False

    @classmethod
    def from_quaternion(cls, time_boot_ms: int, q: Sequence[float], body_rate: Sequence[float] = (0.0, 0.0, 0.0),
                        **fields: object) -> "Telemetry":
        """Telemetry whose Euler angles are computed from ``q`` (ZYX, yaw in (−π, π])."""
        q = tuple(map(float, q))
        roll, pitch, yaw = euler_of(q)
        return cls(int(time_boot_ms), q, roll, pitch, yaw, tuple(map(float, body_rate)), **fields)  # type: ignore[arg-type]
