"""I2C drivers against their simulated twins: registers, conversion, data-ready, faults, boards.

Register-level expectations (register addresses, bit positions, byte orders, sensitivities)
are written out here from the parts' datasheets, independently of the driver constants, so a
driver and its twin cannot agree on the same mistake unnoticed.
"""

from __future__ import annotations

import errno
import math
from types import SimpleNamespace

import numpy as np
import pytest

from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
)
from ahrs_service.drivers.boards import i2c_board_names as board_names
from ahrs_service.drivers.boards import make_board, make_simulated_board
from ahrs_service.drivers.buses.i2c import SMBusI2C
from ahrs_service.drivers.device import DeviceIdentityError, I2CDeviceError
from ahrs_service.drivers.parts.adxl345 import ADXL345
from ahrs_service.drivers.parts.ak8963 import AK8963
from ahrs_service.drivers.parts.hmc5883l import HMC5883L
from ahrs_service.drivers.parts.l3g4200d import L3G4200D
from ahrs_service.drivers.parts.l3gd20 import L3GD20
from ahrs_service.drivers.parts.lsm303dlhc import LSM303DLHCAcc, LSM303DLHCMag
from ahrs_service.drivers.parts.mpu9250 import MPU9250
from ahrs_service.drivers.sim.adxl345 import SimulatedADXL345
from ahrs_service.drivers.sim.ak8963 import SimulatedAK8963
from ahrs_service.drivers.sim.bus import SimulatedI2CBus
from ahrs_service.drivers.sim.hmc5883l import SimulatedHMC5883L
from ahrs_service.drivers.sim.l3g4200d import SimulatedL3G4200D
from ahrs_service.drivers.sim.l3gd20 import SimulatedL3GD20
from ahrs_service.drivers.sim.lsm303dlhc import SimulatedLSM303DLHCAcc, SimulatedLSM303DLHCMag
from ahrs_service.drivers.sim.mpu9250 import SimulatedMPU9250

G0 = 9.80665
D2R = math.pi / 180


class StandInImu:
    """A tiny physics source: constant readings the test sets, a clock the test moves."""

    def __init__(self) -> None:
        self.clock = SimpleNamespace(t=0.0)
        self.clock.now = lambda: self.clock.t
        self.gyr = np.array([0.1, -0.2, 0.3])
        self.acc = np.array([1.5, -2.5, -9.0])
        self.mag = np.array([21.0, -6.0, 43.0])
        self.temperature_c = 30.0
        self.q = np.array([1.0, 0.0, 0.0, 0.0])
        self.calls: list[float] = []

    def advance(self, dt: float) -> None:
        self.clock.t += dt

    def physics(self, t: float) -> dict:
        self.calls.append(t)
        return {"gyr": self.gyr.copy(), "acc": self.acc.copy(), "mag": self.mag.copy(),
                "temperature_c": self.temperature_c, "truth": SimpleNamespace(q=self.q.copy())}


def s16(hi: int, lo: int) -> int:
    v = (hi << 8) | lo
    return v - 0x10000 if v & 0x8000 else v


# --------------------------------------------------------------------------- per-part table
# name, driver factory, twin factory, physics key, identity register, default period (s)


PARTS = {
    "adxl345": dict(driver=lambda b, **k: ADXL345(b, **k), twin=SimulatedADXL345, key="acc",
                    id_reg=0x00, period=1 / 800),
    "l3g4200d": dict(driver=lambda b, **k: L3G4200D(b, **k), twin=SimulatedL3G4200D, key="gyr",
                     id_reg=0x0F, period=1 / 800),
    "hmc5883l": dict(driver=lambda b, **k: HMC5883L(b, **k), twin=SimulatedHMC5883L, key="mag",
                     id_reg=0x0A, period=1 / 75),
    "l3gd20": dict(driver=lambda b, **k: L3GD20(b, **k), twin=SimulatedL3GD20, key="gyr",
                   id_reg=0x0F, period=1 / 760),
    "lsm303dlhc_acc": dict(driver=lambda b, **k: LSM303DLHCAcc(b, **k), twin=SimulatedLSM303DLHCAcc,
                           key="acc", id_reg=None, period=1 / 1344),
    "lsm303dlhc_mag": dict(driver=lambda b, **k: LSM303DLHCMag(b, **k), twin=SimulatedLSM303DLHCMag,
                           key="mag", id_reg=0x0A, period=1 / 220),
    "mpu9250": dict(driver=lambda b, **k: MPU9250(b, **k), twin=SimulatedMPU9250, key="gyr",
                    id_reg=0x75, period=1 / 1000),
    "ak8963": dict(driver=lambda b, **k: AK8963(b, **k), twin=SimulatedAK8963, key="mag",
                   id_reg=0x00, period=1 / 100),
}


def setup_part(name: str, **driver_kw):
    """(src, bus, twin, driver) with the twin attached (and the MPU-9250 for the AK8963)."""
    spec = PARTS[name]
    src = StandInImu()
    bus = SimulatedI2CBus(src.clock, name="test-bus")
    visible_if = None
    if name == "ak8963":
        mpu = bus.attach(SimulatedMPU9250(src))
        visible_if = mpu.bypass_enabled
        MPU9250(bus).configure()
    twin = bus.attach(spec["twin"](src), visible_if=visible_if)
    twin.clock_error = 0.0  # register timing on the nominal grid (the default runs off it)
    driver = spec["driver"](bus, **driver_kw)
    return src, bus, twin, driver


