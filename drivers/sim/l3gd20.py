"""The simulated L3GD20 gyroscope: the L3G4200D's twin with the L3GD20's identity and rates
(:mod:`ahrs_service.drivers.parts.l3gd20`).
"""

from __future__ import annotations

from ahrs_service.drivers.sim.l3g4200d import SimulatedL3G4200D


class SimulatedL3GD20(SimulatedL3G4200D):
    """Simulated L3GD20 (WHO_AM_I 0xD4, 95…760 Hz)."""

    CLOCK_ERROR = +0.0050  # this simulated unit runs 0.5 % fast
    PART = "L3GD20"
    DEFAULT_ADDRESS = 0x6B
    WHO_AM_I_VALUE = 0xD4
    RATES = (95.0, 190.0, 380.0, 760.0)
    POWER_ON = {0x0F: 0xD4, 0x20: 0x07}
