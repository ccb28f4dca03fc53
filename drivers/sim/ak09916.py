"""The simulated AK09916, the magnetometer on the ICM-20948's auxiliary I2C bus: see
:mod:`ahrs_service.drivers.parts.ak09916`.
"""

from __future__ import annotations

from ahrs_service.drivers.parts.ak09916 import (
    ADDRESS,
    CNTL2,
    CNTL3,
    DOR,
    DRDY,
    FULL_SCALE,
    HOFL,
    HXL,
    MODES_HZ,
    SRST,
    ST1,
    ST2,
    UT_PER_LSB,
    WIA2,
    WIA2_VALUE,
)
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts


class SimulatedAK09916(SimulatedRegisterDevice):
    """AK09916 twin. The physics field (board = ICM-20948 accelerometer axes) is written in the
    die's own axes: X_mag = X_acc, Y_mag = −Y_acc, Z_mag = −Z_acc (datasheet orientation)."""

    PART = "AK09916"
    DEFAULT_ADDRESS = ADDRESS
    POWER_ON = {0x00: 0x48, WIA2: WIA2_VALUE}
    WRITABLE = frozenset({CNTL2, CNTL3})

    def rate_hz(self) -> float | None:
        return MODES_HZ.get(self.regs[CNTL2] & 0x1F)

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == CNTL3 and value & SRST:
            self.power_on_reset(now)
        elif reg == CNTL2:
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        m = phys["mag"]
        die = (m[0], -m[1], -m[2])
        counts = [to_counts(v, UT_PER_LSB, -FULL_SCALE, FULL_SCALE) for v in die]
        out = []
        for c in counts:
            out.extend(i16_bytes(c, False))
        self.regs[HXL:HXL + 6] = bytes(out)
        self.regs[ST2] = HOFL if any(abs(c) >= FULL_SCALE for c in counts) else 0
        self.regs[ST1] = DRDY | (DOR if skipped or self.regs[ST1] & DRDY else 0)

    def on_read(self, regs: list[int], now: float) -> None:
        if ST2 in regs:
            self.regs[ST1] = 0
