"""AKM AK8963 3-axis magnetometer (inside the MPU-9250), and its twin.

Reachable on the host bus at 0x0C only while the MPU-9250 is in I2C bypass mode
(INT_PIN_CFG.BYPASS_EN = 1, USER_CTRL.I2C_MST_EN = 0). Register map used:

=====  ===========  ===========================================================
0x00   WIA          0x48
0x02   ST1          bit 0 DRDY, bit 1 DOR (a sample was skipped)
0x03…  HXL…HZH      X, Y, Z little-endian two's complement
0x09   ST2          bit 3 HOFL (magnetic overflow), bit 4 BITM (output width)
0x0A   CNTL1        bit 4 BIT (0 = 14-bit 0.6 µT/LSB, 1 = 16-bit 0.15 µT/LSB),
                    MODE 3:0: 0 power-down, 2 continuous 8 Hz, 6 continuous 100 Hz, F fuse ROM
0x0B   CNTL2        bit 0 SRST (soft reset)
0x10…  ASAX…ASAZ    sensitivity adjustment (fuse ROM, readable in fuse-ROM mode only)
=====  ===========  ===========================================================

DRDY and DOR clear when a data register or ST2 is read; reading ST2 ends the read and lets
the part place the next measurement. The adjusted field is H · ((ASA − 128) / 256 + 1).
Overflow: HOFL is set when |X| + |Y| + |Z| exceeds 4912 µT; that reading is invalid.

Axes: the AK8963 die is turned relative to the MPU-9250's accelerometer/gyro axes
(X_mag = Y_acc, Y_mag = X_acc, Z_mag = −Z_acc). :meth:`AK8963.to_si` returns the field in the
**MPU-9250's axes**, so a board's three sensors share one frame; ``raw`` keeps the die's order.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import I2CDevice

WIA, INFO, ST1, HXL, ST2, CNTL1, CNTL2, ASTC, ASAX = 0x00, 0x01, 0x02, 0x03, 0x09, 0x0A, 0x0B, 0x0C, 0x10
WIA_VALUE = 0x48
DRDY, DOR = 0x01, 0x02
HOFL, BITM = 0x08, 0x10
BIT_16 = 0x10
POWER_DOWN, FUSE_ROM = 0x00, 0x0F
MODES_HZ = {8: 0x02, 100: 0x06}
UT_PER_LSB = {14: 0.6, 16: 0.15}
OVERFLOW_UT = 4912.0
_UNPACK = struct.Struct("<3hB").unpack


class AK8963(I2CDevice):
    """AK8963 driver: field in µT in the MPU-9250's axes (see the module notes).

    rate_hz: 8 or 100 (continuous modes 1 and 2). bits: 16 (0.15 µT/LSB) or 14 (0.6 µT/LSB).
    """

    PART = "AK8963"
    DEFAULT_ADDRESS = 0x0C

    def __init__(self, bus: I2CBus, address: int | None = None, *, rate_hz: float = 100, bits: int = 16,
                 **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        if rate_hz not in MODES_HZ:
            raise ValueError(f"AK8963 rate_hz must be one of {sorted(MODES_HZ)}, got {rate_hz}")
        if bits not in UT_PER_LSB:
            raise ValueError(f"AK8963 bits must be 14 or 16, got {bits}")
        self.rate_hz, self.bits = float(rate_hz), bits
        self.asa = (128, 128, 128)
        self.overflow = False
        self.full_scale = 32760 if bits == 16 else 8190
        self._set_scale()

    def _set_scale(self) -> None:
        lsb = UT_PER_LSB[self.bits]
        self.die_scale = np.array([lsb * ((a - 128) / 256.0 + 1.0) for a in self.asa])

    def configure(self) -> None:
        """Checks WIA, reads the ASA fuse ROM, starts continuous measurement."""
        self.check_identity(WIA, bytes([WIA_VALUE]), "WIA")
        # mode changes must pass through power-down, 100 µs apart (datasheet 6.4)
        self.write_u8(CNTL1, POWER_DOWN)
        self.transport.sleep(1e-4)
        self.write_u8(CNTL1, FUSE_ROM)
        self.transport.sleep(1e-4)
        self.asa = tuple(self.read_regs(ASAX, 3))
        self._set_scale()
        self.write_u8(CNTL1, POWER_DOWN)
        self.transport.sleep(1e-4)
        self.write_u8(CNTL1, (BIT_16 if self.bits == 16 else 0) | MODES_HZ[self.rate_hz])

    def read_if_new(self, t_ns: int | None = None) -> tuple[int, int, int] | None:
        """(X, Y, Z) die counts of a new measurement, or None when DRDY is clear.

        ST1 is polled alone: reading the data registers clears DRDY, so polling them while
        no data are ready could swallow a sample arriving mid-transfer. The data burst runs
        on to ST2, which ends the read; its HOFL bit is kept in ``overflow``. ``t_ns`` is
        unused (same call as the Honeywell-style magnetometers).
        """
        if not self.read_u8(ST1) & DRDY:
            return None
        x, y, z, st2 = _UNPACK(self.read_regs(HXL, 7))
        self.overflow = bool(st2 & HOFL)
        return x, y, z

    @property
    def resolution(self) -> float:
        return float(np.max(self.die_scale))

    def to_si(self, counts) -> np.ndarray:
        """Field (µT) in the MPU-9250's axes from die counts (ASA applied)."""
        x, y, z = np.multiply(counts, self.die_scale)
        return np.array([y, x, -z])

    def is_saturated(self, counts) -> bool:
        """HOFL of the last reading, or an axis at the output limit."""
        fs = self.full_scale
        return self.overflow or any(c >= fs or c <= -fs for c in counts)