def read_new(driver, bus):
    """The part's "new sample" call, whatever its shape, as counts (or None)."""
    if isinstance(driver, (HMC5883L, LSM303DLHCMag, AK8963)):
        return driver.read_if_new(bus.now_ns())
    r = driver.read_if_new()
    if isinstance(driver, MPU9250):
        return None if r is None else r[2]
    return r


def to_si(driver, counts):
    return driver.gyr_si(counts) if isinstance(driver, MPU9250) else driver.to_si(counts)


def first_sample(name: str, src, bus, driver):
    """Configures and steps the clock until the first sample is read.

    One period suffices for the parts with a data-ready flag; the Honeywell-style
    magnetometers take a reference reading and drop the first measurement after configuration.
    """
    driver.configure()
    period = PARTS[name]["period"]
    assert read_new(driver, bus) is None  # nothing measured yet
    periods = 3 if name in ("hmc5883l", "lsm303dlhc_mag") else 1
    for i in range(periods):
        src.advance(1.1 * period)
        counts = read_new(driver, bus)
        assert (counts is None) == (i < periods - 1)
    return counts


# --------------------------------------------------------------------------- identity


@pytest.mark.parametrize("name", [n for n, s in PARTS.items() if s["id_reg"] is not None])
def test_wrong_identity_names_bus_address_register_and_values(name):
    src, bus, twin, driver = setup_part(name)
    reg = PARTS[name]["id_reg"]
    twin.regs[reg] = 0x5A
    with pytest.raises(DeviceIdentityError) as exc:
        driver.configure()
    msg = str(exc.value)
    assert "test-bus" in msg
    assert f"0x{twin.address:02X}" in msg
    assert f"register 0x{reg:02X}" in msg
    assert "0x5A" in msg
    assert exc.value.read[0] == 0x5A


@pytest.mark.parametrize("name", list(PARTS))
def test_absent_device_is_a_clear_oserror(name):
    src, bus, twin, driver = setup_part(name)
    bus.set_present(twin.address, False)
    with pytest.raises(I2CDeviceError) as exc:
        driver.configure()
    assert exc.value.errno == errno.ENXIO
    assert "test-bus" in str(exc.value) and f"0x{twin.address:02X}" in str(exc.value)
    assert driver.diagnostics.bus_errors == driver.retries + 1


def test_identity_values_are_the_datasheet_ones():
    expected = {"adxl345": [0xE5], "l3g4200d": [0xD3], "l3gd20": [0xD4], "mpu9250": [0x71],
                "ak8963": [0x48], "hmc5883l": [0x48, 0x34, 0x33], "lsm303dlhc_mag": [0x48, 0x34, 0x33]}
    for name, ident in expected.items():
        src, bus, twin, driver = setup_part(name)
        got = bus.read_i2c_block_data(twin.address, PARTS[name]["id_reg"], len(ident))
        assert got == ident, name
        driver.configure()  # and the driver accepts it


def test_mpu9255_identity_is_accepted_and_others_refused():
    src = StandInImu()
    bus = SimulatedI2CBus(src.clock, name="b")
    bus.attach(SimulatedMPU9250(src, who_am_i=0x73))
    MPU9250(bus).configure()
    bus2 = SimulatedI2CBus(src.clock, name="b2")
    bus2.attach(SimulatedMPU9250(src, who_am_i=0x70))  # an MPU-6500
    with pytest.raises(DeviceIdentityError, match="0x70"):
        MPU9250(bus2).configure()


def test_l3gd20_driver_refuses_an_l3g4200d():
    src = StandInImu()
    bus = SimulatedI2CBus(src.clock, name="b")
    bus.attach(SimulatedL3G4200D(src, 0x6B))
    with pytest.raises(DeviceIdentityError, match=r"0xD3.*expected 0xD4"):
        L3GD20(bus).configure()


def test_lsm303dlhc_acc_without_id_register_is_checked_by_read_back():
    src = StandInImu()
    bus = SimulatedI2CBus(src.clock, name="b")
    bus.attach(SimulatedHMC5883L(src, 0x19))  # some other part answering at 0x19
    with pytest.raises(DeviceIdentityError) as exc:
        LSM303DLHCAcc(bus).configure()
    assert "0x19" in str(exc.value) and "register 0x23" in str(exc.value)


def test_ak8963_answers_only_in_mpu9250_bypass_mode():
    src = StandInImu()
    bus = SimulatedI2CBus(src.clock, name="b")
    mpu = bus.attach(SimulatedMPU9250(src))
    bus.attach(SimulatedAK8963(src), visible_if=mpu.bypass_enabled)
    assert bus.addresses() == [0x68]
    with pytest.raises(I2CDeviceError):
        AK8963(bus, retries=0).configure()
    MPU9250(bus).configure()
    assert bus.addresses() == [0x0C, 0x68]
    assert mpu.regs[0x37] & 0x02 and not mpu.regs[0x6A] & 0x20
    AK8963(bus).configure()


