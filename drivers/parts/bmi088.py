"""Bosch BMI088: accelerometer and gyroscope on two dies, each with its own chip select,
registers and FIFO (SPI), and their twins.

Accelerometer die (Bosch BST-BMI088-DS001, accelerometer register descriptions §5.3.x — PX4
cites "Datasheet 5.3.7" for TEMP_MSB/LSB; the FIFO chapter's frame formats):

=====  ==============  ===============================================================
0x00   ACC_CHIP_ID     0x1E
0x24   FIFO_LENGTH_0/1 bytes in the FIFO, 13:0 (0x24 = 7:0, 0x25 = 13:8)
0x26   FIFO_DATA       frames: 0x84 + 6 data bytes (X, Y, Z little-endian), 0x40 + 1 skip,
                       0x44 + 3 sensortime, 0x48 + 1 config change, 0x50 + 1 drop; 0x80 = empty
0x40   ACC_CONF        bwp 7:4 (0xA normal), odr 3:0 (0x08 100 … 0x0C 1600 Hz)
0x41   ACC_RANGE       0…3: ±3/6/12/24 g
0x46   FIFO_WTM_0/1    watermark in bytes, 12:0
0x48   FIFO_CONFIG_0   bit 1 must be 1; bit 0 mode: 1 FIFO (stop when full), 0 stream
0x49   FIFO_CONFIG_1   bit 6 acc_en; bit 4 must be 1
0x53   INT1_IO_CTRL    bit 3 out, bit 2 open-drain, bit 1 active high
0x58   INT_MAP_DATA    bit 1 int1_fwm, bit 0 int1_ffull
0x7C   ACC_PWR_CONF    0x03 suspend (power-on), 0x00 active
0x7D   ACC_PWR_CTRL    0x00 off (power-on), 0x04 on
0x7E   ACC_SOFTRESET   0xB6 soft reset (1 ms); 0xB0 flushes the FIFO
=====  ==============  ===============================================================

SPI on the accelerometer (§6.1 / §6.1.2, as PX4 quotes them): a read returns one **dummy
byte** before the data; after power-on the die listens on I2C until a rising edge on CSB1 —
the driver's first access is a throw-away read of ACC_CHIP_ID. Sensitivity:
32768 / (1.5 · 2^(range+1)) LSB/g. FIFO 1024 bytes = 146 accelerometer frames of 7 bytes; an
empty FIFO's length reads 0x8000 (bit 15, masked off with the 13:8 field). Power: ACC_PWR_CONF
then ACC_PWR_CTRL, 5 ms each (Bosch's BMI08_POWER_CONFIG_DELAY).

Gyroscope die (gyroscope register descriptions; the FIFO chapter):

=====  ==================  ===========================================================
0x00   GYRO_CHIP_ID        0x0F
0x0E   FIFO_STATUS         bit 7 overrun, 6:0 frames in the FIFO
0x0F   GYRO_RANGE          0…4: ±2000/1000/500/250/125 °/s
0x10   GYRO_BANDWIDTH      ODR/filter: 0x01 2000/230, 0x02 1000/116, 0x03 400/47,
                           0x04 200/23, 0x05 100/12 Hz (bit 7 reads 1)
0x11   GYRO_LPM1           0x00 normal
0x14   GYRO_SOFTRESET      0xB6
0x15   GYRO_INT_CTRL       bit 6 FIFO interrupt on
0x16   INT3_INT4_IO_CONF   bit 1 int3 open-drain, bit 0 int3 active high
0x18   INT3_INT4_IO_MAP    bit 2 FIFO on INT3
0x1E   FIFO_WM_ENABLE      0x88 watermark interrupt on, 0x08 off
0x3D   FIFO_CONFIG_0       watermark level, frames 6:0; a write clears the FIFO buffer
0x3E   FIFO_CONFIG_1       mode 7:6: 0x40 FIFO (stop when full), 0x80 stream; a write is the
                           only way to clear the overrun flag
0x3F   FIFO_DATA           6-byte frames X, Y, Z little-endian
=====  ==================  ===========================================================

No dummy byte on the gyroscope. FIFO 100 frames. Sensitivity 16.384 · 2^range LSB/(°/s).
Soft reset: 0xB6, then 30 ms.

Verified against (2026-12-02; read, not copied): Bosch ``BMI08x_SensorAPI`` ``bmi08_defs.h``
and ``bmi08.h`` (commit c1ed227: every gyro register, bit and code above, ACC_CONF
bandwidth/ODR codes, ACC_PWR_* values, INT1_IO_CONF and INT map bits, FIFO_CONFIG_1
acc_en, frame headers, 0xB6, the 1 ms / 30 ms / 5 ms delays, BMI088 accel range codes);
PX4-Autopilot ``src/drivers/imu/bosch/bmi088/Bosch_BMI088_Accelerometer_Registers.hpp``
(1e944a5a), ``Bosch_BMI088_Gyroscope_Registers.hpp`` (15c4f088),
``BMI088_Accelerometer.cpp`` (9ffa0096) and ``BMI088_Gyroscope.cpp`` (accel FIFO addresses,
FIFO_CONFIG_0/1 "must be 1" bits, 1024-byte / 100-frame FIFOs, FIFO_WM_ENABLE 0x88/0x08, the
dummy byte and first CSB1 edge, 0x8000 = empty); ArduPilot
``libraries/AP_InertialSensor/AP_InertialSensor_BMI088.cpp`` (05ac7a31: addresses, 0xAC,
±24 g scale, FIFO_CONFIG1 0x50, frame headers, 30 ms gyro reset) and Zephyr
``drivers/sensor/bosch/bmi08x`` (``bmi08x_accel_stream.c``: FIFO_WTM 12:0, FIFO_CONFIG_0
0x03, FIFO_CONFIG_1 0x50, INT map 0x03, INT1_IO_CONF 0x0A; ``bmi08x.h``: range codes).
PX4's own gyro header gives 0x04/0x05 for ±250/±125 °/s; Bosch and Zephyr give 0x03/0x04,
which the driver uses. Confirmed by one source only: the accelerometer's FIFO flush command
0xB0 (PX4, its SPI and I2C drivers) and the gyro's FIFO_CONFIG_0/1 clearing rules (PX4,
quoting the datasheet); Bosch's API writes FIFO_WM_ENABLE as 0x80 where PX4 (and this
driver) write 0x88. Power-on values in the accelerometer twin other than ACC_PWR_*
(ACC_CONF 0xA8, ACC_RANGE 0x01, FIFO_CONFIG 0x02/0x10, FIFO_WTM 0x0200) are unconfirmed.
Fixed in this check: the accelerometer FIFO was "cleared" by rewriting FIFO_CONFIG_0, which
no source supports (now the 0xB0 command, also at the end of configure); the gyro FIFO reset
wrote only FIFO_CONFIG_1 (now FIFO_CONFIG_0, which clears the buffer, then FIFO_CONFIG_1,
which clears the overrun flag); the twins model exactly those rules.

The dies run on separate oscillators: the board pairs them by the rule in
:class:`~ahrs_service.drivers.boards.transport.BMI088Board`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY, RegisterDevice
from ahrs_service.drivers.transport import RegisterTransport

# accelerometer die
ACC_CHIP_ID, ACC_CHIP_ID_VALUE = 0x00, 0x1E
FIFO_LENGTH_0, ACC_FIFO_DATA = 0x24, 0x26
ACC_CONF, ACC_RANGE, FIFO_WTM_0, FIFO_WTM_1 = 0x40, 0x41, 0x46, 0x47
ACC_FIFO_CONFIG_0, ACC_FIFO_CONFIG_1 = 0x48, 0x49
INT1_IO_CTRL, INT_MAP_DATA = 0x53, 0x58
ACC_PWR_CONF, ACC_PWR_CTRL, ACC_SOFTRESET = 0x7C, 0x7D, 0x7E
ACC_ODR_CODES = {100: 0x08, 200: 0x09, 400: 0x0A, 800: 0x0B, 1600: 0x0C}
ACC_ODR_HZ = {c: float(r) for r, c in ACC_ODR_CODES.items()}
ACC_RANGES_G = {3: 0, 6: 1, 12: 2, 24: 3}
ACC_FRAME_HEADER, ACC_FRAME, ACC_EMPTY = 0x84, 7, 0x80
ACC_FIFO_BYTES = 1024
SOFTRESET_CMD = 0xB6
ACC_FIFO_FLUSH_CMD = 0xB0  # to ACC_SOFTRESET (PX4 BMI088_Accelerometer.cpp FIFOReset)

# gyroscope die
GYRO_CHIP_ID, GYRO_CHIP_ID_VALUE = 0x00, 0x0F
FIFO_STATUS, GYRO_RANGE, GYRO_BANDWIDTH, GYRO_LPM1 = 0x0E, 0x0F, 0x10, 0x11
GYRO_SOFTRESET, GYRO_INT_CTRL, INT3_INT4_IO_CONF, INT3_INT4_IO_MAP = 0x14, 0x15, 0x16, 0x18
FIFO_WM_ENABLE, GYRO_FIFO_CONFIG_0, GYRO_FIFO_CONFIG_1, GYRO_FIFO_DATA = 0x1E, 0x3D, 0x3E, 0x3F
GYRO_ODR_CODES = {2000: 0x01, 1000: 0x02, 400: 0x03, 200: 0x04, 100: 0x05}
GYRO_ODR_HZ = {0x00: 2000.0, 0x01: 2000.0, 0x02: 1000.0, 0x03: 400.0, 0x04: 200.0, 0x05: 100.0,
               0x06: 200.0, 0x07: 100.0}
GYRO_RANGES_DPS = {2000: 0, 1000: 1, 500: 2, 250: 3, 125: 4}
GYRO_FRAME, GYRO_FIFO_FRAMES = 6, 100
OVERRUN = 0x80


def acc_lsb_per_g(range_code: int) -> float:
    return 32768.0 / (1.5 * 2 ** (range_code + 1))


def gyro_lsb_per_dps(range_code: int) -> float:
    return 16.384 * 2 ** range_code


class BMI088Accel(RegisterDevice):
    """BMI088 accelerometer die: FIFO mode (stop when full), watermark on INT1."""

    PART = "BMI088 accelerometer"

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1600, range_g: int = 24,
                 watermark: int = 8, **kw: Any) -> None:
        super().__init__(transport, **kw)
        if odr_hz not in ACC_ODR_CODES:
            raise ValueError(f"BMI088 acc_odr_hz must be one of {sorted(ACC_ODR_CODES)}, got {odr_hz}")
        if range_g not in ACC_RANGES_G:
            raise ValueError(f"BMI088 acc_range_g must be one of {sorted(ACC_RANGES_G)}, got {range_g}")
        self.odr_hz, self.range_g, self.watermark = float(odr_hz), range_g, int(watermark)
        self.scale = STANDARD_GRAVITY / acc_lsb_per_g(ACC_RANGES_G[range_g])
        self.full_scale = 32767

    def configure(self) -> None:
        t = self.transport
        self.read_u8(ACC_CHIP_ID)  # the rising CSB1 edge that puts the die into SPI mode (§6.1)
        self.check_identity(ACC_CHIP_ID, (ACC_CHIP_ID_VALUE,), "ACC_CHIP_ID")
        self.write_u8(ACC_SOFTRESET, SOFTRESET_CMD)
        t.sleep(0.001)
        self.read_u8(ACC_CHIP_ID)  # back to SPI after the reset
        self.write_u8(ACC_PWR_CONF, 0x00)
        t.sleep(0.005)
        self.write_u8(ACC_PWR_CTRL, 0x04)
        t.sleep(0.005)
        self.write_u8(ACC_CONF, 0xA0 | ACC_ODR_CODES[int(self.odr_hz)])
        self.write_u8(ACC_RANGE, ACC_RANGES_G[self.range_g])
        wm = self.watermark * ACC_FRAME
        self.write_u8(FIFO_WTM_0, wm & 0xFF)
        self.write_u8(FIFO_WTM_1, wm >> 8)
        self.write_u8(ACC_FIFO_CONFIG_1, 0x50)  # acc_en | reserved 1
        self.write_u8(ACC_FIFO_CONFIG_0, 0x03)  # FIFO mode: stop when full (also clears it)
        self.write_u8(INT1_IO_CTRL, 0x0A)  # out, push-pull, active high
        self.write_u8(INT_MAP_DATA, 0x03)  # watermark and full on INT1
        self.flush()

    def flush(self) -> None:
        """Empties the FIFO: the 0xB0 command to ACC_SOFTRESET (PX4's FIFOReset)."""
        self.write_u8(ACC_SOFTRESET, ACC_FIFO_FLUSH_CMD)

    def read_level(self) -> int:
        b = self.read_regs(FIFO_LENGTH_0, 2)
        return b[0] | (b[1] & 0x3F) << 8

    def read_frames(self, n_bytes: int) -> tuple[np.ndarray, bool]:
        """(counts (n, 3) of the accelerometer frames in ``n_bytes`` of FIFO, full flag)."""
        data = self.read_fifo(ACC_FIFO_DATA, n_bytes) if n_bytes else b""
        rows, i = [], 0
        while i < len(data):
            h = data[i] & 0xFC  # bits 1:0 tag the interrupt pins
            if h == ACC_FRAME_HEADER and i + ACC_FRAME <= len(data):
                rows.append(data[i + 1:i + ACC_FRAME])
                i += ACC_FRAME
            elif h == 0x44:
                i += 4
            elif h in (0x40, 0x48, 0x50):
                i += 2
            else:  # 0x80: empty, or a partial frame
                break
        counts = np.frombuffer(b"".join(rows), dtype="<i2").reshape(-1, 3).astype(np.int64)
        return counts, n_bytes > ACC_FIFO_BYTES - ACC_FRAME


class BMI088Gyro(RegisterDevice):
    """BMI088 gyroscope die: FIFO mode (stop when full), watermark on INT3."""

    PART = "BMI088 gyroscope"

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 2000, range_dps: int = 2000,
                 watermark: int = 8, **kw: Any) -> None:
        super().__init__(transport, **kw)
        if odr_hz not in GYRO_ODR_CODES:
            raise ValueError(f"BMI088 odr_hz must be one of {sorted(GYRO_ODR_CODES)}, got {odr_hz}")
        if range_dps not in GYRO_RANGES_DPS:
            raise ValueError(f"BMI088 gyro_range_dps must be one of {sorted(GYRO_RANGES_DPS)}, got {range_dps}")
        if not 1 <= watermark <= GYRO_FIFO_FRAMES - 2:
            raise ValueError(f"BMI088 watermark must be 1…{GYRO_FIFO_FRAMES - 2} frames, got {watermark}")
        self.odr_hz, self.range_dps, self.watermark = float(odr_hz), range_dps, int(watermark)
        self.scale = DEG2RAD / gyro_lsb_per_dps(GYRO_RANGES_DPS[range_dps])
        self.full_scale = 32767

    def configure(self) -> None:
        self.check_identity(GYRO_CHIP_ID, (GYRO_CHIP_ID_VALUE,), "GYRO_CHIP_ID")
        self.write_u8(GYRO_SOFTRESET, SOFTRESET_CMD)
        self.transport.sleep(0.03)
        self.write_u8(GYRO_LPM1, 0x00)
        self.write_u8(GYRO_RANGE, GYRO_RANGES_DPS[self.range_dps])
        self.write_u8(GYRO_BANDWIDTH, GYRO_ODR_CODES[int(self.odr_hz)])
        self.write_u8(GYRO_FIFO_CONFIG_0, self.watermark)
        self.write_u8(FIFO_WM_ENABLE, 0x88)
        self.write_u8(INT3_INT4_IO_CONF, 0x01)  # push-pull, active high
        self.write_u8(INT3_INT4_IO_MAP, 0x04)  # FIFO interrupt on INT3
        self.write_u8(GYRO_INT_CTRL, 0x40)
        self.write_u8(GYRO_FIFO_CONFIG_1, 0x40)  # FIFO mode: stop when full
        self.flush()

    def flush(self) -> None:
        """Empties the FIFO and clears its overrun flag (the datasheet's rules as PX4 quotes
        them: a write of FIFO_CONFIG_0 clears the buffer, only a write of FIFO_CONFIG_1 the
        overrun)."""
        self.write_u8(GYRO_FIFO_CONFIG_0, self.watermark)
        self.write_u8(GYRO_FIFO_CONFIG_1, 0x40)
        self.read_status()  # an overrun flagged before the flush must not show as a new one

    def read_status(self) -> tuple[int, bool]:
        """(frames waiting, overrun) from FIFO_STATUS."""
        s = self.read_u8(FIFO_STATUS)
        return s & 0x7F, bool(s & OVERRUN)

    def read_frames(self, frames: int) -> np.ndarray:
        data = self.read_fifo(GYRO_FIFO_DATA, frames * GYRO_FRAME, GYRO_FRAME)
        return np.frombuffer(data, dtype="<i2").reshape(-1, 3).astype(np.int64)


# ============================================================================ twins
