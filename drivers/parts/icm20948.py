"""TDK InvenSense ICM-20948 gyroscope + accelerometer with its AK09916 magnetometer read by
the part's auxiliary I2C master (SPI or I2C), and its twin.

Register map used (TDK DS-000189, the register map per user bank). Every bank has
REG_BANK_SEL at 0x7F (bits 5:4 = bank):

=====  ==========  ===================  =================================================
bank   reg         name                 use
=====  ==========  ===================  =================================================
0      0x00        WHO_AM_I             0xEA
0      0x03        USER_CTRL            bit 6 FIFO_EN, bit 5 I2C_MST_EN, bit 4 I2C_IF_DIS
0      0x06        PWR_MGMT_1           bit 7 DEVICE_RESET, bit 6 SLEEP, CLKSEL 2:0 (1 = auto)
0      0x07        PWR_MGMT_2           0x00: accelerometer and gyroscope on
0      0x17        I2C_MST_STATUS       bit 6 I2C_SLV4_DONE
0      0x1B        INT_STATUS_2         FIFO_OVERFLOW_INT 4:0
0      0x3B…       EXT_SLV_SENS_DATA    what the aux master's slave 0 read
0      0x66        FIFO_EN_1            bit 0 SLV_0_FIFO_EN
0      0x67        FIFO_EN_2            bit 4 ACCEL, bits 3:1 GYRO_Z/Y/X
0      0x68        FIFO_RST             write 0x1F then 0x00 to empty the FIFO
0      0x69        FIFO_MODE            bit 0 snapshot (stop when full)
0      0x70        FIFO_COUNTH/L        bytes in the FIFO, big-endian (0x70 … 0x71)
0      0x72        FIFO_R_W             reads pop the FIFO
2      0x00        GYRO_SMPLRT_DIV      gyro ODR = 1125 Hz / (1 + div)
2      0x01        GYRO_CONFIG_1        DLPFCFG 5:3 (1 = ArduPilot's "188 Hz"), GYRO_FS_SEL 2:1
                                        (±250/500/1000/2000), FCHOICE 0 (1 = DLPF in)
2      0x10        ACCEL_SMPLRT_DIV_1/2 accel ODR = 1125 Hz / (1 + div), 11:0
2      0x14        ACCEL_CONFIG         DLPFCFG 5:3, ACCEL_FS_SEL 2:1 (±2/4/8/16 g), FCHOICE 0
3      0x01        I2C_MST_CTRL         I2C_MST_CLK 3:0 (7 = 345.6 kHz)
3      0x03…0x06   I2C_SLV0_ADDR/REG/   slave 0: address | 0x80 read, register, EN 7 | LENG 3:0
                   CTRL/DO
3      0x13…0x17   I2C_SLV4_ADDR/REG/   slave 4: one transfer per EN write (DONE in
                   CTRL/DO/DI           I2C_MST_STATUS), the configuration path to the AK09916
=====  ==========  ===================  =================================================

FIFO: 512 bytes (the datasheet's figure; some units hold more). With accelerometer, gyro and
slave 0's 9 bytes a packet is 21 bytes, big-endian: ACCEL X Y Z, GYRO X Y Z, then ST1, HXL …
HZH (little-endian), TMPS, ST2 — 24 packets, 21 ms at 1125 Hz. The part has no programmable
FIFO watermark interrupt (its watermark belongs to the DMP), so the board polls on the timer;
``source.drdy_gpio`` is refused for it. SPI: mode 0 or 3, ≤ 7 MHz, read bit 0x80; I2C
address 0x68 (AD0 low) or 0x69. Reset: DEVICE_RESET, then 100 ms (PWR_MGMT_1 reads 0x41,
asleep, auto clock); the AK09916 gets 100 ms after its CNTL3 soft reset.

Verified against (2026-12-02; read, not copied): PX4-Autopilot
``src/drivers/imu/invensense/icm20948/InvenSense_ICM20948_registers.hpp`` (0a12a2b3),
``ICM20948.cpp`` (1bbd1168), ``ICM20948.hpp`` (f929353e) and ``ICM20948_AK09916.cpp``
(542f41f2: 512-byte FIFO, FIFO_RST 0x1F then 0x00, snapshot FIFO_MODE, PWR_MGMT_1 0x41
after reset, 100 ms reset wait, 7 MHz SPI); ArduPilot
``libraries/AP_InertialSensor/AP_InertialSensor_Invensensev2_registers.h`` (04117858: every
bank 0/2/3 address above, FIFO_EN_1/2 bits, USER_CTRL bits, FCHOICE/DLPF codes, I2C_SLV0…4
and WHO_AM_I 0xEA). Slave 4's DONE flag (I2C_MST_STATUS bit 6) and the slave-4 sequence
(ADDR, REG, DO, CTRL.EN, poll DONE, read DI) are confirmed by third-party MPU-6050/MPU-9250
and ICM-20948 register headers and AK8963 examples found in the code index (the same
InvenSense I2C master), not by PX4 or ArduPilot, which reach the AK09916 through slave 0.
INT_STATUS_2 (0x1B, ArduPilot) with one FIFO_OVERFLOW_INT bit per FIFO in 4:0: a third-party
ICM-20948 library in the code index. Not confirmed by a second source: the 13-bit FIFO count
mask, the ACCEL_CONFIG DLPFCFG 1 bandwidth, the
power-on 0x01 of GYRO_CONFIG_1/ACCEL_CONFIG in the twin, and I2C_MST_CLK 7 = 345.6 kHz (PX4
quotes the datasheet's recommendation; ArduPilot writes 13, the MPU-6000 table's 400 kHz
code). Fixed in this check: the AK09916 was asked for its
identity right after its soft reset (PX4 waits 100 ms), and the gyro DLPF 1 was called
"≈ 197 Hz" (ArduPilot names it 188 Hz; the bandwidth is not used by the driver).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY, PartIdentityError, RegisterDevice
from ahrs_service.drivers.parts import ak09916
from ahrs_service.drivers.transport import RegisterTransport

REG_BANK_SEL = 0x7F
# bank 0
WHO_AM_I, USER_CTRL, PWR_MGMT_1, PWR_MGMT_2, I2C_MST_STATUS = 0x00, 0x03, 0x06, 0x07, 0x17
INT_STATUS_2, ACCEL_XOUT_H, EXT_SLV_SENS_DATA_00 = 0x1B, 0x2D, 0x3B
FIFO_EN_1, FIFO_EN_2, FIFO_RST, FIFO_MODE, FIFO_COUNTH, FIFO_R_W = 0x66, 0x67, 0x68, 0x69, 0x70, 0x72
# bank 2
GYRO_SMPLRT_DIV, GYRO_CONFIG_1, ACCEL_SMPLRT_DIV_1, ACCEL_SMPLRT_DIV_2, ACCEL_CONFIG = 0x00, 0x01, 0x10, 0x11, 0x14
# bank 3
I2C_MST_CTRL, I2C_SLV0_ADDR, I2C_SLV0_REG, I2C_SLV0_CTRL = 0x01, 0x03, 0x04, 0x05
I2C_SLV4_ADDR, I2C_SLV4_REG, I2C_SLV4_CTRL, I2C_SLV4_DO, I2C_SLV4_DI = 0x13, 0x14, 0x15, 0x16, 0x17

WHO_AM_I_VALUE = 0xEA
FIFO_EN_BIT, I2C_MST_EN, I2C_IF_DIS = 0x40, 0x20, 0x10
DEVICE_RESET, SLEEP, CLKSEL_AUTO = 0x80, 0x40, 0x01
SLV4_DONE, SLV_EN, READ = 0x40, 0x80, 0x80
BASE_RATE_HZ = 1125.0
FIFO_BYTES, PACKET, MAG_BYTES = 512, 21, 9
GYRO_LSB = (131.0, 65.5, 32.8, 16.4)
ACC_LSB = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_RANGES_DPS = {250: 0, 500: 1, 1000: 2, 2000: 3}
ACC_RANGES_G = {2: 0, 4: 1, 8: 2, 16: 3}


class ICM20948(RegisterDevice):
    """ICM-20948 driver: FIFO (snapshot mode) of accelerometer + gyro + the AK09916's 9 bytes.

    odr_hz: 1125 / (1 + n), n = 0…255 (1125, 562.5, 375, 281.25, 225, …); gyro and
    accelerometer alike. The magnetometer runs at ``mag_rate_hz`` 10/20/50/100.
    """

    PART = "ICM-20948"

    def __init__(self, transport: RegisterTransport, *, odr_hz: float = 1125, gyro_range_dps: int = 2000,
                 acc_range_g: int = 16, mag_rate_hz: float = 100, **kw: Any) -> None:
        super().__init__(transport, **kw)
        div = round(BASE_RATE_HZ / odr_hz) - 1 if odr_hz > 0 else -1
        if not 0 <= div <= 255 or abs(BASE_RATE_HZ / (1 + div) - odr_hz) > 0.01:
            raise ValueError(f"ICM-20948 odr_hz must be 1125 / (1 + n), n = 0…255 (1125, 562.5, 375, "
                             f"281.25, 225, …), got {odr_hz}")
        if gyro_range_dps not in GYRO_RANGES_DPS:
            raise ValueError(f"ICM-20948 gyro_range_dps must be one of {sorted(GYRO_RANGES_DPS)}, got {gyro_range_dps}")
        if acc_range_g not in ACC_RANGES_G:
            raise ValueError(f"ICM-20948 acc_range_g must be one of {sorted(ACC_RANGES_G)}, got {acc_range_g}")
        modes = {v: k for k, v in ak09916.MODES_HZ.items()}
        if mag_rate_hz not in modes:
            raise ValueError(f"ICM-20948 mag_rate_hz must be one of {sorted(modes)}, got {mag_rate_hz}")
        self.div, self.odr_hz = div, BASE_RATE_HZ / (1 + div)
        self.gyro_code, self.acc_code = GYRO_RANGES_DPS[gyro_range_dps], ACC_RANGES_G[acc_range_g]
        self.mag_mode = modes[mag_rate_hz]
        self.gyro_scale = DEG2RAD / GYRO_LSB[self.gyro_code]
        self.acc_scale = STANDARD_GRAVITY / ACC_LSB[self.acc_code]
        self.gyro_full_scale = min(32767, int(gyro_range_dps * GYRO_LSB[self.gyro_code]))
        self.acc_full_scale = min(32767, int(acc_range_g * ACC_LSB[self.acc_code]))
        self._bank = -1

    def bank(self, n: int) -> None:
        """Selects user bank ``n`` (written only when it changes)."""
        if n != self._bank:
            self.write_u8(REG_BANK_SEL, n << 4)
            self._bank = n

    def aux_transfer(self, reg: int, value: int | None = None) -> int:
        """One transfer to the AK09916 through slave 4: a write of ``value``, or a read."""
        self.bank(3)
        self.write_u8(I2C_SLV4_ADDR, ak09916.ADDRESS | (READ if value is None else 0))
        self.write_u8(I2C_SLV4_REG, reg)
        if value is not None:
            self.write_u8(I2C_SLV4_DO, value)
        self.write_u8(I2C_SLV4_CTRL, SLV_EN)
        self.bank(0)
        for _ in range(10):
            if self.read_u8(I2C_MST_STATUS) & SLV4_DONE:
                break
            self.transport.sleep(0.001)
        else:
            raise OSError(5, "ICM-20948 aux I2C master: slave 4 transfer to the AK09916 never completed")
        if value is not None:
            return value
        self.bank(3)
        got = self.read_u8(I2C_SLV4_DI)
        self.bank(0)
        return got

    def configure(self) -> None:
        t = self.transport
        self._bank = -1
        self.bank(0)
        self.check_identity(WHO_AM_I, (WHO_AM_I_VALUE,), "WHO_AM_I")
        self.write_u8(PWR_MGMT_1, DEVICE_RESET)
        t.sleep(0.1)
        self._bank = -1
        self.bank(0)
        self.write_u8(PWR_MGMT_1, CLKSEL_AUTO)
        self.write_u8(PWR_MGMT_2, 0x00)
        spi = I2C_IF_DIS if t.kind == "spi" else 0
        self.write_u8(USER_CTRL, spi | I2C_MST_EN)
        self.bank(2)
        self.write_u8(GYRO_SMPLRT_DIV, self.div)
        self.write_u8(GYRO_CONFIG_1, 1 << 3 | self.gyro_code << 1 | 1)  # DLPFCFG 1, FCHOICE: DLPF in
        self.write_u8(ACCEL_SMPLRT_DIV_1, 0)
        self.write_u8(ACCEL_SMPLRT_DIV_2, self.div)
        self.write_u8(ACCEL_CONFIG, 1 << 3 | self.acc_code << 1 | 1)
        self.bank(3)
        self.write_u8(I2C_MST_CTRL, 0x07)
        self.bank(0)
        self.aux_transfer(ak09916.CNTL3, ak09916.SRST)
        t.sleep(0.1)  # the AK09916's soft reset (PX4 ICM20948_AK09916.cpp waits 100 ms)
        wia = self.aux_transfer(ak09916.WIA2)
        if wia != ak09916.WIA2_VALUE:
            raise PartIdentityError(f"{t.where} aux I2C 0x0C", "AK09916", ak09916.WIA2, wia,
                                    (ak09916.WIA2_VALUE,), "WIA2 (through I2C slave 4)")
        self.aux_transfer(ak09916.CNTL2, self.mag_mode)
        self.bank(3)
        self.write_u8(I2C_SLV0_ADDR, READ | ak09916.ADDRESS)
        self.write_u8(I2C_SLV0_REG, ak09916.ST1)
        self.write_u8(I2C_SLV0_CTRL, SLV_EN | MAG_BYTES)
        self.bank(0)
        self.write_u8(FIFO_EN_1, 0x01)  # slave 0
        self.write_u8(FIFO_EN_2, 0x1E)  # accel + gyro X/Y/Z
        self.write_u8(FIFO_MODE, 0x01)  # snapshot: stop when full
        self.flush()
        self.write_u8(USER_CTRL, spi | I2C_MST_EN | FIFO_EN_BIT)

    def flush(self) -> None:
        self.bank(0)
        self.write_u8(FIFO_RST, 0x1F)
        self.write_u8(FIFO_RST, 0x00)
        self.read_status()  # clears an overflow flag raised before the reset

    def read_status(self) -> tuple[bool, int]:
        """(overflow, FIFO count in bytes)."""
        self.bank(0)
        overflow = bool(self.read_u8(INT_STATUS_2) & 0x1F)
        b = self.read_regs(FIFO_COUNTH, 2)
        return overflow, (b[0] << 8 | b[1]) & 0x1FFF

    def read_packets(self, n: int) -> np.ndarray:
        """(n, 12) int64: accel X Y Z, gyro X Y Z, ST1, mag X Y Z (die axes), TMPS, ST2."""
        a = np.frombuffer(self.read_fifo(FIFO_R_W, n * PACKET), dtype=np.uint8).reshape(n, PACKET)
        out = np.empty((n, 12), dtype=np.int64)
        out[:, 0:6] = a[:, 0:12].copy().view(">i2")  # accel, gyro: big-endian
        out[:, 6] = a[:, 12]  # ST1
        out[:, 7:10] = a[:, 13:19].copy().view("<i2")  # HX, HY, HZ: little-endian (AK09916)
        out[:, 10], out[:, 11] = a[:, 19], a[:, 20]  # TMPS, ST2
        return out

    @staticmethod
    def mag_to_board(counts: np.ndarray) -> np.ndarray:
        """AK09916 die axes → ICM-20948 accelerometer axes (X, −Y, −Z), µT."""
        return counts * np.array([1.0, -1.0, -1.0]) * ak09916.UT_PER_LSB