# --------------------------------------------------------------------------- configuration


def test_adxl345_configuration_registers():
    src, bus, twin, drv = setup_part("adxl345", range_g=4, rate_hz=400)
    drv.configure()
    assert twin.regs[0x2C] == 0x0C  # 400 Hz
    assert twin.regs[0x31] == 0x08 | 0x01  # FULL_RES, ±4 g
    assert twin.regs[0x2D] == 0x08  # Measure
    assert twin.rate_hz() == 400


@pytest.mark.parametrize("name,kw,ctrl1,ctrl4", [
    ("l3g4200d", dict(range_dps=500, rate_hz=200), 0x4F, 0x90),
    ("l3g4200d", dict(range_dps=2000, rate_hz=800), 0xCF, 0xA0),
    ("l3gd20", dict(range_dps=250, rate_hz=380), 0x8F, 0x80),
])
def test_st_gyro_configuration_registers(name, kw, ctrl1, ctrl4):
    src, bus, twin, drv = setup_part(name, **kw)
    drv.configure()
    assert twin.regs[0x20] == ctrl1  # DR bits 7:6, PD, Z/Y/X enable
    assert twin.regs[0x23] == ctrl4  # BDU, FS bits 5:4


def test_hmc5883l_configuration_registers():
    src, bus, twin, drv = setup_part("hmc5883l", range_ga=4.0, rate_hz=30, averaging=8)
    drv.configure()
    assert twin.regs[0x00] == (0b11 << 5) | (0b101 << 2)  # 8 averaged, 30 Hz, normal
    assert twin.regs[0x01] == 0b100 << 5  # ±4.0 Ga
    assert twin.regs[0x02] == 0x00  # continuous


def test_lsm303dlhc_configuration_registers():
    src, bus, twin, drv = setup_part("lsm303dlhc_acc", range_g=4, rate_hz=100)
    drv.configure()
    assert twin.regs[0x20] == 0x57  # 100 Hz, X/Y/Z on
    assert twin.regs[0x23] == 0x80 | 0x10 | 0x08  # BDU, ±4 g, HR
    src, bus, twin, drv = setup_part("lsm303dlhc_mag", range_ga=2.5, rate_hz=220)
    drv.configure()
    assert twin.regs[0x00] == 0b111 << 2
    assert twin.regs[0x01] == 0b011 << 5
    assert twin.regs[0x02] == 0x00


def test_mpu9250_configuration_registers():
    src, bus, twin, drv = setup_part("mpu9250", gyro_range_dps=500, acc_range_g=4, rate_hz=200)
    drv.configure()
    r = twin.regs
    assert r[0x19] == 4  # 1 kHz / (1 + 4) = 200 Hz
    assert r[0x1A] == 2  # 92 Hz DLPF: widest below 100 Hz
    assert r[0x1B] == 0b01 << 3 and r[0x1C] == 0b01 << 3 and r[0x1D] == 2
    assert r[0x6B] == 0x01 and r[0x37] == 0x02 and r[0x6A] == 0x00
    assert twin.rate_hz() == 200
    with pytest.raises(ValueError, match="1000 / \\(1 \\+ n\\)"):
        MPU9250(bus, rate_hz=300)


def test_ak8963_configuration_and_asa():
    src, bus, twin, drv = setup_part("ak8963")
    twin.asa = (150, 128, 100)
    drv.configure()
    assert twin.regs[0x0A] == 0x16  # 16-bit, continuous mode 2 (100 Hz)
    assert drv.asa == (150, 128, 100)
    np.testing.assert_allclose(drv.die_scale, 0.15 * np.array([1 + 22 / 256, 1.0, 1 - 28 / 256]))
    # the fuse ROM is not readable outside fuse-ROM access mode
    assert bus.read_i2c_block_data(0x0C, 0x10, 3) == [0, 0, 0]


@pytest.mark.parametrize("cls,kw", [(ADXL345, dict(range_g=3)), (L3G4200D, dict(rate_hz=760)),
                                    (HMC5883L, dict(rate_hz=220)), (AK8963, dict(bits=12)),
                                    (LSM303DLHCMag, dict(range_ga=0.88))])
def test_invalid_settings_are_refused_with_the_choices(cls, kw):
    bus = SimulatedI2CBus(StandInImu().clock)
    with pytest.raises(ValueError, match="must be"):
        cls(bus, **kw)


# --------------------------------------------------------------------------- scale and order


@pytest.mark.parametrize("name", list(PARTS))
def test_known_value_in_gives_si_out_within_one_lsb(name):
    src, bus, twin, drv = setup_part(name)
    src.gyr = np.array([0.7, -1.9, 2.6])
    src.acc = np.array([3.3, -5.1, -9.6])
    src.mag = np.array([23.0, -17.0, 41.0])
    counts = first_sample(name, src, bus, drv)
    got = to_si(drv, counts)
    key = PARTS[name]["key"]
    np.testing.assert_allclose(got, getattr(src, key), atol=drv.resolution + 1e-12)


