"""What every sensor input gives the service: timestamped samples in SI units, and counters.

A source (an I2C IMU, a DroneCAN IMU, the simulator, a recorded log) is one class behind
:class:`ImuSource`. The scheduler calls :meth:`ImuSource.read` once per tick; a source
returns the newest *new* sample or ``None`` — it never hands the same reading out twice.

Units and axes of an :class:`ImuSample`: gyroscope rad/s, specific force m/s², magnetic
field µT; ``gyr``/``acc``/``mag`` are calibrated and in the **body frame (FRD)** once
:mod:`ahrs_service.drivers.calibration` has been applied, in the sensor's own axes before.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# validity flags of one sample (bit mask)
GYR_VALID = 1 << 0
ACC_VALID = 1 << 1
MAG_VALID = 1 << 2
GYR_SATURATED = 1 << 3
ACC_SATURATED = 1 << 4
MAG_SATURATED = 1 << 5
MAG_NEW = 1 << 6  # the magnetometer value is a fresh reading (magnetometers run slower)


@dataclass(slots=True)
class ImuSample:
    """One IMU reading.

    t_ns: timestamp in nanoseconds on the monotonic clock of the host (``time.monotonic_ns``),
        or the sensor's own clock mapped onto it (CAN).
    gyr, acc: (3,) float64, rad/s and m/s² (specific force).
    mag: (3,) float64 in µT, or None when the source has no magnetometer value for this sample.
    flags: validity bits (``GYR_VALID`` …). A reading that is saturated or not finite has its
        ``*_VALID`` bit cleared and is not fed to the estimator as valid.
    raw: the uncalibrated readings where the driver has them, e.g. {"gyr": [counts…], …}.
    truth_q: ground-truth q_earth←body [w, x, y, z] when the source knows it (simulator, BROAD).
    """

    t_ns: int
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None = None
    flags: int = GYR_VALID | ACC_VALID
    raw: dict[str, Any] | None = None
    truth_q: np.ndarray | None = None
    temperature_c: float | None = None


@dataclass
class SourceDiagnostics:
    """Fault counters of one source; the service publishes them (SYS_STATUS, STATUSTEXT, MCAP).

    Every fault a source survives increments one of these; ``last_error`` keeps the latest
    message for humans.
    """

    samples: int = 0
    bus_errors: int = 0  # I2C OSError/NACK, CAN interface errors
    retries: int = 0
    reinitialisations: int = 0
    device_lost: bool = False
    saturated: int = 0
    non_finite: int = 0
    dropped_frames: int = 0  # malformed / foreign / out-of-order CAN frames
    incomplete_transfers: int = 0
    last_error: str = ""
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "extra"}
        d.update(self.extra)
        return d


class ImuSource(abc.ABC):
    """Base of every sensor input. Subclasses implement ``open``, ``read`` and ``close``."""

    #: whether this source can deliver magnetometer readings at all
    has_mag: bool = True
    #: whether several samples can be due at once (a FIFO, a replayed log): the service then
    #: reads until ``read`` returns None, a bounded number per tick, so a late tick loses nothing
    may_have_backlog: bool = False

    def __init__(self) -> None:
        self.diagnostics = SourceDiagnostics()

    @abc.abstractmethod
    def open(self) -> None:
        """Connects and configures the device; raises a clear error naming bus/address on failure."""

    @abc.abstractmethod
    def read(self) -> ImuSample | None:
        """The newest new sample, or None when nothing new arrived since the last call.

        Must not raise on transient faults: count them in ``diagnostics`` and return None.
        """

    def close(self) -> None:
        """Releases the bus."""

    def __enter__(self) -> "ImuSource":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
