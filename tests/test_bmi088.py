"""BMI088 against its twins: the two dies (identity, chip selects, the accelerometer's SPI
dummy byte and SPI-mode switch), configuration, frame layout and scale, watermark,
overflow, and the pairing of the two clocks into rows.

Register expectations are written out from Bosch BST-BMI088-DS001 (accelerometer and
gyroscope register maps, FIFO chapter) independently of the driver's constants, each checked
against Bosch's BMI08x Sensor API, PX4, ArduPilot and Zephyr (see the module header of
drivers/imu/bmi088.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_icm42688p import ConstantImu

from ahrs_service.drivers.boards import make_transport_board
from ahrs_service.drivers.device import PartIdentityError
from ahrs_service.drivers.sim.drdy import SimulatedDataReadyLine
from ahrs_service.drivers.transport import SPITransport

G0 = 9.80665
D2R = math.pi / 180


def board(**options):
    imu = ConstantImu()
    b = make_transport_board("bmi088", "spi", simulated_imu=imu, **options)
    bus = b.transport.bus
    return b, imu, bus.device(0), bus.device(1)


def test_two_dies_on_two_chip_selects_with_their_identities():
    b, imu, acc, gyro = board()
    assert b.acc_transport.cs == 0 and b.transport.cs == 1
    assert b.acc_transport.dummy_bytes == 1 and b.transport.dummy_bytes == 0
    b.open()
    assert acc.regs[0x00] == 0x1E and gyro.regs[0x00] == 0x0F  # ACC_CHIP_ID, GYRO_CHIP_ID
    # the accelerometer ignores SPI until its first chip-select edge after power-on
    b.transport.bus.set_present(0, False)
    b.transport.bus.set_present(0, True)  # power-cycled: back in I2C mode
    plain = SPITransport(b.transport.bus, 0, dummy_bytes=1)
    assert plain.read(0x00, 1) == b"\xff"  # the throw-away read that switches it to SPI
    assert plain.read(0x00, 1) == b"\x1e"
    without_dummy = SPITransport(b.transport.bus, 0)
    assert without_dummy.read(0x00, 1) == b"\xff"  # the dummy byte, taken for data
    b2 = make_transport_board("bmi088", "spi", simulated_imu=ConstantImu(), gyro_spi_device=3)
    b2.transport.bus.set_present(3, False)  # nothing answers on chip select 3
    with pytest.raises(PartIdentityError, match=r"sim-spi0\.3: expected BMI088 gyroscope.*reads 0xFF"):
        b2.open()


def test_configuration_registers_of_both_dies():
    b, imu, acc, gyro = board(odr_hz=1000, acc_odr_hz=800, gyro_range_dps=500, acc_range_g=6, watermark=10)
    b.open()
    a, g = acc.regs, gyro.regs
    assert a[0x7C] == 0x00 and a[0x7D] == 0x04  # ACC_PWR_CONF active, ACC_PWR_CTRL on
    assert a[0x40] == 0xAB and a[0x41] == 0x01  # ACC_CONF normal bwp + 800 Hz, ACC_RANGE ±6 g
    assert a[0x48] == 0x03 and a[0x49] == 0x50  # FIFO mode (stop when full), acc_en
    assert a[0x58] == 0x03 and a[0x53] == 0x0A  # watermark + full on INT1, push-pull active high
    assert (a[0x46] | a[0x47] << 8) == 8 * 7  # 800 Hz / (1000 Hz / 10) = 8 frames of 7 bytes
    assert g[0x0F] == 0x02 and g[0x10] == 0x82  # GYRO_RANGE ±500 °/s, GYRO_BANDWIDTH 1000 Hz (bit 7 reads 1)
    assert g[0x3D] == 10 and g[0x3E] == 0x40 and g[0x1E] == 0x88  # watermark, FIFO mode, WM on
    assert g[0x18] == 0x04 and g[0x15] == 0x40  # FIFO interrupt on INT3
    assert gyro.rate_hz() == pytest.approx(1000 * 1.0073) and acc.rate_hz() == pytest.approx(800 * 0.9939)


def test_frames_scale_and_little_endian_layout():
    b, imu, acc, gyro = board(gyro_range_dps=2000, acc_range_g=24)
    b.open()
    for _ in range(300):
        imu.clock.advance(0.001)
        blk = b.read_block()
    assert np.abs(blk.gyr - imu.gyr).max() <= D2R / 16.384 / 2 + 1e-12  # 16.384 LSB/(°/s)
    assert np.abs(blk.acc - imu.acc).max() <= G0 / (32768 / 24) / 2 + 1e-12  # ±24 g: 32768 / (1.5·2^4) = 1365 LSB/g
    imu.clock.advance(0.002)
    acc.update(imu.clock.now())  # the twins latch when the bus touches them
    gyro.update(imu.clock.now())
    frame = bytes(acc.fifo.data[:7])
    assert frame[0] == 0x84  # accelerometer frame header
    x = int.from_bytes(frame[1:3], "little", signed=True)
    assert x == round(imu.acc[0] / (G0 / (32768 / 24)))
    gx = int.from_bytes(bytes(gyro.fifo.data[:2]), "little", signed=True)
    assert gx == round(imu.gyr[0] / (D2R / 16.384))


def test_rows_follow_the_gyro_with_the_newest_earlier_accelerometer_sample():
    b, imu, acc, gyro = board(odr_hz=2000, acc_odr_hz=100)
    b.open()
    got = []
    for k in range(600):
        imu.acc = np.array([0.0, 0.0, -9.0 - k * 1e-3])  # a slow ramp identifies each accel sample
        imu.clock.advance(0.001)
        got.append(b.read_block())
    n = sum(len(x) for x in got)
    assert n == b.diagnostics.samples and 1150 <= n <= 1210  # 2014.6 Hz for 0.6 s, minus the start
    t = np.concatenate([x.t_ns for x in got])
    a = np.concatenate([x.acc for x in got])
    assert (np.diff(t) > 0).all()
    # the held accelerometer value changes about every 10 ms (100 Hz), never within a row's future
    changes = np.flatnonzero(np.diff(a[:, 2]) != 0)
    assert 50 <= len(changes) <= 62
    assert np.median(np.diff(t[changes + 1])) == pytest.approx(1e9 / (100 * 0.9939), rel=0.02)
    assert (b._acc_t[-1] <= t[-1] + 1e9 / 100)


def test_gyro_overflow_counted_and_fifo_reset_accel_overflow_counted_apart():
    b, imu, acc, gyro = board(odr_hz=2000, acc_odr_hz=1600)
    b.open()
    for _ in range(300):
        imu.clock.advance(0.001)
        b.read_block()
    imu.clock.advance(0.2)  # gyro FIFO (100 frames, 50 ms) and accel FIFO (146 frames, 92 ms) overflow
    gyro.update(imu.clock.now())
    assert gyro.read_register(0x0E) & 0x80  # FIFO_STATUS overrun
    blk = b.read_block()
    assert len(blk) == 100
    lost = b.diagnostics.lost.fifo_overflow
    assert abs(lost - gyro.fifo.dropped) <= 1 and lost > 250
    assert b.diagnostics.extra["fifo_overflows"] == 1 and b.diagnostics.extra["acc_fifo_overflows"] == 1
    assert gyro.fifo.level == 0 and not gyro.read_register(0x0E) & 0x80
    imu.clock.advance(0.002)
    after = b.read_block()
    assert after.lost.fifo_overflow == lost
    assert (after.t_ns[0] - blk.t_ns[-1]) / 1e9 == pytest.approx((lost + 1) / gyro.rate_hz(), abs=2e-4)


def test_fifo_flush_rules_of_both_dies():
    # accelerometer: the 0xB0 command to ACC_SOFTRESET (0x7E) flushes the FIFO, a rewrite of
    # FIFO_CONFIG_0 (0x48) does not; gyroscope: a write of FIFO_CONFIG_0 (0x3D) clears the
    # buffer but not the overrun flag (FIFO_STATUS bit 7), only a write of FIFO_CONFIG_1 (0x3E)
    # clears that
    b, imu, acc, gyro = board(odr_hz=2000, acc_odr_hz=1600, watermark=8)
    b.open()
    imu.clock.advance(0.2)  # both FIFOs overflow
    gyro.update(imu.clock.now())  # the twins latch when the bus touches them
    acc_bus, gyro_bus = b.acc_transport, b.transport
    acc_bus.write(0x48, 0x03)
    assert acc.fifo.level == 146 * 7  # still full
    acc_bus.write(0x7E, 0xB0)
    assert acc.fifo.level == 0 and acc.regs[0x40] == 0xAC  # flushed, configuration kept
    assert gyro.read_register(0x0E) == 0x80 | 100  # overrun, 100 frames
    gyro_bus.write(0x3D, 8)
    assert gyro.read_register(0x0E) == 0x80  # empty, overrun still flagged
    gyro_bus.write(0x3E, 0x40)
    assert gyro.read_register(0x0E) == 0x00
    imu.clock.advance(0.002)
    gyro.update(imu.clock.now())
    assert 3 <= gyro.read_register(0x0E) <= 5  # filling again in FIFO mode (2014.6 Hz)


def test_gyro_watermark_raises_int3_for_the_data_ready_line():
    b, imu, acc, gyro = board(odr_hz=1000, watermark=5)
    b.open()
    line = SimulatedDataReadyLine(gyro, imu.clock)
    sizes = []
    for _ in range(10):
        assert line.wait(0.05)
        sizes.append(len(b.read_block()))
    assert sizes[1:] == [5] * 9 and line.edges == 10