def test_adxl345_bytes_little_endian_xyz():
    src, bus, twin, drv = setup_part("adxl345", range_g=16)
    src.acc = np.array([2 * G0, -1 * G0, 0.5 * G0])
    counts = first_sample("adxl345", src, bus, drv)
    assert counts == (512, -256, 128)  # 256 LSB/g in full resolution
    raw = bus.read_i2c_block_data(0x53, 0x32, 6)
    assert raw == [0x00, 0x02, 0x00, 0xFF, 0x80, 0x00]


def test_l3g4200d_bytes_little_endian_and_sensitivity():
    src, bus, twin, drv = setup_part("l3g4200d", range_dps=250)
    src.gyr = np.array([8.75e-3 * 1000, -8.75e-3 * 300, 8.75e-3 * 2]) * D2R  # 1000, −300, 2 digits
    counts = first_sample("l3g4200d", src, bus, drv)
    assert counts == (1000, -300, 2)
    assert twin.regs[0x28:0x2E] == bytes([0xE8, 0x03, 0xD4, 0xFE, 0x02, 0x00])


def test_st_auto_increment_needs_the_subaddress_msb():
    src, bus, twin, drv = setup_part("l3g4200d")
    first_sample("l3g4200d", src, bus, drv)
    same = bus.read_i2c_block_data(0x69, 0x28, 4)
    assert same == [twin.regs[0x28]] * 4
    assert bus.read_i2c_block_data(0x69, 0x80 | 0x28, 4) == list(twin.regs[0x28:0x2C])


def test_hmc5883l_data_order_x_z_y_big_endian_and_gain():
    src, bus, twin, drv = setup_part("hmc5883l", range_ga=1.3)
    src.mag = np.array([20.0, 5.0, 45.0])  # µT
    counts = first_sample("hmc5883l", src, bus, drv)
    x, y, z = round(0.20 * 1090), round(0.05 * 1090), round(0.45 * 1090)
    assert counts == (x, y, z)
    regs = list(twin.regs[0x03:0x09])
    assert regs == [x >> 8, x & 0xFF, z >> 8, z & 0xFF, y >> 8, y & 0xFF]
    np.testing.assert_allclose(drv.to_si(counts), src.mag, atol=100 / 1090)


def test_hmc5883l_pointer_wraps():
    src, bus, twin, drv = setup_part("hmc5883l")
    first_sample("hmc5883l", src, bus, drv)
    data = list(twin.regs[0x03:0x09])
    # after the status register (0x09) the pointer goes back to the first data register
    assert bus.read_i2c_block_data(0x1E, 0x09, 8) == [twin.regs[0x09]] + data + [twin.regs[0x09]]
    # after identification C (0x0C) it goes to 0x00
    assert bus.read_i2c_block_data(0x1E, 0x0A, 4) == [0x48, 0x34, 0x33, twin.regs[0x00]]


def test_lsm303dlhc_mag_separate_xy_and_z_gain():
    src, bus, twin, drv = setup_part("lsm303dlhc_mag", range_ga=1.3)
    src.mag = np.array([30.0, -10.0, 50.0])
    counts = first_sample("lsm303dlhc_mag", src, bus, drv)
    assert counts == (round(0.3 * 1100), round(-0.1 * 1100), round(0.5 * 980))
    z = counts[2]
    assert list(twin.regs[0x05:0x07]) == [z >> 8, z & 0xFF]  # Z sits between X and Y


def test_lsm303dlhc_acc_left_justified_12_bit():
    src, bus, twin, drv = setup_part("lsm303dlhc_acc", range_g=2)
    src.acc = np.array([0.5 * G0, -0.25 * G0, 1.0 * G0])
    counts = first_sample("lsm303dlhc_acc", src, bus, drv)
    assert counts == (500 * 16, -250 * 16, 1000 * 16)  # 1 mg/LSB, shifted left by 4
    assert s16(twin.regs[0x29], twin.regs[0x28]) == 8000


def test_mpu9250_big_endian_frame_and_temperature():
    src, bus, twin, drv = setup_part("mpu9250", gyro_range_dps=250, acc_range_g=2)
    src.acc = np.array([0.5, -0.25, 1.0]) * G0
    src.gyr = np.array([10.0, -20.0, 1.0]) * D2R
    src.temperature_c = 31.0
    drv.configure()
    src.advance(0.001)
    acc, temp, gyr = drv.read_if_new()
    assert acc == (8192, -4096, 16384)
    assert gyr == (1310, -2620, 131)
    assert s16(twin.regs[0x3B], twin.regs[0x3C]) == 8192
    assert abs(drv.temperature_c(temp) - 31.0) <= 1 / 333.87


def test_ak8963_die_axes_and_asa():
    src, bus, twin, drv = setup_part("ak8963")
    twin.asa = (176, 128, 80)
    src.mag = np.array([30.0, -12.0, 40.0])  # MPU-9250 axes
    counts = first_sample("ak8963", src, bus, drv)
    adj = [1 + 48 / 256, 1.0, 1 - 48 / 256]
    die = [-12.0, 30.0, -40.0]  # X_mag = Y_acc, Y_mag = X_acc, Z_mag = −Z_acc
    assert counts == tuple(round(b / (0.15 * a)) for b, a in zip(die, adj))
    np.testing.assert_allclose(drv.to_si(counts), src.mag, atol=0.15 * 1.2)


