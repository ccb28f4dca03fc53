"""The simplest simulated input: samples straight from a :class:`SimulatedImu`, no bus.

Samples fall on a fixed grid t_k = k / rate_hz of the simulation clock. ``read`` returns the
newest grid sample not delivered yet, or None when the clock has not reached a new one, so
no sample is ever handed out twice; samples skipped because ``read`` came late (a host
stall: the simulated part, like a real one without FIFO, keeps only its newest sample) are
counted as lost in ``diagnostics.lost.host_stall`` (and in ``diagnostics.dropped_frames``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
    ImuSample,
    ImuSource,
)
from ahrs_service.drivers.sim.imu import SimulatedImu

_VALID = {"gyr": GYR_VALID, "acc": ACC_VALID, "mag": MAG_VALID}
_SATURATED = {"gyr": GYR_SATURATED, "acc": ACC_SATURATED, "mag": MAG_SATURATED}


class SimulatedSource(ImuSource):
    """An :class:`ImuSource` reading a :class:`SimulatedImu` at a nominal rate.

    rate_hz: gyro/accelerometer sample rate, Hz.
    mag_rate_hz: magnetometer rate, Hz (rounded to every k-th sample, k = rate/mag_rate);
        None: a new magnetometer reading with every sample; 0: no magnetometer.
    Samples between two magnetometer readings carry the last one with ``MAG_VALID`` but
    without ``MAG_NEW``; before the first there is none (``mag`` None). ``truth_q`` is the
    true q_earth←body, ``temperature_c`` the die temperature. Values are in the sensor's axes.
    """

    def __init__(self, imu: SimulatedImu, rate_hz: float = 200.0, mag_rate_hz: float | None = None) -> None:
        super().__init__()
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        self.imu = imu
        self.rate_hz = float(rate_hz)
        if mag_rate_hz is None:
            self.mag_every = 1
        elif mag_rate_hz == 0:
            self.mag_every = 0
        elif mag_rate_hz > 0 and mag_rate_hz <= rate_hz:
            self.mag_every = max(1, round(rate_hz / mag_rate_hz))
        else:
            raise ValueError(f"mag_rate_hz must be 0 … rate_hz ({rate_hz}), got {mag_rate_hz!r}")
        self.has_mag = self.mag_every > 0
        self._next = 0  # index of the first grid sample not delivered yet
        self._delivered = False  # a sample has been read: later skips are losses
        self._mag: np.ndarray | None = None
        self._mag_saturated = False
        self._open = False

    @property
    def clock(self) -> Any:
        """The simulation clock (the IMU's)."""
        return self.imu.clock

    def open(self) -> None:
        self._open = True

    def close(self) -> None:
        self._open = False

    def read(self) -> ImuSample | None:
        """The newest new sample due on the clock, or None; never the same sample twice."""
        now = self.imu.clock.now()
        # small tolerance so that t = k / rate exactly on a ManualClock counts as due
        k = math.floor(now * self.rate_hz + 1e-9)
        tr = self.imu.trajectory
        if not tr.looping and math.isfinite(tr.duration):
            k = min(k, math.floor(tr.duration * self.rate_hz + 1e-9))
        if k < self._next:
            return None
        if self._delivered:  # what the part made before the first read was never due
            self.diagnostics.dropped_frames += k - self._next
            self.diagnostics.lost.host_stall += k - self._next
        self._delivered = True
        self._next = k + 1
        return self._sample(k)

    def _to_ns(self, t: float) -> int:
        # clocks without a host mapping (user-made ones) count from 0 ns
        to_ns = getattr(self.imu.clock, "to_ns", None)
        return to_ns(t) if to_ns is not None else int(round(t * 1e9))

    def _sample(self, k: int) -> ImuSample:
        t = k / self.rate_hz
        ph = self.imu.physics(t)
        flags = GYR_VALID | ACC_VALID
        mag_new = self.mag_every > 0 and k % self.mag_every == 0
        sat = ph["saturated"]
        if mag_new:
            self._mag, self._mag_saturated = ph["mag"], sat["mag"]
            flags |= MAG_NEW
        if self._mag is not None:
            flags |= MAG_SATURATED if self._mag_saturated else MAG_VALID
        for key in ("gyr", "acc"):
            if sat[key]:
                flags = (flags & ~_VALID[key]) | _SATURATED[key]
        # each saturated reading counted once, not again on the samples that repeat a magnetometer value
        self.diagnostics.saturated += int(sat["gyr"]) + int(sat["acc"]) + int(mag_new and sat["mag"])
        self.diagnostics.samples += 1
        return ImuSample(
            t_ns=self._to_ns(t),
            gyr=ph["gyr"],
            acc=ph["acc"],
            mag=self._mag,
            flags=flags,
            truth_q=ph["truth"].q,
            temperature_c=ph["temperature_c"],
        )
