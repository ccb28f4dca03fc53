"""TDK InvenSense ICM-42688-P gyroscope + accelerometer (SPI or I2C), and its twin.

Register map used (user bank 0; TDK DS-000347, register descriptions in §14.x — Zephyr's
driver cites "datasheet 14.36" for PWR_MGMT0; the FIFO's 20-byte hi-res packet is the one
PX4 calls "Packet 4"):

=====  ==================  ===============================================================
0x11   DEVICE_CONFIG       bit 0 SOFT_RESET_CONFIG (wait 1 ms)
0x14   INT_CONFIG          INT1: bit 2 MODE (0 pulsed), bit 1 DRIVE (1 push-pull), bit 0
                           POLARITY (1 active high)
0x16   FIFO_CONFIG         FIFO_MODE 7:6: 00 bypass, 01 stream, 10 (and 11) stop-on-full
0x2D   INT_STATUS          bit 4 RESET_DONE_INT, bit 3 DATA_RDY_INT, bit 2 FIFO_THS_INT,
                           bit 1 FIFO_FULL_INT — cleared by reading (INT_CONFIG0 default)
0x2E   FIFO_COUNTH/L       bytes in the FIFO (INTF_CONFIG0: big-endian, in bytes), 0x2E…0x2F
0x30   FIFO_DATA           reads pop the FIFO (no address increment)
0x4B   SIGNAL_PATH_RESET   bit 1 FIFO_FLUSH
0x4C   INTF_CONFIG0        power-on 0x30: FIFO count and sensor data big-endian, count in bytes
0x4E   PWR_MGMT0           GYRO_MODE 3:2, ACCEL_MODE 1:0 (11 = low noise): 0x0F
0x4F   GYRO_CONFIG0        GYRO_FS_SEL 7:5 (000 = ±2000 °/s), GYRO_ODR 3:0
0x50   ACCEL_CONFIG0       ACCEL_FS_SEL 7:5 (000 = ±16 g), ACCEL_ODR 3:0
0x5F   FIFO_CONFIG1        bit 5 WM_GT_TH, 4 HIRES_EN, 3 TMST_FSYNC_EN, 2 TEMP_EN, 1 GYRO_EN,
                           0 ACCEL_EN
0x60   FIFO_CONFIG2/3      watermark in bytes, 11:0 (0x60 = 7:0, 0x61 = 11:8)
0x64   INT_CONFIG1         bit 6 INT_TPULSE_DURATION (1 = 8 µs), bit 5 INT_TDEASSERT_DISABLE,
                           bit 4 INT_ASYNC_RESET (power-on 1; must be cleared for proper INT1
                           operation); bits 6 and 5 are required at ODR ≥ 4 kHz
0x65   INT_SOURCE0         bit 2 FIFO_THS_INT1_EN, bit 1 FIFO_FULL_INT1_EN (power-on 0x10:
                           RESET_DONE_INT1_EN)
0x75   WHO_AM_I            0x47
0x76   REG_BANK_SEL        BANK_SEL 2:0, bank 0 after reset
=====  ==================  ===============================================================

ODR codes (GYRO_ODR / ACCEL_ODR): 3 = 8 kHz, 4 = 4 kHz, 5 = 2 kHz, 6 = 1 kHz, 15 = 500 Hz,
7 = 200 Hz, 8 = 100 Hz. FIFO: 2048 bytes = 102 hi-res packets (12.75 ms at 8 kHz, 102 ms at
1 kHz). Hi-res packet, big-endian: header (0x78: accel, gyro, 20-bit, ODR timestamp), accel
X/Y/Z bits 19:4, gyro X/Y/Z bits 19:4, temperature (16 bit, T = raw / 132.48 + 25 °C),
timestamp (16 bit, µs on the part's clock), then one byte per axis with accel bits 3:0 in
the high nibble and gyro bits 3:0 in the low one. In hi-res the FIFO data are ±16 g at
8192 LSB/g in 18 bits (two zero LSBs) and ±2000 °/s at 131 LSB/(°/s) in 19 bits (one zero
LSB), whatever the FS_SEL; −524288 marks an invalid sample. A header with bit 7 set marks an
empty FIFO. Start-up: 1 ms after the soft reset; after PWR_MGMT0 no register write for
200 µs, and the gyro needs 30 ms (accel 10 ms) to valid data — the driver waits 50 ms as
Zephyr does. SPI: mode 0 or 3, up to 24 MHz, read bit 0x80; I2C address 0x68 (AD0 low) or
0x69.

Verified against (2026-12-02; read, not copied): PX4-Autopilot
``src/drivers/imu/invensense/icm42688p/InvenSense_ICM42688P_registers.hpp`` (commit
032a09b5), ``ICM42688P.cpp`` (00d281a5) and ``ICM42688P.hpp`` (b8ffe13b); Linux
``drivers/iio/imu/inv_icm42600/inv_icm42600.h`` (05909cd9) and ``inv_icm42600_core.c``
(``inv_icm42600_irq_init``: "Deassert async reset for proper INT pin operation (cf
datasheet)"); Zephyr ``drivers/sensor/tdk/icm42688/icm42688_reg.h`` (20f7c36f),
``icm42688_common.c`` (1de8336b) and ``icm42688_decoder.c`` (06758ff2); ArduPilot
``libraries/AP_InertialSensor/AP_InertialSensor_Invensensev3.cpp`` (FIFODataHighRes, header
mask 0x78, FIFO_CONFIG 0x80, FIFO_FLUSH 2). Every address, bit and code above is confirmed by
at least two of them, with these exceptions: the 16-bit FIFO timestamp's unit (1 µs with
TMST_CONFIG.TMST_RES = 0, the power-on value) is confirmed only by the register bit names;
the twin's power-on TMST_CONFIG 0x23 only in its bit 0 (PX4: "TMST_EN … (default)") and
INT_SOURCE0 0x10 by one source (PX4's ICM-40609-D sibling header: "RESET_DONE_INT1_EN …
enabled by default"); the twin treats stream mode (FIFO_MODE 01) like stop-on-full; the SPI
modes and I2C addresses are from the datasheet only. Fixed in this check:
INT_CONFIG1 was never written (INT_ASYNC_RESET left at its power-on 1, no 8 µs pulse at
≥ 4 kHz: PX4 register header, Linux, Zephyr), and the gyro start-up wait cited a "45 ms"
that no source gives (PX4 and Zephyr: 30 ms gyro, 10 ms accel).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY, RegisterDevice
from ahrs_service.drivers.transport import RegisterTransport

DEVICE_CONFIG, INT_CONFIG, FIFO_CONFIG = 0x11, 0x14, 0x16
TEMP_DATA1, ACCEL_DATA_X1, GYRO_DATA_X1 = 0x1D, 0x1F, 0x25
INT_STATUS, FIFO_COUNTH, FIFO_COUNTL, FIFO_DATA = 0x2D, 0x2E, 0x2F, 0x30
SIGNAL_PATH_RESET, INTF_CONFIG0, PWR_MGMT0 = 0x4B, 0x4C, 0x4E
GYRO_CONFIG0, ACCEL_CONFIG0, TMST_CONFIG = 0x4F, 0x50, 0x54
FIFO_CONFIG1, FIFO_CONFIG2, FIFO_CONFIG3, INT_CONFIG1, INT_SOURCE0 = 0x5F, 0x60, 0x61, 0x64, 0x65
WHO_AM_I, REG_BANK_SEL = 0x75, 0x76
WHO_AM_I_VALUE = 0x47

SOFT_RESET = 0x01
FIFO_MODE_STOP_ON_FULL, FIFO_MODE_MASK = 0x80, 0xC0
FIFO_THS_INT, FIFO_FULL_INT, DATA_RDY_INT, RESET_DONE_INT = 0x04, 0x02, 0x08, 0x10
FIFO_FLUSH = 0x02
PWR_LOW_NOISE = 0x0F
FIFO_WM_GT_TH, FIFO_HIRES_EN, FIFO_TMST_FSYNC_EN = 0x20, 0x10, 0x08
FIFO_TEMP_EN, FIFO_GYRO_EN, FIFO_ACCEL_EN = 0x04, 0x02, 0x01
FIFO_THS_INT1_EN, FIFO_FULL_INT1_EN = 0x04, 0x02
INT1_PUSH_PULL_ACTIVE_HIGH = 0x03
# INT_CONFIG1 (PX4 register header, Linux inv_icm42600.h, Zephyr icm42688_reg.h)
INT_TPULSE_8US, INT_TDEASSERT_DISABLE, INT_ASYNC_RESET = 0x40, 0x20, 0x10
#: from this ODR up: 8 µs pulses, no de-assert time (Zephyr icm42688_common.c; the datasheet's
#: "required if ODR ≥ 4 kHz", quoted in PX4's ICM-40609-D register header)
FAST_ODR_HZ = 4000

ODR_CODES = {8000: 3, 4000: 4, 2000: 5, 1000: 6, 500: 15, 200: 7, 100: 8}
ODR_HZ = {c: float(r) for r, c in ODR_CODES.items()}
FIFO_BYTES = 2048
PACKET = 20
HIRES_HEADER = 0x78  # accel + gyro + 20-bit + ODR timestamp (§6.1 header bits 6:3)
HEADER_EMPTY = 0x80
INVALID_20BIT = -524288
HIRES_ACC_LSB_PER_G, HIRES_GYRO_LSB_PER_DPS = 8192.0, 131.0
TEMP_LSB_PER_C, TEMP_OFFSET_C = 132.48, 25.0
#: register-path sensitivity for GYRO_FS_SEL 0..3 / ACCEL_FS_SEL 0..3 (16-bit data registers)
GYRO_REG_LSB = (16.4, 32.8, 65.5, 131.0)
ACC_REG_LSB = (2048.0, 4096.0, 8192.0, 16384.0)
#: on the wire per burst besides the data: INT_STATUS + FIFO_COUNTH/L in one read
STATUS_BYTES = 3


#: one hi-res FIFO packet (§6.1) as NumPy reads it: the six 20-bit values' upper 16 bits
#: (accelerometer X, Y, Z, then gyro X, Y, Z) are big-endian int16 (so already sign-extended),
#: their lowest 4 bits in the three extension bytes (accelerometer: high nibbles, gyro: low)
_HIRES_PACKET = np.dtype([("header", "u1"), ("hi", ">i2", 6), ("temp", ">i2"), ("tmst", ">u2"), ("ext", "u1", 3)])
#: the bits a 20-bit value has beyond its counts: the accelerometer's 18, the gyro's 19 (§6.1)
_COUNT_SHIFT = np.array([2, 2, 2, 1, 1, 1])


def decode_hires(data: bytes) -> dict[str, np.ndarray]:
    """Decodes whole 20-byte hi-res packets: {"header", "temp", "tmst"} (n,) int32; the
    counts "acc" (n,3) 18-bit and "gyr" (n,3) 19-bit, and the 20-bit values as read, "acc20"
    and "gyr20" (n,3), all int64 views of two (n,6) arrays, accelerometer first (the 20-bit
    one is "all20": :func:`invalid_packets` looks at all six values at once).

    A 20-bit two's complement value is its upper 16 bits read as a signed int16, times 16,
    plus its lowest 4 bits: read so from the packet's bytes it needs no sign fix-up, and the
    six values of the packets take one shift and one OR together, their counts one more
    shift (a few NumPy calls a burst: every burst at 8 kHz; int64, as the rows keep them)."""
    p = np.frombuffer(data, dtype=_HIRES_PACKET)
    ext = p["ext"]
    all20 = p["hi"].astype(np.int64)
    all20 <<= 4
    all20 |= np.concatenate((ext >> 4, ext & 0x0F), axis=1)  # the lowest bits, in the order of "hi"
    counts = all20 >> _COUNT_SHIFT
    return {"header": p["header"].astype(np.int32), "all20": all20, "acc20": all20[:, :3], "gyr20": all20[:, 3:],
            "acc": counts[:, :3], "gyr": counts[:, 3:],
            "temp": p["temp"].astype(np.int32), "tmst": p["tmst"].astype(np.int32)}


def invalid_packets(packets: dict[str, np.ndarray]) -> np.ndarray | None:
    """Which of :func:`decode_hires`' packets are not usable rows — not a hi-res packet
    (header), or a reading the part marks invalid (−524288, the most negative 20-bit value:
    the sensor off or not ready): an (n,) bool mask, or None when every packet is usable
    (the usual burst, told apart in three NumPy calls)."""
    header, all20 = packets["header"], packets["all20"]
    other_header = (header & 0xFC) != HIRES_HEADER
    # no value is below the invalid marker: none is the marker when the least is above it
    if len(header) == 0 or (int(all20.min()) > INVALID_20BIT and not other_header.any()):
        return None
    return other_header | (all20 == INVALID_20BIT).any(axis=1)


class ICM42688P(RegisterDevice):
    """ICM-42688-P driver: hi-res FIFO packets at ``odr_hz`` with a FIFO watermark.

    odr_hz: 100/200/500/1000/2000/4000/8000 (gyro and accelerometer alike).
    watermark: samples per FIFO burst (the watermark interrupt fires at it), 1…102.
    """

    PART = "ICM-42688-P"
    BYTES_PER_SAMPLE = PACKET
    FIFO_SAMPLES = FIFO_BYTES // PACKET

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1000, watermark: int = 8,
                 **kw: Any) -> None:
        super().__init__(transport, **kw)
        if odr_hz not in ODR_CODES:
            raise ValueError(f"ICM-42688-P odr_hz must be one of {sorted(ODR_CODES)}, got {odr_hz}")
        if not isinstance(watermark, int) or not 1 <= watermark <= self.FIFO_SAMPLES - 2:
            raise ValueError(f"ICM-42688-P watermark must be 1…{self.FIFO_SAMPLES - 2} samples, "
                             f"got {watermark!r}")
        self.odr_hz, self.watermark = float(odr_hz), watermark
        self.gyro_scale = DEG2RAD / HIRES_GYRO_LSB_PER_DPS
        self.acc_scale = STANDARD_GRAVITY / HIRES_ACC_LSB_PER_G
        # saturation: the hi-res ranges, 18/19 bits
        self.acc_full_scale, self.gyro_full_scale = (1 << 17) - 1, (1 << 18) - 1

    def configure(self) -> None:
        """Identity, soft reset, low-noise mode at ``odr_hz``, hi-res FIFO stop-on-full with
        the watermark, INT1 push-pull active high on watermark and full."""
        t = self.transport
        self.write_u8(REG_BANK_SEL, 0)
        self.check_identity(WHO_AM_I, (WHO_AM_I_VALUE,), "WHO_AM_I")
        self.write_u8(DEVICE_CONFIG, SOFT_RESET)
        t.sleep(0.001)
        self.write_u8(REG_BANK_SEL, 0)
        code = ODR_CODES[int(self.odr_hz)]
        self.write_u8(GYRO_CONFIG0, 0 << 5 | code)  # ±2000 °/s
        self.write_u8(ACCEL_CONFIG0, 0 << 5 | code)  # ±16 g
        self.write_u8(INT_CONFIG, INT1_PUSH_PULL_ACTIVE_HIGH)
        # INT_ASYNC_RESET cleared for proper INT1 operation (Linux inv_icm42600_irq_init, PX4
        # register header); 8 µs pulses without de-assert time at ≥ 4 kHz (Zephyr)
        fast = self.odr_hz >= FAST_ODR_HZ
        self.write_u8(INT_CONFIG1, (INT_TPULSE_8US | INT_TDEASSERT_DISABLE) if fast else 0x00)
        self.write_u8(FIFO_CONFIG, FIFO_MODE_STOP_ON_FULL)
        self.write_u8(FIFO_CONFIG1, FIFO_WM_GT_TH | FIFO_HIRES_EN | FIFO_TMST_FSYNC_EN
                      | FIFO_TEMP_EN | FIFO_GYRO_EN | FIFO_ACCEL_EN)
        wm = self.watermark * PACKET
        self.write_u8(FIFO_CONFIG2, wm & 0xFF)
        self.write_u8(FIFO_CONFIG3, wm >> 8)
        self.write_u8(INT_SOURCE0, FIFO_THS_INT1_EN | FIFO_FULL_INT1_EN)
        self.write_u8(PWR_MGMT0, PWR_LOW_NOISE)
        # no write for 200 µs, gyro 30 ms / accel 10 ms to valid data (PX4 ICM42688P.cpp,
        # Zephyr icm42688_common.c, which waits 50 ms)
        t.sleep(0.050)
        self.flush()

    def flush(self) -> None:
        """Empties the FIFO (after an overflow), then reads INT_STATUS: a FIFO_FULL raised
        before the flush (by samples turned away while the full FIFO was being read) must not
        show at the next read as a new overflow."""
        self.write_u8(SIGNAL_PATH_RESET, FIFO_FLUSH)
        self.read_status()

    def read_status(self) -> tuple[int, int]:
        """(INT_STATUS, FIFO count in bytes) in one 3-byte read (reading clears INT_STATUS)."""
        b = self.read_regs(INT_STATUS, STATUS_BYTES)
        return b[0], (b[1] << 8) | b[2]

    def read_packets(self, count_bytes: int) -> dict[str, np.ndarray]:
        """The whole packets among ``count_bytes``, decoded (:func:`decode_hires`)."""
        n = min(count_bytes, FIFO_BYTES) // PACKET
        # FIFO_DATA is a byte stream: transfers may split packets (full 32-byte SMBus blocks)
        return decode_hires(self.read_fifo(FIFO_DATA, n * PACKET))

    def read_status_and_packets(self, count_bytes: int) -> tuple[int, int, dict[str, np.ndarray]]:
        """(INT_STATUS, FIFO count in bytes, the whole packets among ``count_bytes`` decoded),
        read from INT_STATUS on: the address increments through FIFO_COUNTH/L to FIFO_DATA,
        which does not increment, so status, count and data come in one transfer (PX4's
        ``FIFOTransferBuffer``; on I2C the first 32-byte block). The status is the one of the
        moment the data start: a FIFO_FULL raised since the level read (a host held between
        the two at a nearly full FIFO) shows with the packets it follows."""
        n = min(count_bytes, FIFO_BYTES) // PACKET * PACKET
        head = self.read_regs(INT_STATUS, min(STATUS_BYTES + n, self.transport.max_read))
        data = head[STATUS_BYTES:]
        if len(data) < n:
            data += self.read_fifo(FIFO_DATA, n - len(data))
        return head[0], (head[1] << 8) | head[2], decode_hires(data)

    @staticmethod
    def temperature_c(raw: np.ndarray) -> np.ndarray:
        return raw / TEMP_LSB_PER_C + TEMP_OFFSET_C