# --------------------------------------------------------------------------- data ready


@pytest.mark.parametrize("name", list(PARTS))
def test_no_new_data_gives_none_and_reading_clears_the_flag(name):
    src, bus, twin, drv = setup_part(name)
    first_sample(name, src, bus, drv)
    assert read_new(drv, bus) is None  # same instant: nothing new
    src.advance(1.1 * PARTS[name]["period"])
    assert read_new(drv, bus) is not None


@pytest.mark.parametrize("name,status_reg,bit", [
    ("l3g4200d", 0x27, 0x08), ("l3gd20", 0x27, 0x08), ("lsm303dlhc_acc", 0x27, 0x08),
    ("adxl345", 0x30, 0x80), ("mpu9250", 0x3A, 0x01), ("ak8963", 0x02, 0x01),
])
def test_status_bit_set_by_new_data_and_cleared_by_the_data_read(name, status_reg, bit):
    src, bus, twin, drv = setup_part(name)
    drv.configure()
    assert not bus.read_byte_data(twin.address, status_reg) & bit
    src.advance(PARTS[name]["period"])
    assert bus.read_byte_data(twin.address, status_reg) & bit
    if name == "adxl345":
        drv.read_counts()
    else:
        read_new(drv, bus)
    assert not bus.read_byte_data(twin.address, status_reg) & bit


def test_st_gyro_overrun_is_counted():
    src, bus, twin, drv = setup_part("l3g4200d")
    first_sample("l3g4200d", src, bus, drv)
    src.advance(3 / 800)  # three samples, two never read
    assert drv.read_if_new() is not None
    assert drv.overruns == 1
    assert drv.diagnostics.extra["gyr_overruns"] == 1
    assert drv.read_if_new() is None


def test_hmc5883l_pacing_never_returns_one_measurement_twice():
    src, bus, twin, drv = setup_part("hmc5883l")
    drv.configure()
    seen = []
    for _ in range(3000):  # 3 s polled at 1 kHz
        src.advance(1e-3)
        src.mag = src.mag + 0.01  # every measurement differs
        c = drv.read_if_new(bus.now_ns())
        if c is not None:
            seen.append(c)
    assert len(seen) == len(set(seen))  # no measurement twice
    assert twin.samples_latched - 3 <= len(seen) <= twin.samples_latched


def test_hmc5883l_pacing_of_a_constant_field():
    src, bus, twin, drv = setup_part("hmc5883l")
    drv.configure()
    n = 0
    for _ in range(3000):  # identical measurements: only the period says a reading is new
        src.advance(1e-3)
        n += drv.read_if_new(bus.now_ns()) is not None
    assert 1000 / 14 * 3 - 3 <= n <= twin.samples_latched  # one per ceil(1.05 × 13.3 ms)


def test_hmc5883l_lock_holds_data_after_a_partial_read():
    src, bus, twin, drv = setup_part("hmc5883l")
    first = first_sample("hmc5883l", src, bus, drv)
    bus.read_i2c_block_data(0x1E, 0x03, 2)  # X only
    assert bus.read_byte_data(0x1E, 0x09) & 0x02  # LOCK
    src.mag = src.mag * 2
    src.advance(3 / 75)
    assert drv.read_counts() == first  # held: the old measurement completes the read
    assert not bus.read_byte_data(0x1E, 0x09) & 0x02
    src.advance(1 / 75)
    assert drv.read_counts() != first


def test_ak8963_data_overrun_and_hold_until_st2():
    src, bus, twin, drv = setup_part("ak8963")
    drv.configure()
    src.advance(2.5 / 100)
    st1 = bus.read_byte_data(0x0C, 0x02)
    assert st1 & 0x01 and st1 & 0x02  # DRDY and DOR: one measurement skipped
    before = list(twin.regs[0x03:0x09])
    src.mag = src.mag + 5
    src.advance(1 / 100)  # held: ST1 read started a read that ST2 ends
    assert bus.read_i2c_block_data(0x0C, 0x03, 7)[:6] == before
    src.advance(1 / 100)
    assert bus.read_byte_data(0x0C, 0x02) & 0x01


# --------------------------------------------------------------------------- saturation


@pytest.mark.parametrize("name,key,value", [
    ("adxl345", "acc", [0, 0, -9 * G0]), ("l3g4200d", "gyr", [0, 40.0, 0]),
    ("hmc5883l", "mag", [250.0, 0, 0]), ("l3gd20", "gyr", [-40.0, 0, 0]),
    ("lsm303dlhc_acc", "acc", [0, 0, 9 * G0]), ("lsm303dlhc_mag", "mag", [0, 0, -300.0]),
    ("ak8963", "mag", [3000.0, 2000.0, 100.0]),
])
def test_saturation_is_detected(name, key, value):
    src, bus, twin, drv = setup_part(name)
    counts = first_sample(name, src, bus, drv)
    assert not drv.is_saturated(counts)
    setattr(src, key, np.array(value, dtype=float))
    src.advance(1.1 * PARTS[name]["period"])
    counts = read_new(drv, bus)
    assert drv.is_saturated(counts)


