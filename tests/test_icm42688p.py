"""ICM-42688-P driver against its twin: identity, configuration, hi-res burst layout and scale,
watermark, overflow, sensor clock, faults, on the simulated SPI and I2C buses.

Register expectations are written out from TDK DS-000347 (register descriptions §14.x, the
hi-res FIFO packet) independently of the driver's constants, so driver and twin cannot share
a mistake unnoticed; each was checked against PX4, Linux inv_icm42600, Zephyr and ArduPilot
(see the module header of drivers/imu/icm42688p.py).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service.drivers.boards import make_transport_board
from ahrs_service.drivers.device import PartIdentityError
from ahrs_service.drivers.parts.icm42688p import decode_hires, invalid_packets
from ahrs_service.drivers.sim.clock import ManualClock

G0 = 9.80665
D2R = math.pi / 180


class ConstantImu:
    """Constant readings the test sets, on a clock the test moves."""

    def __init__(self) -> None:
        self.clock = ManualClock()
        self.gyr = np.array([0.1, -0.2, 0.3])
        self.acc = np.array([1.5, -2.5, -9.0])
        self.q = np.array([1.0, 0.0, 0.0, 0.0])

    def physics(self, t: float) -> dict:
        return {"gyr": self.gyr, "acc": self.acc, "mag": np.zeros(3), "temperature_c": 31.0,
                "truth": {"q": self.q}}


def board(bus: str = "spi", **options):
    imu = ConstantImu()
    b = make_transport_board("icm42688p", bus, simulated_imu=imu, **options)
    return b, imu, b.transport.bus.device(b.transport.cs if bus == "spi" else 0x68)


def test_identity_is_checked_and_a_missing_part_reads_ff_on_spi():
    b, imu, twin = board()
    b.open()
    assert twin.regs[0x75] == 0x47  # WHO_AM_I
    twin.regs[0x75] = 0x12  # another InvenSense part
    with pytest.raises(PartIdentityError, match=r"sim-spi0\.0: expected ICM-42688-P.*0x75\) reads 0x12"):
        b.part.configure()
    b2, _, _ = board()
    b2.transport.bus.set_present(0, False)
    with pytest.raises(PartIdentityError, match="reads 0xFF"):
        b2.open()


@pytest.mark.parametrize("odr, code", [(8000, 3), (4000, 4), (2000, 5), (1000, 6), (500, 15), (200, 7), (100, 8)])
def test_configuration_registers(odr, code):
    b, imu, twin = board(odr_hz=odr, watermark=10)
    b.open()
    r = twin.regs
    assert r[0x4F] == code and r[0x50] == code  # GYRO/ACCEL_CONFIG0: FS 000 (±2000 °/s, ±16 g), ODR
    assert r[0x4E] == 0x0F  # PWR_MGMT0: gyro and accel low-noise
    assert r[0x16] == 0x80  # FIFO_CONFIG: stop-on-full
    assert r[0x5F] == 0x3F  # FIFO_CONFIG1: WM_GT_TH, HIRES, TMST_FSYNC, TEMP, GYRO, ACCEL
    assert r[0x60] | (r[0x61] & 0x0F) << 8 == 200  # watermark: 10 packets of 20 bytes
    assert r[0x65] == 0x06  # INT_SOURCE0: FIFO_THS and FIFO_FULL on INT1
    assert r[0x14] == 0x03  # INT_CONFIG: INT1 pulsed, push-pull, active high
    # INT_CONFIG1: INT_ASYNC_RESET (bit 4, power-on 1) cleared; at ODR >= 4 kHz 8 us pulses
    # (bit 6) without de-assert time (bit 5)
    assert r[0x64] == (0x60 if odr >= 4000 else 0x00)
    assert twin.rate_hz() == pytest.approx(odr * 1.0042)  # the unit runs 0.42 % fast


def test_hires_packet_layout_decoded_from_the_datasheet_order():
    # accel X = 0x12345 (20 bit), gyro Z = -3 (0xFFFFD), temperature 0x0102, timestamp 0xBEEF
    pkt = bytearray(20)
    pkt[0] = 0x78
    pkt[1], pkt[2], pkt[17] = 0x12, 0x34, 0x50  # accel X bits 19:12, 11:4, 3:0 in the high nibble
    pkt[11], pkt[12], pkt[19] = 0xFF, 0xFF, 0x0D  # gyro Z bits 19:12, 11:4, 3:0 in the low nibble
    pkt[13], pkt[14], pkt[15], pkt[16] = 0x01, 0x02, 0xBE, 0xEF
    d = decode_hires(bytes(pkt))
    assert d["acc20"][0, 0] == 0x12345 and d["acc"][0, 0] == 0x12345 >> 2
    assert d["gyr20"][0, 2] == -3 and d["gyr"][0, 2] == -2  # 19 bits: arithmetic shift
    assert d["temp"][0] == 0x0102 and d["tmst"][0] == 0xBEEF and d["header"][0] == 0x78


def test_invalid_packets_are_those_with_another_header_or_an_invalid_reading():
    def packet(header=0x78, acc_x_invalid=False, gyr_z_invalid=False):
        pkt = bytearray(20)
        pkt[0] = header
        pkt[2] = 0x10  # small nonzero readings elsewhere
        if acc_x_invalid:  # -524288: bits 19:12 = 0x80, 11:4 = 0x00, 3:0 = 0
            pkt[1], pkt[2] = 0x80, 0x00
        if gyr_z_invalid:
            pkt[11], pkt[12] = 0x80, 0x00
        return bytes(pkt)

    assert invalid_packets(decode_hires(packet() * 8)) is None  # the usual burst
    assert invalid_packets(decode_hires(b"")) is None
    d = decode_hires(packet() + packet(header=0x68) + packet(acc_x_invalid=True) + packet(gyr_z_invalid=True)
                     + packet(header=0x7B))  # header bits 1:0 are not checked
    assert invalid_packets(d).tolist() == [False, True, True, True, False]
    # a value one above the marker is a reading (the test is on the smallest value)
    one_above = bytearray(packet(acc_x_invalid=True))
    one_above[17] = 0x10
    assert invalid_packets(decode_hires(bytes(one_above))) is None


def test_burst_scale_within_one_lsb_and_timestamps_on_the_part_clock():
    b, imu, twin = board(odr_hz=8000, watermark=8)
    b.open()
    blocks = []
    for _ in range(400):  # 0.4 s of 1 ms bursts
        imu.clock.advance(0.001)
        blk = b.read_block()
        if len(blk):
            blocks.append(blk)
    blk = blocks[-1]
    assert np.abs(blk.gyr - imu.gyr).max() <= D2R / 131 / 2 + 1e-12  # 131 LSB/(°/s)
    assert np.abs(blk.acc - imu.acc).max() <= G0 / 8192 / 2 + 1e-12  # 8192 LSB/g
    assert blk.temperature_c[0] == pytest.approx(31.0, abs=1 / 132.48)
    assert blk.raw["gyr"][0].tolist() == [round(w / (D2R / 131)) for w in imu.gyr]
    n = sum(len(x) for x in blocks)
    assert n == b.diagnostics.samples == twin.samples_latched  # every sample, none twice
    # the packets' 16-bit µs timestamp steps by 125 µs of the part's clock at 8 kHz
    twin_rate = twin.rate_hz()
    assert b.clock.rate_hz == pytest.approx(twin_rate, rel=2e-4)
    t = np.concatenate([x.t_ns for x in blocks])
    assert (np.diff(t) > 0).all()
    # once the rate is tracked (after 0.2 s), rows are the part's real period apart
    late = np.concatenate([x.t_ns for x in blocks[-100:]])
    assert np.median(np.diff(late)) == pytest.approx(1e9 / twin_rate, rel=2e-4)


def test_packet_timestamps_step_by_the_output_period():
    b, imu, twin = board(odr_hz=8000, watermark=8)
    b.open()
    imu.clock.advance(0.002)
    b.part.read_status()
    d = b.part.read_packets(twin.fifo.level)
    assert len(d["tmst"]) == 16
    assert set(np.diff(d["tmst"]) % 65536) == {125}


def test_watermark_sets_int_status_and_raises_int1_once():
    b, imu, twin = board(odr_hz=1000, watermark=5)
    b.open()
    edges = []
    twin.int1 = edges.append
    imu.clock.advance(0.0045)  # 4 samples (1004.2 Hz): below the watermark
    status, count = b.part.read_status()
    assert status & 0x06 == 0 and count == 80  # neither FIFO_THS nor FIFO_FULL
    assert edges == []
    imu.clock.advance(0.001)  # the fifth
    status, count = b.part.read_status()
    assert status & 0x04 and count == 100  # FIFO_THS_INT
    assert len(edges) == 1 and edges[0] == pytest.approx(5 / 1004.2)
    imu.clock.advance(0.001)
    assert b.part.read_status()[0] & 0x04 and len(edges) == 1  # still above: no new edge
    assert len(b.read_block()) == 6


def test_int1_stays_quiet_while_int_async_reset_is_left_at_its_power_on_value():
    # INT_CONFIG1 bit 4 powers on set; the datasheet (quoted by PX4 and Linux) says it must be
    # cleared for the INT pins to work: the twin raises no edge until it is
    b, imu, twin = board(odr_hz=1000, watermark=5)
    b.open()
    edges = []
    twin.int1 = edges.append
    twin.regs[0x64] = 0x10
    imu.clock.advance(0.0065)
    assert b.part.read_status()[0] & 0x04 and edges == []  # FIFO_THS set, but no INT1 edge
    b.read_block()
    twin.regs[0x64] = 0x00
    imu.clock.advance(0.0055)
    b.part.read_status()  # the twin latches when the bus touches it
    assert len(edges) == 1


def test_overflow_counts_the_loss_resets_the_fifo_and_shows_the_gap():
    b, imu, twin = board(odr_hz=8000, watermark=8)
    b.open()
    for _ in range(300):  # 0.3 s: the part's real rate is tracked
        imu.clock.advance(0.001)
        b.read_block()
    imu.clock.advance(0.05)  # a 50 ms stall: the 102-packet FIFO (12.7 ms) overflows
    full = b.read_block()
    assert len(full) == 102
    assert b.diagnostics.extra["fifo_overflows"] == 1
    lost = b.diagnostics.lost.fifo_overflow
    assert abs(lost - twin.fifo.dropped) <= 1  # the samples the full FIFO turned away
    assert lost > 250
    assert twin.fifo.level == 0  # FIFO_FLUSH
    imu.clock.advance(0.001)
    after = b.read_block()
    assert after.lost.fifo_overflow == lost and after.lost.total == lost
    gap = (after.t_ns[0] - full.t_ns[-1]) / 1e9
    assert gap == pytest.approx((lost + 1) / twin.rate_hz(), abs=2e-4)  # a long dt, no fake rows


def test_bus_errors_are_retried_and_a_vanished_part_comes_back_with_the_loss_counted():
    b, imu, twin = board(odr_hz=1000, watermark=4)
    b.open()
    bus = b.transport.bus
    for _ in range(20):
        imu.clock.advance(0.004)
        b.read_block()
    bus.inject_errors(0, 2)
    imu.clock.advance(0.004)
    assert len(b.read_block()) == 4
    assert b.diagnostics.retries == 2 and b.diagnostics.bus_errors == 2
    bus.set_present(0, False)  # MISO floats: the count reads 0xFFFF
    imu.clock.advance(0.004)
    assert len(b.read_block()) == 0 and b.diagnostics.device_lost
    for _ in range(25):  # 100 ms away
        imu.clock.advance(0.004)
        b.read_block()
    bus.set_present(0, True)  # power-cycled: must be configured again
    for _ in range(20):
        imu.clock.advance(0.004)
        b.read_block()
    assert not b.diagnostics.device_lost and b.diagnostics.reinitialisations == 1
    assert 95 <= b.diagnostics.lost.bus_error <= 160


@pytest.mark.parametrize("adapter, transfers", [
    ("plain I2C", 1 + 1),  # status+count, then status, count and the 200 bytes in one read
    ("SMBus only", 1 + 7),  # status+count, then 203 bytes in 32-byte SMBus blocks
])
def test_i2c_transport_reads_the_fifo_in_as_few_transfers_as_the_adapter_allows(adapter, transfers):
    b, imu, twin = board("i2c", odr_hz=1000, watermark=10)
    if adapter == "SMBus only":  # an adapter without I2C_FUNC_I2C
        b.transport.bus.max_read_bytes = b.transport.max_read = 32
    b.open()
    imu.clock.advance(0.0105)
    bus = b.transport.bus
    before = bus.transfers
    blk = b.read_block()
    assert len(blk) == 10 and blk.lost.total == 0
    assert bus.transfers - before == transfers
    assert np.abs(blk.gyr - imu.gyr).max() <= D2R / 131 / 2 + 1e-12


def test_read_block_takes_at_most_max_samples_and_empties_the_fifo_at_once():
    b, imu, twin = board(odr_hz=8000, watermark=8)
    b.open()
    for _ in range(300):
        imu.clock.advance(0.001)
        b.read_block()
    imu.clock.advance(0.03)  # overflowed
    a = b.read_block(max_samples=64)
    # the whole FIFO is read (and reset) at once; the rows beyond 64 wait on the host
    assert len(a) == 64 and b.diagnostics.extra["fifo_overflows"] == 1 and twin.fifo.level == 0
    transfers = b.transport.bus.transfers
    c = b.read_block(max_samples=64)
    assert len(c) == 38 and c.lost.total == 0
    assert c.t_ns[0] - a.t_ns[-1] == pytest.approx(1e9 / twin.rate_hz(), rel=1e-3)  # contiguous
    after = b.read_block(max_samples=64)  # the rows after the gap, carrying the loss
    assert after.lost.fifo_overflow == b.diagnostics.lost.fifo_overflow > 0
    assert b.transport.bus.transfers > transfers


def test_a_stop_shorter_than_the_fifo_loses_nothing_while_the_host_catches_up_slowly():
    # 1 kHz: the FIFO holds 102 samples (101.6 ms at the twin's 1004.2 Hz). The host stops
    # 95 ms, then takes 16 rows a call but spends 18 ms a call for a while (a busy loop):
    # more samples arrive per call than it takes. Every call empties the FIFO, the backlog
    # waits on the host, and nothing is lost (taking only 16 from the FIFO a call left it
    # full two calls after the stop)
    b, imu, twin = board(odr_hz=1000)
    b.open()
    rows = 0
    for _ in range(1000):
        imu.clock.advance(0.001)
        rows += len(b.read_block(max_samples=16))
    imu.clock.advance(0.095)
    for _ in range(20):
        rows += len(b.read_block(max_samples=16))
        imu.clock.advance(0.018)
    for _ in range(300):
        imu.clock.advance(0.001)
        rows += len(b.read_block(max_samples=16))
    assert b.diagnostics.lost.total == 0 and twin.fifo.dropped == 0
    assert rows + b.pending + twin.fifo.level // 20 == twin.samples_due
    assert b.pending == 0  # caught up


def test_rows_carry_the_truth_of_their_own_sample():
    b, imu, twin = board(odr_hz=1000, watermark=4)
    b.open()
    imu.clock.advance(0.0045)
    rows = [b.read() for _ in range(4)]
    assert all(r is not None for r in rows) and b.read() is None
    assert rows[0].t_ns < rows[-1].t_ns and rows[0].truth_q.tolist() == [1.0, 0.0, 0.0, 0.0]
    assert rows[0].mag is None and rows[0].raw["acc"] == [round(a / (G0 / 8192)) for a in imu.acc]


# issue 15: at 1 kHz a stop shorter than the FIFO lost 2-18 samples in some service runs. The
# FIFO filled between the level read and the data read of one burst: the twin spent tens of ms
# making the samples inside the level read (a busy host), and a host can be held there too.


class TimedImu(ConstantImu):
    """Each sample's gyro x is its true time (rad/s = s), so a row's time can be checked
    against the moment the part took it; ``cost_s``: what making a sample costs the
    simulation, in time on its own clock (the host's, on a real-time clock)."""

    cost_s = 0.0

    def physics(self, t: float) -> dict:
        self.clock.advance(self.cost_s)
        return dict(super().physics(t), gyr=np.array([t, 0.0, 0.0]))


def timed_board(**options):
    imu = TimedImu()
    b = make_transport_board("icm42688p", "spi", simulated_imu=imu, **options)
    return b, imu, b.transport.bus.device(b.transport.cs)


def held_after_the_level_read(b, imu, seconds: float):
    """The next burst's level read returns, then the host is held ``seconds`` before the data."""
    read_status = b.part.read_status

    def held():
        out = read_status()
        b.part.read_status = read_status
        imu.clock.advance(seconds)
        return out
    b.part.read_status = held


def test_a_fifo_filled_between_level_and_data_read_is_known_with_that_data():
    b, imu, twin = timed_board(odr_hz=1000, fifo_read_hz=100)
    b.open()
    blocks = []
    for _ in range(100):  # 1 s: the part's rate is tracked
        imu.clock.advance(0.010)
        blocks.append(b.read_block())
    imu.clock.advance(0.092)  # a stop: 92 of the FIFO's 102 packets
    held_after_the_level_read(b, imu, 0.015)  # … and the host held at the level read
    for _ in range(10):
        blocks.append(b.read_block())
        imu.clock.advance(0.010)
    rows = [blk for blk in blocks if len(blk)]
    t = np.concatenate([blk.t_ns for blk in rows]) / 1e9
    true_t = np.concatenate([blk.gyr[:, 0] for blk in rows])
    period = 1 / twin.rate_hz()
    # the packets read after the FIFO filled are the oldest (stop-on-full), each row placed
    # within a period of the moment it was taken, none after the gap placed before it
    assert np.abs(t - true_t).max() < period
    lost = b.diagnostics.lost.fifo_overflow
    assert lost > 0 and b.diagnostics.extra["fifo_overflows"] == 1
    assert abs(lost - (twin.fifo.dropped + twin.fifo.discarded)) <= 1  # the part's own count
    # the block after the reset carries the loss; its first row shows the gap
    i = next(i for i, blk in enumerate(blocks) if blk.lost.total)
    assert blocks[i].lost.fifo_overflow == lost
    prev = next(blk for blk in reversed(blocks[:i]) if len(blk))
    assert (blocks[i].t_ns[0] - prev.t_ns[-1]) / 1e9 == pytest.approx((lost + 1) * period, abs=period)


def test_a_start_up_backlog_that_fills_during_the_first_burst_is_not_a_loss():
    # the consumer's first read comes 95 ms after open (the service sets up its log and
    # links): 95 of the 102 packets wait, and the host is held at the level read. Those
    # samples predate the consumer: flushed, nothing counted, as an overflow found before
    # the first read (the "window 47-57 ms" losses of 2-18 samples)
    b, imu, twin = timed_board(odr_hz=1000, fifo_read_hz=100)
    b.open()
    imu.clock.advance(0.095)
    held_after_the_level_read(b, imu, 0.015)
    rows = 0
    for _ in range(50):
        rows += len(b.read_block())
        imu.clock.advance(0.010)
    assert b.diagnostics.lost.total == 0 and b.diagnostics.extra["fifo_overflows"] == 0
    assert twin.fifo.dropped > 0 and rows > 0  # it did fill; what came after it is all there
    assert b.diagnostics.extra["fifo_longest_window_ms"] < 30


def test_the_twins_level_counts_the_samples_made_while_the_simulation_made_them():
    # making a sample costs the simulation 0.3 ms (a busy host): a level read 50 ms after
    # the start makes 50 samples, and 15 more come due meanwhile. A real part's samples cost
    # nothing: the level it latches counts all of them, so the data read right after it
    # finds the FIFO where the level left it (the simulated bus has the part catch up first)
    b, imu, twin = timed_board(odr_hz=1000, fifo_read_hz=100)
    b.open()
    imu.cost_s = 0.0003
    imu.clock.advance(0.050)
    _, count = b.part.read_status()
    due_now = math.floor((imu.clock.now() - twin._t0) * twin.rate_hz())
    assert due_now - count // 20 <= 1


def test_data_registers_show_the_newest_sample_at_the_configured_range():
    # TEMP_DATA1 … GYRO_DATA_Z0 (0x1D…0x2A), big-endian 16 bit: ±16 g → 2048 LSB/g,
    # ±2000 °/s → 16.4 LSB/(°/s), T = raw / 132.48 + 25 °C (filled when read)
    b, imu, twin = board(odr_hz=1000)
    b.open()
    imu.clock.advance(0.0035)
    raw = bytes(b.part.read_regs(0x1D, 14))
    v = [int.from_bytes(raw[i:i + 2], "big", signed=True) for i in range(0, 14, 2)]
    assert v[0] == round((31.0 - 25.0) * 132.48)
    assert v[1:4] == [round(a / G0 * 2048) for a in imu.acc]
    assert v[4:7] == [round(w / D2R * 16.4) for w in imu.gyr]


@pytest.mark.parametrize("stall_s", [0.014, 0.02, 0.05])
def test_consecutive_overflows_count_what_the_part_turned_away(stall_s):
    # a host that stays slow: 30 reads in a row each after a stall longer than the 12.7 ms
    # FIFO, so every read after a reset finds the FIFO full again. That read's only bound
    # ("its newest sample existed by now") put the full FIFO's newest sample at the read,
    # and each reset then counted from that line: 87 lost counted where the part turned
    # away 1 760 (20 ms stalls). The reset itself now bounds the first sample after it.
    b, imu, twin = board(odr_hz=8000, watermark=8)
    b.open()
    for _ in range(300):
        imu.clock.advance(0.001)
        b.read_block()
    for _ in range(30):
        imu.clock.advance(stall_s)
        b.read_block()
    for _ in range(100):
        imu.clock.advance(0.001)
        b.read_block()
    events = b.diagnostics.extra["fifo_overflows"]
    part = twin.fifo.dropped + twin.fifo.discarded
    assert events == 30
    # each gap is counted from the sensor clock to within its phase: in all within half a
    # sample per event, and not one way (measured 300/314, 1 769/1 760, 8 999/8 990)
    assert abs(b.diagnostics.lost.fifo_overflow - part) <= events // 2
    assert b.diagnostics.samples + b.pending + b.diagnostics.lost.fifo_overflow == pytest.approx(
        twin.samples_due - twin.fifo.level // 20, abs=events // 2)


# issue 15: the 1 kHz service stall test's known defect (39 periods in 1 run of 21 on a host
# at load 6-9): a busy host held up around the run's first level read — before the part
# latched its level or after — placed the sensor clock's first rows as far off as the hold
# (the only bound then was that wide read), and the next tight read jumped the times by as
# much; the BMI088 also dropped, unpaired and uncounted, the gyroscope rows older than its
# last accelerometer read


def hold_the_first_level_read(part, imu, seconds: float, before_the_latch: bool):
    """The part's next level read (``read_status``): the host held ``seconds`` before it
    reaches the part, or after the part answered."""
    read_status = part.read_status

    def held():
        part.read_status = read_status
        if before_the_latch:
            imu.clock.advance(seconds)
        out = read_status()
        if not before_the_latch:
            imu.clock.advance(seconds)
        return out
    part.read_status = held


@pytest.mark.parametrize("before_the_latch", [True, False], ids=["held-before-latch", "held-after-latch"])
@pytest.mark.parametrize("name, options", [
    ("icm42688p", {"odr_hz": 1000, "fifo_read_hz": 100}),
    ("icm20948", {"odr_hz": 1125}),
    ("bmi088", {"odr_hz": 1000, "fifo_read_hz": 100}),
])
def test_a_host_held_at_the_first_level_read_neither_misplaces_nor_drops_rows(name, options, before_the_latch):
    imu = TimedImu()
    b = make_transport_board(name, "spi", simulated_imu=imu, **options)
    b.open()
    imu.clock.advance(0.005)
    hold_the_first_level_read(b.part, imu, 0.039, before_the_latch)
    rows = []
    for _ in range(100):  # 1 s
        block = b.read_block()
        if len(block):
            rows.append(block)
        imu.clock.advance(0.010)
    t = np.concatenate([blk.t_ns for blk in rows]) / 1e9
    true_t = np.concatenate([blk.gyr[:, 0] for blk in rows])  # quantised to the gyro's LSB
    period = 1.0 / b.clock.rate_hz
    lsb = D2R / (16.4 if name != "bmi088" else 16.384)  # ±2000 °/s: the truth's own resolution
    # every row within a period (and the truth's LSB) of the moment the part took it: the
    # first rows were 39 periods early when the hold came before the latch …
    assert np.abs(t - true_t).max() < period + lsb
    # … and no jump after them, no row missing: one period between rows, none lost (a hold
    # that overflowed the ICM-20948's FIFO before the first rows is a stale start, not a loss)
    assert np.diff(t).max() < 1.5 * period
    assert b.diagnostics.lost.total == 0
