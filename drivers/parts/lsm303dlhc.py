"""ST LSM303DLHC accelerometer + magnetometer (the MinIMU-9 v2's), and their twins.

The package answers at two addresses, as two parts.

Accelerometer, 0x19 (register map of datasheet Doc ID 018771):

=====  ============  ========================================================
0x20   CTRL_REG1_A   ODR3:0 LPen Zen Yen Xen; ODR 1/10/25/50/100/200/400 Hz, 1344 Hz (code 9)
0x23   CTRL_REG4_A   BDU BLE FS1 FS0 HR 0 0 SIM; FS ±2/4/8/16 g; HR = 12-bit output
0x27   STATUS_REG_A  ZYXOR … ZYXDA ZDA YDA XDA (DA bits clear when the high bytes are read)
0x24   CTRL_REG5_A   bit 6 FIFO_EN
0x28…  OUT_X_L_A…    X, Y, Z little-endian, left-justified 12-bit (shift right by 4)
0x2E   FIFO_CTRL_A   FM1:0 (bits 7:6), TR, FTH4:0; 0x2F FIFO_SRC_REG_A — the 32-level FIFO
                     (§3.3), the same block as the ST gyroscopes': :mod:`.st_fifo`
=====  ============  ========================================================

Sensitivity in high-resolution mode: 1, 2, 4, 12 mg/LSB at ±2, 4, 8, 16 g (the datasheet's
values). Sub-address MSB set = auto-increment, as on the other ST parts.

**Identity of the accelerometer**: the LSM303DLHC datasheet documents no WHO_AM_I for the
accelerometer, so the driver checks that the part answers at the address and that
CTRL_REG1_A and CTRL_REG4_A read back exactly what was written (a wrong part or an empty
address fails with the bus, address, register and value).

Magnetometer, 0x1E: the Honeywell-style layout of :mod:`~ahrs_service.drivers.parts.hmc5883l`
(CRA_REG_M rate, CRB_REG_M gain, MR_REG_M mode, data X, Z, Y big-endian, SR_REG_M with
LOCK/DRDY, IRA/IRB/IRC = 'H43'), with the LSM303DLHC's own gains — separate for X/Y and Z —
a 220 Hz rate and no averaging bits. **Identity of the magnetometer**: the driver checks
IRA/IRB/IRC = 'H' '4' '3'; these are the same bytes an HMC5883L returns, so the check proves
a Honeywell-compatible magnetometer at 0x1E, and the board (an accelerometer answering at
0x19) says it is the LSM303DLHC's.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import STANDARD_GRAVITY, I2CDevice
from ahrs_service.drivers.parts.hmc5883l import HoneywellStyleMagnetometer
from ahrs_service.drivers.parts.st_fifo import STFifoDriver

CTRL_REG1_A, CTRL_REG2_A, CTRL_REG3_A, CTRL_REG4_A, CTRL_REG5_A, CTRL_REG6_A = range(0x20, 0x26)
STATUS_REG_A, OUT_X_L_A = 0x27, 0x28
AUTO_INCREMENT = 0x80
XYZ_EN = 0x07
BDU, BLE, HR = 0x80, 0x40, 0x08
ZYXDA, ZYXOR = 0x08, 0x80
#: CTRL_REG1_A ODR code → rate in normal / high-resolution mode (Hz)
ACC_RATES_BY_CODE = (0.0, 1.0, 10.0, 25.0, 50.0, 100.0, 200.0, 400.0, 0.0, 1344.0)
ACC_RATES_HZ = {r: c for c, r in enumerate(ACC_RATES_BY_CODE) if r}
#: range (g) → (FS code, mg per LSB of the 12-bit value)
ACC_RANGES_G = {2: (0b00, 1.0), 4: (0b01, 2.0), 8: (0b10, 4.0), 16: (0b11, 12.0)}
_UNPACK = struct.Struct("<3h").unpack


class LSM303DLHCAcc(STFifoDriver, I2CDevice):
    """LSM303DLHC accelerometer driver (high-resolution 12-bit): specific force in m/s².

    range_g: 2, 4, 8 or 16. rate_hz: 1, 10, 25, 50, 100, 200, 400 or 1344. fifo: run the
    32-level FIFO in stream mode with the ``watermark`` (samples).
    """

    FM_SHIFT = 6

    PART = "LSM303DLHC accelerometer"
    DEFAULT_ADDRESS = 0x19
    AUTO_INCREMENT_FLAG = AUTO_INCREMENT

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_g: int = 8,
                 rate_hz: float = 1344, fifo: bool = False, watermark: int = 8, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        self.fifo, self.fifo_watermark = bool(fifo), int(watermark)
        if range_g not in ACC_RANGES_G:
            raise ValueError(f"{self.PART} range_g must be one of {sorted(ACC_RANGES_G)}, got {range_g}")
        if rate_hz not in ACC_RATES_HZ:
            raise ValueError(f"{self.PART} rate_hz must be one of {sorted(ACC_RATES_HZ)}, "
                             f"got {rate_hz}")
        self.range_g, self.rate_hz = range_g, float(rate_hz)
        mg = ACC_RANGES_G[range_g][1]
        # the registers hold the 12-bit value left-justified: scale the raw 16-bit word
        self.scale = np.full(3, mg * 1e-3 * STANDARD_GRAVITY / 16.0)
        self.full_scale = 16 * min(2047, int(range_g / (mg * 1e-3)))

    @property
    def resolution(self) -> float:
        return 16 * float(self.scale[0])  # one step of the 12-bit value

    def configure(self) -> None:
        """Writes range (BDU, HR) and rate, verifying each by read-back (no WHO_AM_I exists)."""
        self.write_verified(CTRL_REG4_A, BDU | HR | (ACC_RANGES_G[self.range_g][0] << 4),
                            "CTRL_REG4_A")
        self.write_verified(CTRL_REG1_A, (ACC_RATES_HZ[self.rate_hz] << 4) | XYZ_EN,
                            "CTRL_REG1_A")
        if self.fifo:
            self.configure_fifo(self.fifo_watermark)

    def data_ready(self) -> bool:
        """STATUS_REG_A.ZYXDA: a new X/Y/Z set not read yet."""
        return bool(self.read_u8(STATUS_REG_A) & ZYXDA)

    def read_counts(self) -> tuple[int, int, int]:
        """Latest raw X, Y, Z words (left-justified 12-bit) in one auto-increment burst."""
        return _UNPACK(self.read_regs(AUTO_INCREMENT | OUT_X_L_A, 6))

    def read_if_new(self) -> tuple[int, int, int] | None:
        """Raw words of a new sample, or None when ZYXDA is clear."""
        return self.read_counts() if self.data_ready() else None


class LSM303DLHCMag(HoneywellStyleMagnetometer):
    """LSM303DLHC magnetometer driver: field in µT, sensor axes.

    range_ga: 1.3, 1.9, 2.5, 4.0, 4.7, 5.6 or 8.1; rate_hz: 0.75 … 220.
    """

    PART = "LSM303DLHC magnetometer"
    DEFAULT_ADDRESS = 0x1E
    GAINS = {1.3: (1, 1100, 980), 1.9: (2, 855, 760), 2.5: (3, 670, 600),
             4.0: (4, 450, 400), 4.7: (5, 400, 355), 5.6: (6, 330, 295), 8.1: (7, 230, 205)}
    RATES_HZ = {0.75: 0, 1.5: 1, 3: 2, 7.5: 3, 15: 4, 30: 5, 75: 6, 220: 7}

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_ga: float = 1.3,
                 rate_hz: float = 220, **kw: Any) -> None:
        super().__init__(bus, address, range_ga=range_ga, rate_hz=rate_hz, **kw)