def test_hmc5883l_overflow_code():
    src, bus, twin, drv = setup_part("hmc5883l", range_ga=0.88)
    src.mag = np.array([0.0, 160.0, 0.0])  # 1.6 Ga × 1370 LSB/Ga > 2047: the Y ADC overflows
    counts = first_sample("hmc5883l", src, bus, drv)
    assert counts[1] == -4096 and counts[0] == 0
    assert drv.is_saturated(counts)


# --------------------------------------------------------------------------- transient errors


@pytest.mark.parametrize("name", list(PARTS))
def test_transient_errors_are_retried_and_counted(name):
    src, bus, twin, drv = setup_part(name)
    first_sample(name, src, bus, drv)
    d = drv.diagnostics
    src.advance(1.1 * PARTS[name]["period"])
    bus.inject_errors(twin.address, 2)
    assert read_new(drv, bus) is not None
    assert (d.bus_errors, d.retries) == (2, 2)
    assert "injected" in d.last_error
    bus.inject_errors(twin.address, 3)
    src.advance(1.1 * PARTS[name]["period"])
    with pytest.raises(I2CDeviceError):
        read_new(drv, bus)
    assert (d.bus_errors, d.retries) == (5, 4)


# --------------------------------------------------------------------------- boards


def stand_in_board(name, **options):
    src = StandInImu()
    board = make_simulated_board(name, src, **options)
    for addr in board.bus.addresses():  # counted against the nominal rates below
        board.bus.device(addr).clock_error = 0.0
    board.open()
    return src, board


BOARD_GYRO = {"gy80": (0x69, 800), "minimu9v2": (0x6B, 760), "mpu9250": (0x68, 1000)}


@pytest.mark.parametrize("name", board_names())
def test_board_gives_each_gyro_sample_once_with_mag_when_new(name):
    # the GY-80 and MinIMU-9 v2 polled (their FIFO path: tests/test_fifo_st_adxl.py), the
    # MPU-9250 through its FIFO (the magnetometer's pacing is the same on both paths)
    src, board = stand_in_board(name, **({} if name == "mpu9250" else {"fifo": False}))
    addr, rate = BOARD_GYRO[name]
    samples = []
    for _ in range(1000):  # 1 s at 1 kHz
        src.advance(1e-3)
        s = board.read()
        if s is not None:
            samples.append(s)
    gyro_twin = board.bus.device(addr)
    # a FIFO board (the MPU-9250's default) has the samples of its last drain period still
    # waiting in the FIFO: handed out at the next drain, none lost
    waiting = gyro_twin.fifo_frames + board.pending if getattr(board, "fifo", False) else 0
    assert len(samples) + waiting == gyro_twin.samples_latched
    assert abs(len(samples) + waiting - rate) <= 1
    t = np.array([s.t_ns for s in samples])
    assert np.all(np.diff(t) > 0)
    s = samples[-1]
    assert s.flags & (GYR_VALID | ACC_VALID) == GYR_VALID | ACC_VALID
    np.testing.assert_allclose(s.gyr, src.gyr, atol=0.002)
    np.testing.assert_allclose(s.acc, src.acc, atol=0.05)
    np.testing.assert_allclose(s.truth_q, src.q)
    if name == "mpu9250":  # its die temperature comes in the same burst as gyro and accelerometer
        assert abs(s.temperature_c - src.temperature_c) <= 1 / 333.87 and "temp" in s.raw
    else:
        assert s.temperature_c is None
    with_mag = [x for x in samples if x.mag is not None]
    assert all(x.flags & MAG_NEW and x.flags & MAG_VALID for x in with_mag)
    assert all(not x.flags & MAG_NEW for x in samples if x.mag is None)
    mag_twin = board.bus.device(board.parts["mag"].address)
    assert 0.85 * mag_twin.samples_latched <= len(with_mag) <= mag_twin.samples_latched
    np.testing.assert_allclose(with_mag[-1].mag, src.mag, atol=0.5)
    # drained (counted) but not handed out yet: the FIFO board's queue
    assert board.diagnostics.samples == len(samples) + getattr(board, "pending", 0)
    assert board.diagnostics.bus_errors == 0


def test_board_counts_gyro_overruns_in_its_diagnostics():
    src, board = stand_in_board("gy80", fifo=False)
    src.advance(1 / 800)
    assert board.read() is not None and "gyr_overruns" not in board.diagnostics.extra
    src.advance(3 / 800)  # three samples, two never read
    assert board.read() is not None
    assert board.diagnostics.extra["gyr_overruns"] == 1


def test_board_read_is_lean():
    src, board = stand_in_board("gy80", fifo=False)
    s = None
    while s is None or s.mag is None:  # up to a fresh magnetometer reading
        src.advance(1 / 800)
        s = board.read()
    bus = board.bus
    start = bus.transfers
    src.advance(1 / 800)
    assert board.read() is not None and bus.transfers - start == 3  # gyro status, gyro, acc
    assert board.read() is None and bus.transfers - start == 4  # gyro status only


