"""The MPU-9250's FIFO on its simulated twin, register by register, and the board's FIFO path.

The twin's FIFO follows the register map (RM-MPU-9250A-00 §4.4, 4.7, 4.19, 4.23, 4.30,
4.31); these tests check what the driver writes, what a burst carries, the drain schedule,
overflow → counted loss → reset → recovery, and the faults through the FIFO path.
"""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service.core.samples import ACC_VALID, GYR_VALID, SampleBlock
from ahrs_service.drivers.boards import make_simulated_board
from ahrs_service.drivers.device import FifoLayout, watermark_frames
from ahrs_service.drivers.parts import mpu9250 as m
from tests.test_i2c import StandInImu


def fifo_board(**options):
    src = StandInImu()
    board = make_simulated_board("mpu9250", src, **options)
    board.bus.device(0x68).clock_error = 0.0  # timed on the nominal 1 ms grid below
    board.open()
    return src, board, board.bus.device(0x68)


class CountingBus:
    """Counts the multi-byte read transfers a board makes, SMBus blocks and plain I2C reads
    alike (wraps the simulated bus's methods)."""

    def __init__(self, bus):
        self.blocks: list[tuple[int, int]] = []
        for name in ("read_i2c_block_data", "read_burst"):
            inner = getattr(bus, name)

            def read(addr, reg, n, inner=inner):
                self.blocks.append((reg, n))
                return inner(addr, reg, n)

            setattr(bus, name, read)


def test_configuration_registers():
    _, board, twin = fifo_board()
    assert twin.regs[m.CONFIG] & m.FIFO_MODE  # a full FIFO keeps its oldest samples
    assert twin.regs[m.FIFO_EN_REG] == 0x78  # gyro X, Y, Z + accel: 12 bytes a sample
    assert twin.regs[m.USER_CTRL] == m.USER_FIFO_EN  # FIFO on, reset bit self-cleared
    assert twin.regs[m.INT_ENABLE] & m.FIFO_OFLOW
    assert twin.frame_bytes() == 12 and m.FIFO_LAYOUT.depth_frames == 42
    _, polled, ptwin = fifo_board(fifo=False)
    assert not ptwin.regs[m.USER_CTRL] & m.USER_FIFO_EN and not ptwin.regs[m.CONFIG] & m.FIFO_MODE


def test_burst_layout_scale_and_transfers():
    src, board, twin = fifo_board()
    src.advance(0.0105)  # 10 samples at 1 kHz, past the first 10 ms drain
    twin.update(src.clock.t)  # the twin moves on bus accesses; look at it now
    assert len(twin.fifo) == 120
    # the bytes are the data registers' order: accel X Y Z, gyro X Y Z, big-endian (§4.7)
    first = np.frombuffer(bytes(twin.fifo[:12]), ">i2")
    np.testing.assert_array_equal(first[:3], np.frombuffer(bytes(twin.regs[0x3B:0x41]), ">i2"))
    np.testing.assert_array_equal(first[3:], np.frombuffer(bytes(twin.regs[0x43:0x49]), ">i2"))
    bus = CountingBus(board.bus)
    block = board.read_block()
    assert isinstance(block, SampleBlock) and len(block) == 10
    fifo_reads = [n for reg, n in bus.blocks if reg == m.FIFO_R_W]
    assert fifo_reads == [120]  # a plain-I2C adapter: the whole burst in one read
    assert m.FIFO_LAYOUT.transfers(10, board.bus.max_read_bytes) == 1
    np.testing.assert_allclose(block.gyr, np.tile(src.gyr, (10, 1)), atol=board.mpu.gyro_scale[0])
    np.testing.assert_allclose(block.acc, np.tile(src.acc, (10, 1)), atol=board.mpu.acc_scale[0])
    assert (block.flags & (GYR_VALID | ACC_VALID) == GYR_VALID | ACC_VALID).all()
    assert block.raw["gyr"].shape == (10, 3) and block.truth_q.shape == (10, 4)
    assert np.all(np.diff(block.t_ns) == 1_000_000)  # one output period apart
    assert block.t_ns[-1] == board.bus.now_ns()  # the newest is timed at the level read
    assert block.lost.total == 0 and len(twin.fifo) == 0


