"""ST L3GD20 3-axis gyroscope (the MinIMU-9 v2's gyro), and its twin.

Same register map as the L3G4200D (see :mod:`ahrs_service.drivers.parts.l3g4200d`) except:
WHO_AM_I (0x0F) reads 0xD4, and the DR bits give 95 / 190 / 380 / 760 Hz. Its 32-level FIFO
(datasheet Doc ID 022116 §4.2, FIFO_CTRL_REG 0x2E, FIFO_SRC_REG 0x2F) is the L3G4200D's:
:mod:`ahrs_service.drivers.parts.st_fifo`. Sensitivity
8.75 / 17.50 / 70 m°/s per digit at ±250 / 500 / 2000 °/s. I2C address 0x6B (SA0 high, the
MinIMU-9 v2) or 0x6A. The L3GD20H (0xD7, MinIMU-9 v3) is a different part and is refused.
"""

from __future__ import annotations

from typing import Any

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.parts.l3g4200d import L3G4200D


class L3GD20(L3G4200D):
    """L3GD20 driver: angular rate in rad/s, sensor axes.

    range_dps: 250, 500 or 2000. rate_hz: 95, 190, 380 or 760.
    """

    PART = "L3GD20"
    DEFAULT_ADDRESS = 0x6B
    WHO_AM_I_VALUE = 0xD4
    RATES_HZ = {95: 0b00, 190: 0b01, 380: 0b10, 760: 0b11}

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_dps: int = 2000,
                 rate_hz: float = 760, **kw: Any) -> None:
        super().__init__(bus, address, range_dps=range_dps, rate_hz=rate_hz, **kw)