def test_board_saturation_flags():
    src, board = stand_in_board("gy80", gyro_range_dps=250, acc_range_g=2, fifo=False)
    src.gyr = np.array([0.0, 0.0, 5.0])  # 286 °/s > 250
    src.acc = np.array([0.0, 0.0, -3 * G0])
    src.advance(1 / 800)
    s = board.read()
    assert s.flags & GYR_SATURATED and not s.flags & GYR_VALID
    assert s.flags & ACC_SATURATED and not s.flags & ACC_VALID
    assert board.diagnostics.saturated == 2


def test_board_mag_saturation_flag():
    src, board = stand_in_board("mpu9250")
    src.mag = np.array([4000.0, 4000.0, 0.0])  # beyond the AK8963's 4912 µT sum
    s = None
    for _ in range(20):
        src.advance(1e-3)
        s = board.read() or s
        if s is not None and s.mag is not None:
            break
    assert s.flags & MAG_NEW and s.flags & MAG_SATURATED and not s.flags & MAG_VALID


def test_board_non_finite_reading_not_valid():
    src, board = stand_in_board("gy80", fifo=False)
    board.parts["acc"].scale = np.array([np.nan, 1.0, 1.0])  # e.g. a corrupted calibration
    src.advance(1 / 800)
    s = board.read()
    assert s.flags & GYR_VALID and not s.flags & ACC_VALID
    assert board.diagnostics.non_finite == 1


def test_board_survives_transient_errors():
    src, board = stand_in_board("minimu9v2", fifo=False)
    board.bus.inject_errors(0x6B, 1)
    board.bus.inject_errors(0x19, 2)
    src.advance(1 / 760)
    s = board.read()
    assert s is not None
    d = board.diagnostics
    assert (d.bus_errors, d.retries, d.device_lost) == (3, 3, False)


@pytest.mark.parametrize("name,role", [("gy80", "gyro"), ("gy80", "acc"), ("minimu9v2", "gyro"),
                                       ("mpu9250", "gyro")])
def test_board_device_loss_and_recovery_with_reinitialisation(name, role):
    src, board = stand_in_board(name)
    part = board.parts[role]
    bus = board.bus
    # a FIFO board (the MPU-9250's default) drains every 10 ms: the first rows come then
    src.advance(11e-3 if getattr(board, "fifo", False) else 2e-3)
    assert board.read() is not None
    while board.read() is not None:  # the rest of that drain, read before the loss
        pass
    bus.set_present(part.address, False)
    for _ in range(100):  # 0.1 s gone: never raises, nothing returned
        src.advance(1e-3)
        assert board.read() is None
    d = board.diagnostics
    assert d.device_lost and f"0x{part.address:02X}" in d.last_error
    assert role in board.lost
    bus.set_present(part.address, True)  # back, power-cycled: needs configuring again
    twin = bus.device(part.address)
    assert not twin.measuring or name == "mpu9250"  # the MPU-9250 samples from power-on
    got = []
    for _ in range(200):
        src.advance(1e-3)
        s = board.read()
        if s is not None:
            got.append(s)
    assert got, "no samples after the device came back"
    assert not d.device_lost and not board.lost
    assert d.reinitialisations >= 1
    if name == "mpu9250":
        assert bus.device(0x68).regs[0x37] & 0x02  # bypass on again, AK8963 reachable
        assert any(s.mag is not None for s in got)
    else:
        assert twin.measuring and twin.rate_hz() == part.rate_hz


def test_board_lost_magnetometer_keeps_gyro_and_acc_flowing():
    src, board = stand_in_board("gy80")
    board.bus.set_present(0x1E, False)
    got = []
    for _ in range(200):
        src.advance(1e-3)
        s = board.read()
        if s is not None:
            got.append(s)
    assert len(got) >= 150 and all(s.mag is None for s in got)
    assert board.diagnostics.device_lost and "mag" in board.lost
    board.bus.set_present(0x1E, True)
    for _ in range(200):
        src.advance(1e-3)
        s = board.read()
        if s is not None:
            got.append(s)
    assert not board.diagnostics.device_lost
    assert board.bus.device(0x1E).regs[0x02] == 0x00  # continuous mode again
    assert any(s.mag is not None for s in got[-100:])


def test_board_recovery_attempts_are_paced():
    src, board = stand_in_board("gy80", reinit_period_s=0.05, fifo=False)
    board.bus.set_present(0x69, False)
    src.advance(1e-3)
    board.read()
    errors = board.diagnostics.bus_errors
    for _ in range(10):  # 10 ms: no new attempt
        src.advance(1e-3)
        board.read()
    assert board.diagnostics.bus_errors == errors
    src.advance(0.05)
    board.read()
    assert board.diagnostics.bus_errors == errors + board.retries + 1


def test_board_names_and_options_are_checked():
    with pytest.raises(ValueError, match="gy80, minimu9v2, mpu9250"):
        make_simulated_board("gy-81", StandInImu())
    with pytest.raises(ValueError, match="gyro_rate"):
        make_simulated_board("gy80", StandInImu(), gyro_rate=100)
    with pytest.raises(ValueError, match="unknown I2C board"):
        make_board("nope", 1)


def test_board_custom_addresses():
    src, board = stand_in_board("gy80", gyro_address=0x68, acc_address=0x1D, fifo=False)
    assert board.bus.addresses() == [0x1D, 0x1E, 0x68]
    src.advance(1 / 800)
    assert board.read() is not None


