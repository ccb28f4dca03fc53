"""The 32-level FIFOs of the ADXL345, L3G4200D, L3GD20 and LSM303DLHC accelerometer on their
simulated twins, register by register, and the GY-80 / MinIMU-9 v2 FIFO paths.

The twins follow the register maps cited in ``drivers/i2c/st_fifo.py`` and
``drivers/i2c/adxl345.py``: these tests check what the drivers write, what a burst carries
(order, scale, transfers), the watermark flag, an overflow → counted loss → recovery, and the
pairing rule of the two boards whose gyroscope and accelerometer run on separate clocks.
The stand-in physics ramps with time (rate x = 20·t rad/s, force x = 100·t m/s²), so each
row's value says which sample it is.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ahrs_service.core.samples import ACC_SATURATED, ACC_VALID, GYR_SATURATED, GYR_VALID
from ahrs_service.drivers.boards import make_simulated_board
from ahrs_service.drivers.parts import adxl345 as adxl
from ahrs_service.drivers.parts import st_fifo as st
from ahrs_service.drivers.parts.adxl345 import ADXL345
from ahrs_service.drivers.parts.l3g4200d import L3G4200D
from ahrs_service.drivers.parts.l3gd20 import L3GD20
from ahrs_service.drivers.parts.lsm303dlhc import LSM303DLHCAcc
from ahrs_service.drivers.sim.adxl345 import SimulatedADXL345
from ahrs_service.drivers.sim.bus import SimulatedI2CBus
from ahrs_service.drivers.sim.clock import ManualClock
from ahrs_service.drivers.sim.l3g4200d import SimulatedL3G4200D
from ahrs_service.drivers.sim.l3gd20 import SimulatedL3GD20
from ahrs_service.drivers.sim.lsm303dlhc import SimulatedLSM303DLHCAcc

GYR_SLOPE, ACC_SLOPE = 20.0, 100.0


class RampImu:
    """Readings that say when they were taken; a clock the test moves."""

    def __init__(self) -> None:
        self.clock = ManualClock()
        self.advance = self.clock.advance

    def physics(self, t: float) -> dict:
        return {"gyr": (GYR_SLOPE * t, 0.1, -0.1), "acc": (ACC_SLOPE * t, 0.5, -9.8),
                "mag": (20.0, -5.0, 40.0), "truth": SimpleNamespace(q=np.array([1.0, t, 0.0, 0.0]))}


# part name → driver, twin, physics key, rate, SI per count of the ramp's axis, FIFO_CTRL value
PARTS = {
    "adxl345": dict(driver=lambda b: ADXL345(b, range_g=16, rate_hz=400, fifo=True, watermark=10),
                    twin=SimulatedADXL345, key="acc", slope=ACC_SLOPE, rate=400.0,
                    ctrl=(adxl.FIFO_CTL, 0x80 | 10), per_transfer=1),
    "l3g4200d": dict(driver=lambda b: L3G4200D(b, rate_hz=800, fifo=True, watermark=10),
                     twin=SimulatedL3G4200D, key="gyr", slope=GYR_SLOPE, rate=800.0,
                     ctrl=(st.FIFO_CTRL_REG, 0x40 | 10), per_transfer=5),
    "l3gd20": dict(driver=lambda b: L3GD20(b, rate_hz=760, fifo=True, watermark=10),
                   twin=SimulatedL3GD20, key="gyr", slope=GYR_SLOPE, rate=760.0,
                   ctrl=(st.FIFO_CTRL_REG, 0x40 | 10), per_transfer=5),
    "lsm303dlhc_acc": dict(driver=lambda b: LSM303DLHCAcc(b, range_g=16, rate_hz=400, fifo=True, watermark=10),
                           twin=SimulatedLSM303DLHCAcc, key="acc", slope=ACC_SLOPE, rate=400.0,
                           ctrl=(st.FIFO_CTRL_REG, 0x80 | 10), per_transfer=5),
}


def part_on_bus(name):
    spec = PARTS[name]
    src = RampImu()
    bus = SimulatedI2CBus(src.clock)
    twin = bus.attach(spec["twin"](src))
    twin.clock_error = 0.0  # register timing on the nominal grid (the default runs off it)
    drv = spec["driver"](bus)
    drv.configure()
    return spec, src, bus, twin, drv


class Transfers:
    def __init__(self, bus):
        self.blocks: list[tuple[int, int]] = []
        inner = bus.read_i2c_block_data

        def read_block(addr, reg, n):
            self.blocks.append((reg & 0x7F, n))
            return inner(addr, reg, n)

        bus.read_i2c_block_data = read_block


@pytest.mark.parametrize("name", PARTS)
def test_configuration_registers(name):
    spec, src, bus, twin, drv = part_on_bus(name)
    reg, value = spec["ctrl"]
    assert twin.regs[reg] == value  # stream mode, watermark 10
    if name != "adxl345":
        assert twin.regs[st.CTRL_REG5] & st.FIFO_EN
    assert twin.fifo_frames == 0 and twin.fifo_room() == 32 and not twin.fifo_keeps_oldest()


@pytest.mark.parametrize("name", PARTS)
def test_burst_layout_scale_order_and_transfers(name):
    spec, src, bus, twin, drv = part_on_bus(name)
    period = 1.0 / spec["rate"]
    src.advance(12.5 * period)  # 12 samples
    status = drv.fifo_status()
    assert status.level == 12 and not status.overflow
    tr = Transfers(bus)
    counts = drv.read_fifo(12)
    data_reg = adxl.DATAX0 if name == "adxl345" else st.OUT_X_L
    reads = [n for reg, n in tr.blocks if reg == data_reg]
    per = spec["per_transfer"]
    # ST: OUT_Z_H rolls over to OUT_X_L with the next sample, 5 samples a 30-byte block;
    # ADXL345: one entry per 6-byte read of DATAX0…DATAZ1
    assert reads == ([30, 30, 12] if per == 5 else [6] * 12)
    assert drv.fifo_layout.transfers(12) == len(reads)
    si = counts[:, 0] * drv.scale[0]
    true_t = np.arange(1, 13) * period  # samples k / rate, oldest first
    np.testing.assert_allclose(si / spec["slope"], true_t, atol=drv.resolution / spec["slope"])
    assert twin.fifo_frames == 0 and (drv.fifo_status().level, drv.fifo_status().overflow) == (0, False)
    assert len(twin.take_popped_truth()) == 12


@pytest.mark.parametrize("name", PARTS)
def test_watermark_flag(name):
    spec, src, bus, twin, drv = part_on_bus(name)
    period = 1.0 / spec["rate"]

    def wtm():
        if name == "adxl345":
            return bool(bus.read_byte_data(0x53, adxl.INT_SOURCE) & adxl.WATERMARK)
        return bool(bus.read_byte_data(twin.address, st.FIFO_SRC_REG) & st.SRC_WTM)

    src.advance(9.5 * period)
    twin.update(src.clock.now())  # the twin latches on bus access; fifo_frames is not one
    assert twin.fifo_frames == 9
    assert not wtm()
    src.advance(period)
    assert wtm()  # 10 stored: at the watermark
    drv.read_fifo(1)
    assert not wtm()


@pytest.mark.parametrize("name", PARTS)
def test_overflow_keeps_the_newest_32_and_reset_empties(name):
    spec, src, bus, twin, drv = part_on_bus(name)
    period = 1.0 / spec["rate"]
    src.advance(50.5 * period)  # 50 samples, 32 fit
    status = drv.fifo_status()
    assert (status.level, status.overflow) == (32, True)
    assert twin.fifo_overflowed == 18
    counts = drv.read_fifo(32)
    t = counts[:, 0] * drv.scale[0] / spec["slope"]
    # stream mode: the oldest were overwritten, the newest 32 (samples 19 … 50) kept
    np.testing.assert_allclose(t, np.arange(19, 51) * period, atol=drv.resolution / spec["slope"])
    assert (drv.fifo_status().level, drv.fifo_status().overflow) == (0, False)
    src.advance(5 * period)
    assert drv.fifo_status().level == 5
    drv.fifo_reset()
    assert twin.fifo_frames == 0 and twin.fifo_discarded == 5
    src.advance(3 * period)
    assert drv.fifo_status().level == 3  # filling again after the reset


# ------------------------------------------------------------------ boards

BOARDS = {"gy80": dict(gyro=0x69, acc=0x53, rate=800.0, options=dict(acc_range_g=16, acc_rate_hz=400)),
          "minimu9v2": dict(gyro=0x6B, acc=0x19, rate=760.0, options=dict(acc_range_g=16, acc_rate_hz=400))}


def board_run(name, seconds, stall_at=None, stall_s=0.0, clock_error=0.0, **options):
    spec = BOARDS[name]
    src = RampImu()
    board = make_simulated_board(name, src, **{**spec["options"], **options})
    for addr in (spec["gyro"], spec["acc"]):
        board.bus.device(addr).clock_error = clock_error
    board.open()
    blocks = []
    for i in range(int(round(seconds / 1e-3))):
        if stall_at is not None and i == stall_at:
            src.advance(stall_s)  # the host stopped: no read for stall_s
        src.advance(1e-3)
        blocks.append(board.read_block())
    return board, blocks


def before_first_acc(name) -> int:
    """Gyroscope samples older than the accelerometer's first one: no row (the pairing rule
    has no accelerometer value for them; only at the start)."""
    return int(np.ceil(BOARDS[name]["rate"] / 400.0)) - 1


def joined(blocks):
    return (np.concatenate([b.t_ns for b in blocks]), np.concatenate([b.gyr for b in blocks]),
            np.concatenate([b.acc for b in blocks]), np.concatenate([b.truth_q for b in blocks if len(b)]))


@pytest.mark.parametrize("name", BOARDS)
def test_board_fifo_rows_every_gyro_sample_on_its_clock(name):
    board, blocks = board_run(name, 0.5)
    spec = BOARDS[name]
    gyro_twin = board.bus.device(spec["gyro"])
    t, gyr, acc, truth = joined(blocks)
    # every sample the gyroscope produced is a row (or still waiting in its FIFO), in order
    skipped = before_first_acc(name)
    assert len(t) + gyro_twin.fifo_frames + skipped == gyro_twin.samples_due
    np.testing.assert_allclose(truth[:, 1], np.arange(1 + skipped, len(t) + 1 + skipped) / spec["rate"],
                               atol=1e-9)
    # a drain every 5 ms (fifo_read_hz 200), each at most its FIFO's depth
    drains = [len(b) for b in blocks if len(b)]
    assert max(drains) <= 32 and len(drains) >= 95
    # times on the gyroscope's clock. Each read bounds its newest sample to one period (the
    # latest time allowed is the read itself), so every row is within a period of its true
    # time; the part's period is known to about a sample over the reads' span, so in the
    # first reads a row can also come out before its true time. Settled (the second half),
    # the rows are on the truth and the tracked rate on the part's
    err = t - np.rint(truth[:, 1] * 1e9)
    period = 1e9 / spec["rate"]
    # (measured on this simulated clock: settled within 2.2 % of a period, rate within 2.3e-5)
    assert np.all(np.abs(err) < period)
    assert np.max(np.abs(err[len(err) // 2:])) < 0.03 * period
    assert abs(board.timeline.clock.rate_hz / spec["rate"] - 1.0) < 1e-4
    assert board.diagnostics.lost.total == 0
    mags = sum(int(np.isfinite(b.mag[:, 0]).sum()) for b in blocks)
    assert mags > 0 and all(np.isfinite(b.mag[:-1]).sum() == 0 for b in blocks if len(b))


@pytest.mark.parametrize("name", BOARDS)
def test_board_pairing_rule_holds_the_newest_accelerometer_sample(name):
    board, blocks = board_run(name, 0.5)
    t, gyr, acc, truth = joined(blocks)
    row_t = truth[:, 1]
    acc_t = acc[:, 0] / ACC_SLOPE  # when the accelerometer sample of each row was taken
    res = board.parts["acc"].resolution / ACC_SLOPE
    assert np.all(acc_t <= row_t + res)  # never a value from the row's future
    assert np.all(row_t - acc_t < 1 / 400 + res)  # the newest one: held less than its period
    assert len(np.unique(np.round(acc_t / (1 / 400)))) > 150  # each accelerometer sample used


@pytest.mark.parametrize("name", BOARDS)
def test_board_stop_shorter_than_the_fifo_loses_nothing(name):
    board, blocks = board_run(name, 0.5, stall_at=250, stall_s=0.030)  # 24 of 32 samples
    spec = BOARDS[name]
    gyro_twin = board.bus.device(spec["gyro"])
    t, *_ = joined(blocks)
    assert board.diagnostics.lost.total == 0 and gyro_twin.fifo_overflowed == 0
    assert len(t) + gyro_twin.fifo_frames + before_first_acc(name) == gyro_twin.samples_due
    assert np.max(np.diff(t)) < 1.5e9 / spec["rate"]


@pytest.mark.parametrize("name", BOARDS)
@pytest.mark.parametrize("clock_error", [0.0, 0.008])
def test_board_stop_longer_than_the_fifo_counts_what_the_gyro_overwrote(name, clock_error):
    board, blocks = board_run(name, 0.8, stall_at=500, stall_s=0.2, clock_error=clock_error)
    spec = BOARDS[name]
    gyro_twin = board.bus.device(spec["gyro"])
    lost = board.diagnostics.lost
    assert gyro_twin.fifo_overflowed > 100
    assert lost.total == lost.fifo_overflow == sum(b.lost.total for b in blocks)
    # the part's own count of the samples it overwrote; 0.8 % off, the tracked clock puts
    # the read within its latency of a sample: one either way
    assert abs(lost.fifo_overflow - gyro_twin.fifo_overflowed) <= (0 if clock_error == 0 else 1)
    t, gyr, acc, truth = joined(blocks)
    assert len(t) + gyro_twin.fifo_frames + gyro_twin.fifo_overflowed + before_first_acc(name) \
        == gyro_twin.samples_due
    # the gap is one long dt before the block that carries the loss, never filled in
    assert np.sum(np.diff(t) > 2e9 / spec["rate"]) == 1
    err = t - np.rint(truth[:, 1] * 1e9)
    assert np.all(np.abs(err) < 1e9 / spec["rate"])
    carrying = [b for b in blocks if b.lost.total]
    assert len(carrying) == 1 and carrying[0].t_ns[0] - t[np.searchsorted(t, carrying[0].t_ns[0]) - 1] > 0.15e9
    assert board.diagnostics.extra["acc_fifo_overflows"] >= 1  # costs no rows


@pytest.mark.parametrize("name", BOARDS)
def test_board_fifo_rows_at_full_scale_are_flagged_saturated(name):
    # the FIFO path's flags (the polled path's: tests/test_i2c.py::test_board_saturation_flags):
    # the ramp passes ±250 °/s at t ≈ 0.22 s and ±2 g at t ≈ 0.20 s
    board, blocks = board_run(name, 0.5, gyro_range_dps=250, acc_range_g=2)
    t, gyr, acc, truth = joined(blocks)
    flags = np.concatenate([b.flags for b in blocks])
    row_t = truth[:, 1]
    early, late = row_t < 0.15, row_t > 0.3
    assert early.sum() > 50 and late.sum() > 50
    assert np.all(flags[early] & GYR_VALID) and np.all(flags[early] & ACC_VALID)
    assert not np.any(flags[early] & (GYR_SATURATED | ACC_SATURATED))
    assert np.all(flags[late] & GYR_SATURATED) and not np.any(flags[late] & GYR_VALID)
    assert np.all(flags[late] & ACC_SATURATED) and not np.any(flags[late] & ACC_VALID)
    assert board.diagnostics.saturated >= 2 * late.sum()


def test_board_fifo_off_polls():
    board, blocks = board_run("gy80", 0.05, fifo=False)
    twin = board.bus.device(0x69)
    assert twin.regs[st.CTRL_REG5] == 0 and board.bus.device(0x53).regs[adxl.FIFO_CTL] == 0
    assert sum(len(b) for b in blocks) == 40  # one sample a 1 ms tick at 800 Hz: 40 of 40 taken


def test_board_fifo_read_hz_is_checked():
    with pytest.raises(ValueError, match="fifo_read_hz"):
        make_simulated_board("gy80", RampImu(), fifo_read_hz=0)


# ------------------------------------------------------------------ odr_hz and the bus


def test_odr_hz_sets_the_rows_rate_and_the_accelerometer_follows():
    board = make_simulated_board("gy80", RampImu(), odr_hz=400)
    assert board.parts["gyro"].rate_hz == 400 and board.parts["acc"].rate_hz == 400
    mini = make_simulated_board("minimu9v2", RampImu(), odr_hz=190)
    # the LSM303DLHC's slowest rate at or above the rows' (the pairing rule holds it)
    assert mini.parts["gyro"].rate_hz == 190 and mini.parts["acc"].rate_hz == 200
    mpu = make_simulated_board("mpu9250", RampImu(), odr_hz=500)
    assert mpu.mpu.rate_hz == 500


def test_rates_the_part_or_the_bus_cannot_do_are_refused_naming_the_key():
    from ahrs_service import config

    def error(board, **options):
        with pytest.raises(config.ConfigError) as exc:
            config.validate({"source": {"type": "simulated_i2c", "board": board, "board_options": options}})
        msg = str(exc.value)
        assert "\n" not in msg
        return msg

    assert error("gy80", odr_hz=1000).startswith("source.board_options.odr_hz = 1000 Hz: the gyroscope runs at 100, 200, 400, 800")
    assert error("mpu9250", odr_hz=8000).startswith("source.board_options.odr_hz = 8000 Hz: the MPU-9250 runs at")
    # the ADXL345 at 3200 Hz: one 6-byte read per entry, more than the 400 kHz bus carries
    msg = error("gy80", acc_rate_hz=3200)
    assert msg.startswith("source.board_options.acc_rate_hz = 3200 Hz:") and "400 kHz" in msg
    # … which a faster bus clock carries
    config.validate({"source": {"type": "simulated_i2c", "board": "gy80", "i2c_speed_hz": 1_000_000,
                                "board_options": {"acc_rate_hz": 3200}}})