def test_an_smbus_only_adapter_reads_the_fifo_in_32_byte_blocks():
    src, board, twin = fifo_board()
    board.bus.max_read_bytes = 32  # an adapter without I2C_FUNC_I2C (SMBus commands only)
    src.advance(0.0105)
    bus = CountingBus(board.bus)
    block = board.read_block()
    assert len(block) == 10 and block.lost.total == 0
    assert [n for reg, n in bus.blocks if reg == m.FIFO_R_W] == [32, 32, 32, 24]  # ⌈120 / 32⌉
    assert m.FIFO_LAYOUT.transfers(10) == 4
    with pytest.raises(ValueError, match="1..32 bytes"):
        board.bus.read_burst(0x68, m.FIFO_R_W, 33)


def test_drain_schedule_is_the_wakeup_rate():
    src, board, twin = fifo_board(fifo_read_hz=50)
    bus = CountingBus(board.bus)
    got = 0
    for _ in range(100):  # 100 ms in 1 ms ticks: a drain every 20 ms
        src.advance(1e-3)
        got += len(board.read_block())
    drains = sum(1 for reg, _ in bus.blocks if reg == m.FIFO_COUNTH)
    assert drains == 5
    assert got + len(twin.fifo) // 12 == twin.samples_latched
    with pytest.raises(ValueError, match="fifo_read_hz"):
        fifo_board(fifo_read_hz=0)


def test_overflow_counts_the_loss_keeps_the_oldest_and_recovers():
    src, board, twin = fifo_board()
    src.advance(0.0105)
    before = board.read_block()
    assert len(before) == 10
    src.advance(0.100)  # 100 ms without a read: 100 samples, 42 fit
    twin.update(src.clock.t)
    assert twin.fifo_overflowed == 58 and twin.regs[m.INT_STATUS] & m.FIFO_OFLOW
    kept = board.read_block()
    assert len(kept) == 42 and kept.lost.total == 0
    # the kept samples are the oldest, contiguous with the last block: timed on from it
    np.testing.assert_array_equal(kept.t_ns, before.t_ns[-1] + 1_000_000 * np.arange(1, 43))
    assert len(twin.fifo) == 0  # reset after the overflow
    assert board.diagnostics.lost.fifo_overflow == 58  # counted from the sensor clock
    src.advance(0.010)
    after = board.read_block()
    assert after.lost.fifo_overflow == 58 and after.lost.total == 58  # before its first row
    assert len(after) == 10 and np.all(np.diff(after.t_ns) == 1_000_000)
    # the gap is one long dt between the blocks, never filled in
    assert after.t_ns[0] - kept.t_ns[-1] == 59 * 1_000_000
    src.advance(0.010)
    again = board.read_block()
    assert len(again) == 10 and again.lost.total == 0
    assert board.diagnostics.lost.total == 58


def test_overwrite_mode_keeps_the_newest():
    src, board, twin = fifo_board()
    twin.regs[m.CONFIG] &= ~m.FIFO_MODE  # FIFO_MODE 0: a full FIFO overwrites its oldest
    src.advance(0.100)
    twin.update(src.clock.t)
    assert len(twin.fifo) == 504 and twin.fifo_overflowed == 58
    assert twin.fifo_samples[-1][0] == pytest.approx(0.100)


def test_bus_errors_retried_and_a_vanished_part_counted_as_lost_samples():
    src, board, twin = fifo_board()
    src.advance(0.0105)
    board.bus.inject_errors(0x68, 2)
    assert len(board.read_block()) == 10  # retried: nothing lost
    assert board.diagnostics.bus_errors == 2 and board.diagnostics.lost.total == 0
    board.bus.set_present(0x68, False)
    for _ in range(50):
        src.advance(1e-3)
        assert len(board.read_block()) == 0
    assert board.diagnostics.device_lost
    board.bus.set_present(0x68, True)
    blocks = []
    for _ in range(60):
        src.advance(1e-3)
        blocks.append(board.read_block())
    # the MPU-9250 and the AK8963 behind it are configured again
    assert not board.diagnostics.device_lost and board.diagnostics.reinitialisations == 2
    lost = sum(b.lost.bus_error for b in blocks)
    # counted from the last drain to the recovery: the 50 ms away plus up to one drain
    # period before the loss was seen and one re-initialisation period (50 ms) after
    assert lost == board.diagnostics.lost.bus_error and 50 <= lost <= 110
    assert sum(len(b) for b in blocks) > 0


