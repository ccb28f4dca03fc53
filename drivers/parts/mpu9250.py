"""InvenSense MPU-9250 gyroscope + accelerometer, and its twin (its AK8963: ak8963.py).

Register map used (RM-MPU-9250A-00 rev 1.6):

=====  ==============  ======================================================
0x19   SMPLRT_DIV      ODR = 1 kHz / (1 + div) with the DLPF on
0x1A   CONFIG          DLPF_CFG 2:0 (1…6 → 1 kHz internal rate; 0, 7 → 8 kHz); bit 6
                       FIFO_MODE: 1 = a full FIFO takes no more samples, 0 = it overwrites
                       the oldest (§4.4)
0x23   FIFO_EN         bits 6:4 GYRO_X/Y/ZOUT, bit 3 ACCEL: what each sample writes to the
                       FIFO, in register order 0x3B… (accel 6 bytes, gyro 6 bytes) (§4.7)
0x38   INT_ENABLE      bit 4 FIFO_OFLOW_EN, bit 0 RAW_RDY_EN (§4.17)
0x1B   GYRO_CONFIG     GYRO_FS_SEL 4:3 ±250/500/1000/2000 °/s, FCHOICE_B 1:0 (00 = DLPF)
0x1C   ACCEL_CONFIG    ACCEL_FS_SEL 4:3 ±2/4/8/16 g
0x1D   ACCEL_CONFIG2   ACCEL_FCHOICE_B bit 3, A_DLPFCFG 2:0
0x37   INT_PIN_CFG     bit 1 BYPASS_EN: the AK8963 (0x0C) appears on the host bus
0x3A   INT_STATUS      bit 4 FIFO_OFLOW_INT, bit 0 RAW_DATA_RDY_INT, cleared by reading
                       INT_STATUS (§4.19)
0x3B…  ACCEL, TEMP,    ACCEL X Y Z, TEMP, GYRO X Y Z — big-endian two's complement,
0x48   GYRO            contiguous: one 15-byte burst from 0x3A reads status and all data
0x6A   USER_CTRL       bit 6 FIFO_EN, bit 5 I2C_MST_EN (must be 0 for bypass), bit 2
                       FIFO_RST (self-clearing) (§4.23)
0x6B   PWR_MGMT_1      bit 7 H_RESET, bit 6 SLEEP, CLKSEL 2:0
0x72   FIFO_COUNTH/L   bytes in the FIFO, 13 bits big-endian (§4.30)
0x74   FIFO_R_W        each read pops the next FIFO byte; the address does not advance,
                       so one burst reads a byte stream (§4.31)
0x75   WHO_AM_I        0x71 (MPU-9250), 0x73 (MPU-9255)
=====  ==============  ======================================================

FIFO: 512 bytes (product specification PS-MPU-9250A-01 §3.1 / register map §4.30); with
accelerometer + gyroscope enabled a sample is 12 bytes, so it holds 42 samples (42 ms at
1 kHz). The driver sets FIFO_MODE = 1: a full FIFO keeps its oldest samples, contiguous with
the last read, and the overflow flag tells the driver to count the rest and reset it.

Sensitivity: gyro 131 / 65.5 / 32.8 / 16.4 LSB/(°/s), accel 16384 / 8192 / 4096 / 2048
LSB/g, temperature (TEMP_OUT − 0) / 333.87 + 21 °C. The part holds its user registers while
a burst is in progress, so status + data in one burst is race-free. Address 0x68 (AD0 low)
or 0x69. Registers auto-increment without a sub-address flag.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ahrs_service.drivers.buses.i2c import I2CBus
from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY, FifoLayout, FifoStatus, I2CDevice

SMPLRT_DIV, CONFIG, GYRO_CONFIG, ACCEL_CONFIG, ACCEL_CONFIG2 = 0x19, 0x1A, 0x1B, 0x1C, 0x1D
INT_PIN_CFG, INT_ENABLE, INT_STATUS, ACCEL_XOUT_H = 0x37, 0x38, 0x3A, 0x3B
USER_CTRL, PWR_MGMT_1, PWR_MGMT_2, WHO_AM_I = 0x6A, 0x6B, 0x6C, 0x75
FIFO_EN_REG, TEMP_OUT_H, FIFO_COUNTH, FIFO_R_W = 0x23, 0x41, 0x72, 0x74
FIFO_MODE = 0x40  # CONFIG bit 6
FIFO_GYRO_ACCEL = 0x78  # FIFO_EN: GYRO_XOUT | GYRO_YOUT | GYRO_ZOUT | ACCEL
USER_FIFO_EN, USER_FIFO_RST = 0x40, 0x04
FIFO_OFLOW = 0x10  # INT_STATUS / INT_ENABLE bit 4
FIFO_BYTES = 512
FIFO_FRAME_BYTES = 12
#: how the driver reads the FIFO: a byte stream from FIFO_R_W, split into 32-byte blocks
FIFO_LAYOUT = FifoLayout(depth_frames=FIFO_BYTES // FIFO_FRAME_BYTES, frame_bytes=FIFO_FRAME_BYTES,
                         data_register=FIFO_R_W, frames_per_transfer=0)
WHO_AM_I_VALUES = (0x71, 0x73)
BYPASS_EN, INT_ANYRD_2CLEAR = 0x02, 0x10
I2C_MST_EN = 0x20
H_RESET, SLEEP, CLKSEL_PLL = 0x80, 0x40, 0x01
RAW_DATA_RDY = 0x01
GYRO_LSB_PER_DPS = (131.0, 65.5, 32.8, 16.4)
ACC_LSB_PER_G = (16384.0, 8192.0, 4096.0, 2048.0)
GYRO_RANGES_DPS = {250: 0, 500: 1, 1000: 2, 2000: 3}
ACC_RANGES_G = {2: 0, 4: 1, 8: 2, 16: 3}
TEMP_LSB_PER_C, TEMP_OFFSET_C = 333.87, 21.0
#: DLPF_CFG → gyro bandwidth (Hz) for codes 1…6 (1 kHz internal rate)
DLPF_BANDWIDTH_HZ = {1: 184.0, 2: 92.0, 3: 41.0, 4: 20.0, 5: 10.0, 6: 5.0}
_UNPACK = struct.Struct(">B3hh3h").unpack


class MPU9250(I2CDevice):
    """MPU-9250 accelerometer + gyroscope driver.

    gyro_range_dps: 250/500/1000/2000; acc_range_g: 2/4/8/16; rate_hz: 1000 / (1 + n) for an
    integer divider n (1000, 500, 333.3…, 250, 200, …, 4 Hz). The low-pass filter is the widest
    one below half the rate (anti-aliasing), for gyro and accelerometer alike.
    """

    PART = "MPU-9250"
    DEFAULT_ADDRESS = 0x68

    def __init__(self, bus: I2CBus, address: int | None = None, *, gyro_range_dps: int = 2000,
                 acc_range_g: int = 8, rate_hz: float = 1000, fifo: bool = False, **kw: Any) -> None:
        super().__init__(bus, address, **kw)
        self.fifo = bool(fifo)
        if gyro_range_dps not in GYRO_RANGES_DPS:
            raise ValueError(f"MPU-9250 gyro_range_dps must be one of {sorted(GYRO_RANGES_DPS)}, "
                             f"got {gyro_range_dps}")
        if acc_range_g not in ACC_RANGES_G:
            raise ValueError(f"MPU-9250 acc_range_g must be one of {sorted(ACC_RANGES_G)}, "
                             f"got {acc_range_g}")
        div = round(1000.0 / rate_hz) - 1 if rate_hz > 0 else -1
        if not 0 <= div <= 255 or abs(1000.0 / (1 + div) - rate_hz) > 1e-6 * rate_hz + 0.01:
            raise ValueError(f"MPU-9250 rate_hz must be 1000 / (1 + n), n = 0…255 "
                             f"(1000, 500, 333.33, 250, 200, …), got {rate_hz}")
        self.gyro_range_dps, self.acc_range_g = gyro_range_dps, acc_range_g
        self.smplrt_div = div
        self.rate_hz = 1000.0 / (1 + div)
        self.dlpf_cfg = next((c for c, bw in sorted(DLPF_BANDWIDTH_HZ.items())
                              if bw <= self.rate_hz / 2), 6)
        g_lsb = GYRO_LSB_PER_DPS[GYRO_RANGES_DPS[gyro_range_dps]]
        a_lsb = ACC_LSB_PER_G[ACC_RANGES_G[acc_range_g]]
        self.gyro_scale = np.full(3, DEG2RAD / g_lsb)
        self.acc_scale = np.full(3, STANDARD_GRAVITY / a_lsb)
        self.scale = self.gyro_scale
        self.gyro_full_scale = min(32767, int(gyro_range_dps * g_lsb))
        self.acc_full_scale = min(32767, int(acc_range_g * a_lsb))
        self.full_scale = self.gyro_full_scale

    def configure(self) -> None:
        """Checks WHO_AM_I, resets, wakes on the PLL, sets rate/filters/ranges, I2C bypass on."""
        self.check_identity(WHO_AM_I, [bytes([v]) for v in WHO_AM_I_VALUES], "WHO_AM_I")
        self.write_u8(PWR_MGMT_1, H_RESET)
        self.transport.sleep(0.1)  # reset takes up to 100 ms
        self.write_u8(PWR_MGMT_1, CLKSEL_PLL)
        self.write_u8(PWR_MGMT_2, 0x00)
        self.write_u8(CONFIG, self.dlpf_cfg | (FIFO_MODE if self.fifo else 0))
        self.write_u8(SMPLRT_DIV, self.smplrt_div)
        self.write_u8(GYRO_CONFIG, GYRO_RANGES_DPS[self.gyro_range_dps] << 3)
        self.write_u8(ACCEL_CONFIG, ACC_RANGES_G[self.acc_range_g] << 3)
        self.write_u8(ACCEL_CONFIG2, self.dlpf_cfg)
        # bypass: the AK8963 answers directly on the host bus instead of the MPU's aux master
        self.write_u8(USER_CTRL, 0x00)
        self.write_u8(INT_PIN_CFG, BYPASS_EN)
        self.write_u8(INT_ENABLE, RAW_DATA_RDY | (FIFO_OFLOW if self.fifo else 0))
        if self.fifo:
            self.write_u8(FIFO_EN_REG, FIFO_GYRO_ACCEL)
            self.fifo_reset()

    # ---------------------------------------------------------------- FIFO
    def fifo_reset(self) -> None:
        """Empties the FIFO and (re)starts filling it (USER_CTRL FIFO_RST + FIFO_EN), then
        reads INT_STATUS: an overflow flagged before the reset must not show at the next
        drain as a new one."""
        self.write_u8(USER_CTRL, USER_FIFO_EN | USER_FIFO_RST)
        self.read_u8(INT_STATUS)

    def fifo_status(self) -> FifoStatus:
        """Whole samples waiting and the overflow flag (INT_STATUS, then FIFO_COUNT: reading
        the status first means a sample arriving in between is counted, never lost)."""
        overflow = bool(self.read_u8(INT_STATUS) & FIFO_OFLOW)
        t = self.transport.now_ns()
        hi, lo = self.read_regs(FIFO_COUNTH, 2)
        return FifoStatus(((hi & 0x1F) << 8 | lo) // FIFO_FRAME_BYTES, overflow, t)

    def read_fifo(self, frames: int) -> tuple[np.ndarray, np.ndarray]:
        """``frames`` samples from the FIFO, oldest first: (accel counts, gyro counts), each
        (frames, 3) int64, in ⌈12·frames / 32⌉ transfers."""
        data = np.frombuffer(self.read_fifo_frames(FIFO_LAYOUT, frames), dtype=">i2")
        counts = data.reshape(frames, 6).astype(np.int64)
        return counts[:, 0:3], counts[:, 3:6]

    def read_temperature_counts(self) -> int:
        """TEMP_OUT (two bytes, big-endian)."""
        hi, lo = self.read_regs(TEMP_OUT_H, 2)
        v = hi << 8 | lo
        return v - 0x10000 if v & 0x8000 else v

    @property
    def resolution(self) -> float:
        """Gyro step, rad/s (``acc_scale`` is the accelerometer's)."""
        return float(self.gyro_scale[0])

    def read_frame(self) -> tuple[int, tuple[int, int, int], int, tuple[int, int, int]]:
        """One 15-byte burst: (INT_STATUS, accel counts, temperature counts, gyro counts)."""
        s, ax, ay, az, t, gx, gy, gz = _UNPACK(self.read_regs(INT_STATUS, 15))
        return s, (ax, ay, az), t, (gx, gy, gz)

    def read_if_new(self) -> tuple[tuple[int, int, int], int, tuple[int, int, int]] | None:
        """(accel counts, temperature counts, gyro counts) of a new sample, else None."""
        s, acc, temp, gyr = self.read_frame()
        return (acc, temp, gyr) if s & RAW_DATA_RDY else None

    def gyr_si(self, counts) -> np.ndarray:
        """Angular rate, rad/s."""
        return np.multiply(counts, self.gyro_scale)

    def acc_si(self, counts) -> np.ndarray:
        """Specific force, m/s²."""
        return np.multiply(counts, self.acc_scale)

    @staticmethod
    def temperature_c(counts: int) -> float:
        """Die temperature, °C."""
        return counts / TEMP_LSB_PER_C + TEMP_OFFSET_C

    def gyr_saturated(self, counts) -> bool:
        fs = self.gyro_full_scale
        return any(c >= fs or c <= -fs for c in counts)

    def acc_saturated(self, counts) -> bool:
        fs = self.acc_full_scale
        return any(c >= fs or c <= -fs for c in counts)