def test_smbus_missing_device_node_is_explained():
    with pytest.raises(FileNotFoundError, match=r"/dev/i2c-250 does not exist.*enable I2C"):
        SMBusI2C(250)


def test_simulated_bus_rejects_bad_arguments():
    bus = SimulatedI2CBus(StandInImu().clock, name="b")
    with pytest.raises(ValueError, match="0x80"):
        bus.read_byte_data(0x80, 0)
    with pytest.raises(ValueError, match="1..32"):
        bus.read_i2c_block_data(0x10, 0, 33)
    with pytest.raises(OSError) as exc:
        bus.read_byte_data(0x10, 0)
    assert exc.value.errno == errno.ENXIO and "0x10" in str(exc.value)


def test_error_names_the_datasheet_register_without_the_increment_flag():
    src, bus, twin, drv = setup_part("l3g4200d", retries=0)
    drv.configure()
    bus.inject_errors(0x69, 1)
    with pytest.raises(I2CDeviceError) as exc:
        drv.read_counts()  # sent as 0x80 | 0x28
    assert exc.value.register == 0x28
    assert "L3G4200D at test-bus address 0x69: reading register 0x28" in str(exc.value)


class FakeSMBus:
    """Stands in for smbus2.SMBus: records calls, answers like one ADXL345."""

    def __init__(self, bus):
        self.bus, self.calls, self.closed = bus, [], False

    def read_byte_data(self, addr, reg):
        self.calls.append(("rb", addr, reg))
        return 0xE5

    def write_byte_data(self, addr, reg, value):
        self.calls.append(("wb", addr, reg, value))

    def read_i2c_block_data(self, addr, reg, n):
        self.calls.append(("rblk", addr, reg, n))
        return list(range(n))

    def write_i2c_block_data(self, addr, reg, data):
        self.calls.append(("wblk", addr, reg, data))

    def close(self):
        self.closed = True


def test_smbus_backend_passes_transfers_through(monkeypatch):
    import os

    import smbus2

    monkeypatch.setattr(smbus2, "SMBus", FakeSMBus)
    monkeypatch.setattr(os.path, "exists", lambda p: p == "/dev/i2c-7")
    bus = SMBusI2C(7)
    assert bus.name == "/dev/i2c-7" and bus._smbus.bus == 7
    drv = ADXL345(bus, range_g=2, rate_hz=100)
    drv.configure()
    assert ("wb", 0x53, 0x31, 0x08) in bus._smbus.calls  # FULL_RES, ±2 g
    assert drv.read_counts() == (0x0100, 0x0302, 0x0504)  # bytes 0…5, little-endian
    assert bus._smbus.calls[-1] == ("rblk", 0x53, 0x32, 6)
    bus.close()
    assert bus._smbus.closed


class FakeI2CAdapter(FakeSMBus):
    """smbus2.SMBus on an adapter that speaks plain I2C (``funcs`` has I2C_FUNC_I2C): a
    combined write-then-read (``i2c_rdwr``) answers bytes 0, 1, 2, … like a FIFO stream."""

    def __init__(self, bus):
        import smbus2

        super().__init__(bus)
        self.funcs = smbus2.I2cFunc.I2C | smbus2.I2cFunc.SMBUS_READ_I2C_BLOCK

    def i2c_rdwr(self, *msgs):
        write, read = msgs
        self.calls.append(("rdwr", write.addr, list(write), read.addr, read.len))
        for i in range(read.len):
            read.buf[i] = bytes([i % 256])


def test_a_plain_i2c_adapter_reads_a_long_burst_in_one_combined_transaction(monkeypatch):
    import os

    import smbus2

    monkeypatch.setattr(os.path, "exists", lambda p: p == "/dev/i2c-1")
    monkeypatch.setattr(smbus2, "SMBus", FakeI2CAdapter)
    bus = SMBusI2C(1)
    assert bus.max_read_bytes == 8192
    assert bus.read_burst(0x68, 0x74, 120) == list(range(120))
    assert bus._smbus.calls[-1] == ("rdwr", 0x68, [0x74], 0x68, 120)  # register, then 120 bytes
    assert bus.read_burst(0x68, 0x74, 12) == list(range(12))  # short: an SMBus block
    assert bus._smbus.calls[-1] == ("rblk", 0x68, 0x74, 12)
    with pytest.raises(ValueError, match="1..8192 bytes"):
        bus.read_burst(0x68, 0x74, 8193)
    monkeypatch.setattr(smbus2, "SMBus", FakeSMBus)  # no funcs: SMBus blocks only
    smbus_only = SMBusI2C(1)
    assert smbus_only.max_read_bytes == 32
    with pytest.raises(ValueError, match="SMBus blocks are 1..32 bytes"):
        smbus_only.read_burst(0x68, 0x74, 120)


def test_smbus_permission_problem_is_explained(monkeypatch):
    import os

    import smbus2

    def denied(bus):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(smbus2, "SMBus", denied)
    monkeypatch.setattr(os.path, "exists", lambda p: True)
    with pytest.raises(PermissionError, match=r"/dev/i2c-3: add the service user to the 'i2c' group"):
        SMBusI2C(3)