def test_read_hands_out_the_rows_of_a_block():
    src, board, twin = fifo_board()
    src.advance(0.0105)
    rows = []
    while (s := board.read()) is not None:
        rows.append(s)
    assert len(rows) == 10 and board.pending == 0
    assert [s.t_ns for s in rows] == sorted(s.t_ns for s in rows)


def test_a_fast_part_keeps_its_sample_spacing_from_the_host_read():
    src, board, twin = fifo_board()
    twin.clock_error = 0.01  # 1 % fast: 1010 samples a second
    n = 0
    for _ in range(100):
        src.advance(0.01)
        block = board.read_block()
        n += len(block)
    assert n == twin.samples_latched - len(twin.fifo) // 12
    assert 1005 <= twin.samples_latched <= 1011


class PerSampleSource:
    """A simulator seen through ``physics`` only (no ``physics_block``): the twin latches it
    one sample at a time, the reference its burst latching must match."""

    def __init__(self, imu) -> None:
        self.imu, self.clock = imu, imu.clock

    def physics(self, t: float, period: float | None = None) -> dict:
        return self.imu.physics(t, period)


@pytest.mark.parametrize("keep_oldest", [True, False], ids=["FIFO_MODE 1", "FIFO_MODE 0"])
def test_the_twin_latches_a_burst_at_once_as_it_latches_it_sample_by_sample(keep_oldest):
    """The twin fed by ``SimulatedImu.physics_block`` (a FIFO burst's samples in one call) and
    the twin fed sample by sample: the same registers, FIFO bytes, sample times, overflow
    counts and rows after every read — drains, stops longer than the FIFO, raw partial reads
    of FIFO_R_W and reads past its end."""
    from ahrs_service.drivers.sim.imu import ManualClock, SimulatedImu
    from ahrs_service.drivers.sim.motion import profile
    from ahrs_service.drivers.sim.sensor_model import board_models

    def board(per_sample: bool):
        models = {k: m_.analog() for k, m_ in board_models("MPU9250", seed=2).items()}
        imu = SimulatedImu(profile("figure8", looping=True), models, clock=ManualClock(), seed=5)
        b = make_simulated_board("mpu9250", PerSampleSource(imu) if per_sample else imu)
        b.open()
        twin = b.bus.device(0x68)
        if not keep_oldest:
            twin.regs[m.CONFIG] &= ~m.FIFO_MODE
        return imu, b, twin

    (imu_a, burst, twin_a), (imu_b, single, twin_b) = board(False), board(True)
    assert twin_a._physics_block is not None and twin_b._physics_block is None
    rng = np.random.default_rng(3)
    for i in range(300):
        dt = float(rng.choice([0.001, 0.004, 0.010, 0.060]))  # 60 ms: beyond the 42 ms FIFO
        imu_a.clock.advance(dt)
        imu_b.clock.advance(dt)
        if rng.random() < 0.1:
            n = int(rng.integers(1, 33))
            assert burst.bus.read_i2c_block_data(0x68, m.FIFO_R_W, n) == \
                single.bus.read_i2c_block_data(0x68, m.FIFO_R_W, n)
        a, b = burst.read_block(), single.read_block()
        assert twin_a.regs == twin_b.regs and twin_a.fifo == twin_b.fifo, i
        assert [t for t, _ in twin_a.fifo_samples] == [t for t, _ in twin_b.fifo_samples]
        assert (twin_a.fifo_overflowed, twin_a.fifo_discarded, twin_a.samples_latched) == \
            (twin_b.fifo_overflowed, twin_b.fifo_discarded, twin_b.samples_latched)
        for key in ("t_ns", "gyr", "acc", "mag", "flags", "truth_q"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))
        assert a.lost == b.lost
    assert twin_a.fifo_overflowed > 0 and twin_a.samples_latched > 2000
    # an empty FIFO reads 0xFF for every byte past its end, as byte by byte
    twin_a.fifo.clear()
    assert burst.bus.read_i2c_block_data(0x68, m.FIFO_R_W, 4) == [0xFF] * 4


def test_fifo_helpers():
    lay = FifoLayout(depth_frames=32, frame_bytes=6, data_register=0xA8, frames_per_transfer=1)
    assert lay.transfers(10) == 10 and lay.transfers(0) == 0
    assert watermark_frames(1000, 100, 42) == 10 and watermark_frames(1000, 1, 42) == 41
    with pytest.raises(ValueError):
        watermark_frames(1000, 0, 42)
