"""Analog Devices ADXL345 3-axis accelerometer (the GY-80's accelerometer), and its twin.

Register map used (datasheet Rev. E):

=====  ============  ==========================================================
0x00   DEVID         0xE5
0x2C   BW_RATE       bits 3:0 rate code, ODR = 3200 Hz / 2^(15 − code)
0x2D   POWER_CTL     bit 3 Measure (0 = standby, the power-on state)
0x30   INT_SOURCE    bit 7 DATA_READY (set on new data, cleared when the data are read)
0x31   DATA_FORMAT   bit 3 FULL_RES, bit 2 Justify, bits 1:0 range ±2/4/8/16 g
0x32…  DATAX0…DATAZ1 X, Y, Z; little-endian two's complement, right-justified
0x38   FIFO_CTL      FIFO_MODE 7:6 (00 bypass, 01 FIFO: stops when full, 10 stream: a full
                     FIFO overwrites its oldest entry, 11 trigger), bit 5 Trigger, Samples
                     4:0 the watermark (entries) ("Register 0x38—FIFO_CTL", "FIFO")
0x39   FIFO_STATUS   bit 7 FIFO_TRIG, Entries 5:0: entries stored (0…32) ("Register 0x39")
0x30   INT_SOURCE    with the FIFO on: bit 1 Watermark (Entries ≥ Samples), bit 0 Overrun
                     (the FIFO is filled; cleared as its contents are read)
=====  ============  ==========================================================

FIFO ("FIFO" and "Retrieving Data from FIFO" in the datasheet): 32 entries of X, Y, Z.
With it on, DATAX0…DATAZ1 hold the oldest entry, and a read of the data registers pops it
when it ends: one entry per transfer (the address does not roll back to DATAX0), so n
entries take n 6-byte reads. The driver runs stream mode; an overrun is flagged only as
"filled", so the loss is estimated from the sensor clock
(:class:`~ahrs_service.drivers.fifo.FifoTimeline`). Bypass mode empties the FIFO.

In I2C mode multi-byte reads auto-increment (no sub-address flag). The driver uses
FULL_RES, so the scale is 3.9 mg/LSB (256 LSB/g) in every range and the register width is
10 + log2(range/2) bits. I2C address 0x53 (ALT ADDRESS low, the GY-80) or 0x1D.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import STANDARD_GRAVITY, FifoLayout, FifoStatus, I2CDevice
from ahrs_service.drivers.parts.st_fifo import FrameFifoDriver

DEVID, BW_RATE, POWER_CTL, INT_SOURCE, DATA_FORMAT, DATAX0 = 0x00, 0x2C, 0x2D, 0x30, 0x31, 0x32
FIFO_CTL, FIFO_STATUS = 0x38, 0x39
FIFO_BYPASS, FIFO_FIFO, FIFO_STREAM = 0b00, 0b01, 0b10
WATERMARK = 0x02  # INT_SOURCE bit 1
FIFO_ENTRIES = 32
#: one entry per 6-byte read of DATAX0…DATAZ1
FIFO_LAYOUT = FifoLayout(depth_frames=FIFO_ENTRIES, frame_bytes=6, data_register=DATAX0,
                         frames_per_transfer=1)
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


class ADXL345(FrameFifoDriver, I2CDevice):
    """ADXL345 driver: specific force in m/s², sensor axes.

    range_g: 2, 4, 8 or 16 (full resolution). rate_hz: 6.25 … 3200 (powers of two × 6.25).
    fifo: run the 32-entry FIFO in stream mode with the ``watermark`` (entries).
    """

    PART = "ADXL345"
    DEFAULT_ADDRESS = 0x53
    fifo_layout = FIFO_LAYOUT
    FIFO_CTRL, FM_SHIFT = FIFO_CTL, 6  # FIFO_MODE in bits 7:6

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_g: int = 8,
                 rate_hz: float = 800, fifo: bool = False, watermark: int = 8, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        self.fifo = bool(fifo)
        if not 1 <= watermark < FIFO_ENTRIES:
            raise ValueError(f"ADXL345 FIFO watermark must be 1…{FIFO_ENTRIES - 1}, got {watermark}")
        self.fifo_watermark = int(watermark)
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
        if self.fifo:
            self.fifo_reset()
        self.write_u8(POWER_CTL, MEASURE)

    # ---------------------------------------------------------------- FIFO
    # fifo_reset (bypass mode empties it, then stream mode with the watermark) and read_fifo
    # (one 6-byte read per entry: FIFO_LAYOUT) are FrameFifoDriver's
    def fifo_status(self) -> FifoStatus:
        """Stored entries (FIFO_STATUS) and whether the FIFO had filled (INT_SOURCE.Overrun)."""
        overrun = bool(self.read_u8(INT_SOURCE) & OVERRUN)
        t = self.transport.now_ns()
        entries = self.read_u8(FIFO_STATUS) & 0x3F
        return FifoStatus(entries, overrun or entries >= FIFO_ENTRIES, t)

    def data_ready(self) -> bool:
        """INT_SOURCE.DATA_READY: a sample not read yet."""
        return bool(self.read_u8(INT_SOURCE) & DATA_READY)

    def read_counts(self) -> tuple[int, int, int]:
        """Latest X, Y, Z counts in one 6-byte burst (clears DATA_READY)."""
        return _UNPACK(self.read_regs(DATAX0, 6))

    def read_if_new(self) -> tuple[int, int, int] | None:
        """Counts of a new sample, or None when DATA_READY is clear."""
        return self.read_counts() if self.data_ready() else None
