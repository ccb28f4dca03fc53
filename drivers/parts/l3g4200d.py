"""ST L3G4200D 3-axis gyroscope (the GY-80's gyro), and its twin. The L3GD20 shares the map.

Register map used (datasheet Doc ID 17116):

=====  ===========  ===========================================================
0x0F   WHO_AM_I     0xD3 (L3GD20: 0xD4)
0x20   CTRL_REG1    DR1 DR0 BW1 BW0 PD Zen Yen Xen; DR 00/01/10/11 = 100/200/400/800 Hz
0x23   CTRL_REG4    BDU BLE FS1 FS0 – ST1 ST0 SIM; FS 00/01/10 = ±250/500/2000 °/s
0x27   STATUS_REG   ZYXOR ZOR YOR XOR ZYXDA ZDA YDA XDA
0x24   CTRL_REG5    bit 6 FIFO_EN (§7.6)
0x28…  OUT_X_L…     X, Y, Z; little-endian (BLE = 0) two's complement
0x2E   FIFO_CTRL    FM2:0, WTM4:0; 0x2F FIFO_SRC: WTM, OVRN, EMPTY, FSS4:0 — the 32-level
                    FIFO, shared with the L3GD20 and LSM303DLHC: :mod:`.st_fifo` (§5.2, 7.16, 7.17)
=====  ===========  ===========================================================

ST sub-address rule: a multi-byte transfer auto-increments only when the MSB of the
sub-address is set (0x80 | reg). An axis' data-available bit clears when its high byte is
read; ZYXDA clears when all three have been. Sensitivity 8.75 / 17.50 / 70 m°/s per digit.
I2C address 0x69 (SDO high, the GY-80) or 0x68.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import DEG2RAD, I2CDevice
from ahrs_service.drivers.parts.st_fifo import STFifoDriver

WHO_AM_I, CTRL_REG1, CTRL_REG2, CTRL_REG3, CTRL_REG4, CTRL_REG5 = 0x0F, 0x20, 0x21, 0x22, 0x23, 0x24
OUT_TEMP, STATUS_REG, OUT_X_L = 0x26, 0x27, 0x28
AUTO_INCREMENT = 0x80
PD_XYZ = 0x0F  # normal mode, X/Y/Z enabled
BDU = 0x80
BLE = 0x40
ZYXDA, ZYXOR = 0x08, 0x80
_UNPACK = struct.Struct("<3h").unpack


class L3G4200D(STFifoDriver, I2CDevice):
    """L3G4200D driver: angular rate in rad/s, sensor axes.

    range_dps: 250, 500 or 2000. rate_hz: 100, 200, 400 or 800 (bandwidth code 0, the
    narrowest filter of each rate). fifo: run the 32-level FIFO in stream mode with the
    ``watermark`` (samples); off, the output registers are polled.
    """

    PART = "L3G4200D"
    DEFAULT_ADDRESS = 0x69
    AUTO_INCREMENT_FLAG = AUTO_INCREMENT
    WHO_AM_I_VALUE = 0xD3
    #: output data rate (Hz) → DR bits
    RATES_HZ: dict[float, int] = {100: 0b00, 200: 0b01, 400: 0b10, 800: 0b11}
    #: full scale (°/s) → (FS bits, sensitivity in °/s per digit)
    RANGES_DPS: dict[int, tuple[int, float]] = {250: (0b00, 8.75e-3), 500: (0b01, 17.5e-3),
                                                2000: (0b10, 70e-3)}

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_dps: int = 2000,
                 rate_hz: float = 800, fifo: bool = False, watermark: int = 8, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        self.fifo, self.fifo_watermark = bool(fifo), int(watermark)
        if range_dps not in self.RANGES_DPS:
            raise ValueError(f"{self.PART} range_dps must be one of {sorted(self.RANGES_DPS)}, "
                             f"got {range_dps}")
        if rate_hz not in self.RATES_HZ:
            raise ValueError(f"{self.PART} rate_hz must be one of {sorted(self.RATES_HZ)}, "
                             f"got {rate_hz}")
        self.range_dps, self.rate_hz = range_dps, float(rate_hz)
        sens = self.RANGES_DPS[range_dps][1]
        self.scale = np.full(3, sens * DEG2RAD)
        self.full_scale = min(32767, int(range_dps / sens))
        self.overruns = 0

    def configure(self) -> None:
        """Checks WHO_AM_I, sets full scale with block data update, then rate and power-up."""
        self.check_identity(WHO_AM_I, bytes([self.WHO_AM_I_VALUE]), "WHO_AM_I")
        # BDU keeps the low and high byte of one axis from two different samples
        self.write_u8(CTRL_REG4, BDU | (self.RANGES_DPS[self.range_dps][0] << 4))
        self.write_u8(CTRL_REG1, (self.RATES_HZ[self.rate_hz] << 6) | PD_XYZ)
        if self.fifo:
            self.configure_fifo(self.fifo_watermark)

    def data_ready(self) -> bool:
        """STATUS_REG.ZYXDA: a new X/Y/Z set not read yet (overruns are counted, also in the
        shared diagnostics as ``extra["gyr_overruns"]``)."""
        status = self.read_u8(STATUS_REG)
        if status & ZYXOR:
            self.overruns += 1
            self.diagnostics.extra["gyr_overruns"] = self.overruns
        return bool(status & ZYXDA)

    def read_counts(self) -> tuple[int, int, int]:
        """Latest X, Y, Z counts in one 6-byte auto-increment burst (clears the DA bits)."""
        return _UNPACK(self.read_regs(AUTO_INCREMENT | OUT_X_L, 6))

    def read_if_new(self) -> tuple[int, int, int] | None:
        """Counts of a new sample, or None when ZYXDA is clear.

        The status byte is read on its own first: reading the data registers clears the DA
        bits, so a burst that also read data while nothing was ready could swallow a sample
        landing mid-transfer.
        """
        return self.read_counts() if self.data_ready() else None
