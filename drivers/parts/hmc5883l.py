"""Honeywell HMC5883L 3-axis magnetometer (the GY-80's compass), and its twin.

Register map used (datasheet Form #900405 Rev E):

=====  ==========  ============================================================
0x00   CRA         bit 7 = 0, MA1:0 samples averaged (1/2/4/8), DO2:0 rate, MS1:0 bias
0x01   CRB         GN2:0 in bits 7:5: gain (±0.88 … ±8.1 Ga)
0x02   MODE        MD1:0: 00 continuous, 01 single (power-on), 1x idle
0x03…  DATA        X MSB, X LSB, **Z** MSB, Z LSB, **Y** MSB, Y LSB — big-endian, X Z Y
0x09   STATUS      bit 1 LOCK, bit 0 RDY
0x0A…  ID A/B/C    'H' '4' '3'
=====  ==========  ============================================================

Data range −2048…2047; an ADC overflow reads −4096 on that axis. Register pointer: after
0x09 it wraps to 0x03, after 0x0C to 0x00, else +1 (no sub-address flag needed).

Data-ready: RDY is *not* cleared by reading — it drops only for ~250 µs while the part
writes a new measurement — so it cannot tell "already read" from "new". The driver decides
newness itself: from ¾ of an output period after the previous fresh reading on, it reads the
data (when RDY is set) and takes them as new when they differ from the previous reading
(different data cannot be the same measurement), or when a full period plus a 5 %
oscillator margin has passed (a measurement that happens to repeat the previous values). It
may skip a measurement, never return one twice. The first measurement after configuration
is dropped (after a gain change it still uses the old gain). Reading all six data bytes in
one burst also releases the part's LOCK (data registers held after a partial read).

The identification registers 'H43' are shared by the LSM303DLHC magnetometer, which sits at
the same address 0x1E: the ID check tells a Honeywell-style magnetometer is there, the board
setting says which one.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import I2CDevice

CRA, CRB, MODE, DATA, STATUS, IDA = 0x00, 0x01, 0x02, 0x03, 0x09, 0x0A
IDENTITY = b"H43"
RDY, LOCK = 0x01, 0x02
CONTINUOUS = 0x00
OVERFLOW = -4096
UT_PER_GAUSS = 100.0
_UNPACK = struct.Struct(">3h").unpack
_AVERAGING = {1: 0b00, 2: 0b01, 4: 0b10, 8: 0b11}


class HoneywellStyleMagnetometer(I2CDevice):
    """Shared driver of the HMC5883L and the LSM303DLHC magnetometer (same register layout).

    range_ga: full scale in gauss (selects the gain). rate_hz: continuous-mode output rate.
    Field out in µT, sensor axes (X, Y, Z reordered from the X, Z, Y registers).
    """

    #: range (Ga) → (GN code, LSB/Ga for X and Y, LSB/Ga for Z)
    GAINS: dict[float, tuple[int, float, float]] = {}
    #: output rate (Hz) → DO code
    RATES_HZ: dict[float, int] = {}
    RATE_MARGIN = 1.05
    MIN_COUNT, MAX_COUNT = -2048, 2047

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_ga: float = 1.3,
                 rate_hz: float = 75, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        if range_ga not in self.GAINS:
            raise ValueError(f"{self.PART} range_ga must be one of {sorted(self.GAINS)}, got {range_ga}")
        if rate_hz not in self.RATES_HZ:
            raise ValueError(f"{self.PART} rate_hz must be one of {sorted(self.RATES_HZ)}, "
                             f"got {rate_hz}")
        self.range_ga, self.rate_hz = range_ga, float(rate_hz)
        _, xy, z = self.GAINS[range_ga]
        self.scale = np.array([UT_PER_GAUSS / xy, UT_PER_GAUSS / xy, UT_PER_GAUSS / z])
        self.full_scale = self.MAX_COUNT
        self._gate_ns = int(self.RATE_MARGIN * 1e9 / self.rate_hz)
        self._poll_ns = int(0.75e9 / self.rate_hz)
        self._last_new_ns: int | None = None
        self._last_counts: tuple[int, int, int] | None = None
        self._skip = 1

    def cra_value(self) -> int:
        """Configuration register A for the chosen rate."""
        return self.RATES_HZ[self.rate_hz] << 2

    def configure(self) -> None:
        """Checks 'H43', writes rate (CRA), gain (CRB) and continuous mode."""
        self.check_identity(IDA, IDENTITY, "identification registers A/B/C")
        self.write_u8(CRA, self.cra_value())
        self.write_u8(CRB, self.GAINS[self.range_ga][0] << 5)
        self.write_u8(MODE, CONTINUOUS)
        self._last_new_ns, self._last_counts, self._skip = None, None, 1

    def read_counts(self) -> tuple[int, int, int]:
        """X, Y, Z counts from one 6-byte burst of the X, Z, Y big-endian registers."""
        x, z, y = _UNPACK(self.read_regs(DATA, 6))
        return x, y, z

    def read_if_new(self, t_ns: int) -> tuple[int, int, int] | None:
        """Counts of a measurement not returned before, or None (see the module notes).

        t_ns: time of this read (ns, the board's clock), used to pace reads at the output rate.
        """
        last = self._last_new_ns
        if last is not None and t_ns - last < self._poll_ns:
            return None
        if not self.read_u8(STATUS) & RDY:
            return None
        counts = self.read_counts()
        if last is None:  # first call after configure: the registers' content is the reference
            self._last_new_ns, self._last_counts = t_ns, counts
            return None
        if counts == self._last_counts and t_ns - last < self._gate_ns:
            return None
        self._last_new_ns, self._last_counts = t_ns, counts
        if self._skip:
            self._skip -= 1
            return None
        return counts

    def is_saturated(self, counts) -> bool:
        """Any axis at the register limit, or the part's ADC overflow code −4096."""
        lo, hi = self.MIN_COUNT, self.MAX_COUNT
        return any(c >= hi or c <= lo for c in counts)


class HMC5883L(HoneywellStyleMagnetometer):
    """HMC5883L driver. range_ga: 0.88, 1.3, 1.9, 2.5, 4.0, 4.7, 5.6, 8.1; rate_hz: 0.75 … 75;
    averaging: 1, 2, 4 or 8 samples per output."""

    PART = "HMC5883L"
    DEFAULT_ADDRESS = 0x1E
    GAINS = {0.88: (0, 1370, 1370), 1.3: (1, 1090, 1090), 1.9: (2, 820, 820),
             2.5: (3, 660, 660), 4.0: (4, 440, 440), 4.7: (5, 390, 390), 5.6: (6, 330, 330),
             8.1: (7, 230, 230)}
    RATES_HZ = {0.75: 0, 1.5: 1, 3: 2, 7.5: 3, 15: 4, 30: 5, 75: 6}

    def __init__(self, bus: I2CBus, address: int | None = None, *, range_ga: float = 1.3,
                 rate_hz: float = 75, averaging: int = 8, **kw: Any) -> None:
        super().__init__(bus, address, range_ga=range_ga, rate_hz=rate_hz, **kw)
        if averaging not in _AVERAGING:
            raise ValueError(f"HMC5883L averaging must be one of {sorted(_AVERAGING)}, got {averaging}")
        self.averaging = averaging

    def cra_value(self) -> int:
        return (_AVERAGING[self.averaging] << 5) | super().cra_value()
