"""ICM-20948 against its twin: identity, user banks, the AK09916 behind the auxiliary I2C
master (slave 4 for configuration, slave 0 into the FIFO), packet layout and scale,
overflow. Expectations written out from TDK DS-000189 and the AK09916 datasheet, each checked
against PX4, ArduPilot and Linux ak8975 (see the module headers of drivers/imu/icm20948.py
and ak09916.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_icm42688p import ConstantImu

from ahrs_service import config
from ahrs_service.core.samples import MAG_NEW, MAG_VALID
from ahrs_service.drivers.boards import make_transport_board
from ahrs_service.drivers.device import PartIdentityError

G0 = 9.80665
D2R = math.pi / 180


class MagImu(ConstantImu):
    def __init__(self) -> None:
        super().__init__()
        self.mag = np.array([20.0, -5.0, 40.0])

    def physics(self, t: float) -> dict:
        d = super().physics(t)
        d["mag"] = self.mag
        return d


def board(bus: str = "spi", **options):
    imu = MagImu()
    b = make_transport_board("icm20948", bus, simulated_imu=imu, **options)
    return b, imu, b.transport.bus.device(0 if bus == "spi" else 0x68)


def test_identity_banks_and_configuration():
    b, imu, twin = board(odr_hz=562.5, gyro_range_dps=1000, acc_range_g=8)
    b.open()
    b0, b2, b3 = twin.banks[0], twin.banks[2], twin.banks[3]
    assert b0[0x00] == 0xEA  # WHO_AM_I
    assert b0[0x03] == 0x70  # USER_CTRL: FIFO_EN, I2C_MST_EN, I2C_IF_DIS (SPI)
    assert b0[0x06] == 0x01 and b0[0x07] == 0x00  # awake, auto clock; all axes on
    assert b2[0x00] == 1 and b2[0x01] == 0x0D  # GYRO_SMPLRT_DIV 1 (562.5 Hz); DLPF 1, ±1000 °/s, FCHOICE
    assert b2[0x11] == 1 and b2[0x14] == 0x0D  # ACCEL_SMPLRT_DIV 1; DLPF 1, ±8 g, FCHOICE
    assert b0[0x66] == 0x01 and b0[0x67] == 0x1E and b0[0x69] == 0x01  # slave 0 + accel + gyro, snapshot
    assert b3[0x03] == 0x8C and b3[0x04] == 0x10 and b3[0x05] == 0x89  # slave 0 reads 9 bytes from ST1
    assert twin.mag.regs[0x31] == 0x08  # AK09916 CNTL2: continuous 100 Hz, written through slave 4
    # a register written in bank 2 is not in bank 0
    assert b0[0x01] == 0 and twin.bank == 0
    twin.banks[0][0x00] = 0x71  # an MPU-9250 answers
    with pytest.raises(PartIdentityError, match=r"expected ICM-20948.*0x71"):
        b.part.configure()


def test_magnetometer_identity_is_checked_through_the_aux_master():
    b, imu, twin = board()
    twin.aux.set_present(0x0C, False)  # the AK09916 does not answer on the aux bus
    with pytest.raises(PartIdentityError, match=r"aux I2C 0x0C: expected AK09916.*WIA2"):
        b.open()


def test_packets_scale_axes_and_magnetometer_rows():
    b, imu, twin = board("i2c", odr_hz=1125)
    b.open()
    blocks = []
    for _ in range(250):  # 1 s of 4 ms polls
        imu.clock.advance(0.004)
        blocks.append(b.read_block())
    blk = blocks[-1]
    assert np.abs(blk.gyr - imu.gyr).max() <= D2R / 16.4 / 2 + 1e-12
    assert np.abs(blk.acc - imu.acc).max() <= G0 / 2048 / 2 + 1e-12
    flags = np.concatenate([x.flags for x in blocks])
    mag = np.concatenate([x.mag for x in blocks])
    new = (flags & MAG_NEW) != 0
    assert 95 <= new.sum() <= 101  # 100 Hz AK09916 among 1115 Hz rows
    assert ((flags[new] & MAG_VALID) != 0).all() and np.isnan(mag[~new]).all()
    # the die's X, −Y, −Z turned into the accelerometer's axes: the field comes back as given
    assert np.abs(mag[new] - imu.mag).max() <= 0.15 / 2 + 1e-9
    # raw: the die's own axes, 0.15 µT/LSB little-endian in the packet
    raw = np.concatenate([x.raw["mag"] for x in blocks])[new][0]
    assert raw.tolist() == [round(20.0 / 0.15), round(5.0 / 0.15), round(-40.0 / 0.15)]
    n = sum(len(x) for x in blocks)
    assert n == b.diagnostics.samples and b.clock.rate_hz == pytest.approx(twin.rate_hz(), rel=5e-4)


def test_overflow_counted_and_fifo_reset():
    b, imu, twin = board(odr_hz=1125)
    b.open()
    for _ in range(250):  # 1 s: the part's real rate is tracked
        imu.clock.advance(0.004)
        b.read_block()
    imu.clock.advance(0.1)  # 512 bytes / 21 = 24 packets: 21 ms
    full = b.read_block()
    assert len(full) == 24 and b.diagnostics.extra["fifo_overflows"] == 1
    lost = b.diagnostics.lost.fifo_overflow
    assert abs(lost - twin.fifo.dropped) <= 1 and lost > 80
    imu.clock.advance(0.004)
    assert b.read_block().lost.fifo_overflow == lost


def test_no_watermark_line_and_rate_limits():
    with pytest.raises(config.ConfigError, match=r"^source.drdy_gpio: board 'icm20948' has no FIFO"):
        config.validate({"source": {"type": "spi", "board": "icm20948", "drdy_gpio": "gpiochip0:4"}})
    config.validate({"source": {"type": "i2c", "board": "icm20948"}})  # 1125 Hz fits 400 kHz
    with pytest.raises(config.ConfigError, match=r"odr_hz = 1125 Hz.*100 kHz"):
        config.validate({"source": {"type": "i2c", "board": "icm20948", "i2c_speed_hz": 100_000}})
