"""Analog Devices ADXL345 3-axis accelerometer (the GY-80's accelerometer), and its twin.

Register map used (datasheet Rev. E):

=====  ============  ==========================================================
0x00   DEVID         0xE5
0x2C   BW_RATE       bits 3:0 rate code, ODR = 3200 Hz / 2^(15 − code)
0x2D   POWER_CTL     bit 3 Measure (0 = standby, the power-on state)
0x30   INT_SOURCE    bit 7 DATA_READY (set on new data, cleared when the data are read)
0x31   DATA_FORMAT   bit 3 FULL_RES, bit 2 Justify, bits 1:0 range ±2/4/8/16 g
0x32…  DATAX0…DATAZ1 X, Y, Z; little-endian two's complement, right-justified
=====  ============  ==========================================================

In I2C mode multi-byte reads auto-increment (no sub-address flag). The driver uses
FULL_RES, so the scale is 3.9 mg/LSB (256 LSB/g) in every range and the register width is
10 + log2(range/2) bits. I2C address 0x53 (ALT ADDRESS low, the GY-80) or 0x1D.
"""

from __future__ import annotations

from typing import Any

import struct

import numpy as np

from ahrs_service.drivers.i2c.bus import I2CBus
from ahrs_service.drivers.i2c.device import (
    STANDARD_GRAVITY,
    I2CDevice,
    SimulatedRegisterDevice,
    i16_bytes,
    to_counts,
)

DEVID, BW_RATE, POWER_CTL, INT_SOURCE, DATA_FORMAT, DATAX0 = 0x00, 0x2C, 0x2D, 0x30, 0x31, 0x32
DEVID_VALUE = 0xE5
MEASURE = 0x08
DATA_READY = 0x80
OVERRUN = 0x01
FULL_RES = 0x08
#: full-resolution sensitivity, LSB per g (3.9 mg/LSB)
LSB_PER_G = 256.0
RANGES_G = {2: 0b00, 4: 0b01, 8: 0b10, 16: 0b11}
#: ODR (Hz) → BW_RATE code
RATES_HZ = {3200 / 2 ** (15 - c): c for c in range(6, 16)}
_UNPACK = struct.Struct("<3h").unpack


class ADXL345(I2CDevice):
    """ADXL345 driver: specific force in m/s², sensor axes.

    range_g: 2, 4, 8 or 16 (full resolution). rate_hz: 6.25 … 3200 (powers of two × 6.25).
    """

    PART = "ADXL345"
    DEFAULT_ADDRESS = 0x53

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_g: int = 8,
                 rate_hz: float = 800, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        if range_g not in RANGES_G:
            raise ValueError(f"ADXL345 range_g must be one of {sorted(RANGES_G)}, got {range_g}")
        if rate_hz not in RATES_HZ:
            raise ValueError(f"ADXL345 rate_hz must be one of {sorted(RATES_HZ)}, got {rate_hz}")
        self.range_g, self.rate_hz = range_g, float(rate_hz)
        self.scale = np.full(3, STANDARD_GRAVITY / LSB_PER_G)
        # register width grows with the range in full resolution: 10 bits at ±2 g … 13 at ±16 g
        self.full_scale = int(range_g * LSB_PER_G) - 1

    def configure(self) -> None:
        """Checks DEVID, sets rate and full-resolution range, then starts measuring."""
        self.check_identity(DEVID, bytes([DEVID_VALUE]), "DEVID")
        self.write_u8(POWER_CTL, 0x00)  # standby while reconfiguring, as the datasheet advises
        self.write_u8(BW_RATE, RATES_HZ[self.rate_hz])
        self.write_u8(DATA_FORMAT, FULL_RES | RANGES_G[self.range_g])
        self.write_u8(POWER_CTL, MEASURE)

    def data_ready(self) -> bool:
        """INT_SOURCE.DATA_READY: a sample not read yet."""
        return bool(self.read_u8(INT_SOURCE) & DATA_READY)

    def read_counts(self) -> tuple[int, int, int]:
        """Latest X, Y, Z counts in one 6-byte burst (clears DATA_READY)."""
        return _UNPACK(bytes(self.read_block(DATAX0, 6)))

    def read_if_new(self) -> tuple[int, int, int] | None:
        """Counts of a new sample, or None when DATA_READY is clear."""
        return self.read_counts() if self.data_ready() else None


class SimulatedADXL345(SimulatedRegisterDevice):
    """Simulated ADXL345: latches physics "acc" at BW_RATE while POWER_CTL.Measure is set."""

    PART = "ADXL345"
    DEFAULT_ADDRESS = 0x53
    POWER_ON = {DEVID: DEVID_VALUE, BW_RATE: 0x0A, INT_SOURCE: 0x02}
    WRITABLE = frozenset({BW_RATE, POWER_CTL, DATA_FORMAT} | set(range(0x1D, 0x2B))
                         | {0x2E, 0x2F, 0x38})

    def rate_hz(self) -> float:
        return 3200.0 / 2 ** (15 - (self.regs[BW_RATE] & 0x0F))

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == POWER_CTL:
            if value & MEASURE and not old & MEASURE:
                self.restart_measurement(now)
            elif not value & MEASURE:
                self.stop_measurement()
        elif reg == BW_RATE and self._t0 is not None:
            self.restart_measurement(now)

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        fmt = self.regs[DATA_FORMAT]
        rng = 2 << (fmt & 0b11)
        if fmt & FULL_RES:
            lsb_per_g, bits = LSB_PER_G, 10 + (fmt & 0b11)
        else:  # 10-bit mode: the scale follows the range
            lsb_per_g, bits = 512.0 / rng, 10
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        lsb = STANDARD_GRAVITY / lsb_per_g
        status = self.regs[INT_SOURCE]
        if status & DATA_READY or skipped:
            status |= OVERRUN
        self.regs[INT_SOURCE] = status | DATA_READY
        for i, a in enumerate(phys["acc"]):
            c = to_counts(a, lsb, lo, hi)
            if fmt & 0x04:  # left-justified (MSB) mode
                c <<= 16 - bits
            self.regs[DATAX0 + 2 * i: DATAX0 + 2 * i + 2] = bytes(i16_bytes(c, False))

    def on_read(self, regs: list[int], now: float) -> None:
        if any(DATAX0 <= r <= DATAX0 + 5 for r in regs):
            self.regs[INT_SOURCE] &= ~(DATA_READY | OVERRUN) & 0xFF
