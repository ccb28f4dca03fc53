"""The real SPI (spidev) and data-ready line (libgpiod 2) backends with their device objects
faked, the simulated line, the data-ready scheduler, and the configuration of SPI sources.

No /dev/spidev*, /dev/gpiochip* here: the fakes stand in for the ``spidev.SpiDev`` class and
``gpiod.request_lines``; the code above them is the code that runs on hardware.
"""

from __future__ import annotations

import errno
import sys
import types
from types import SimpleNamespace

import numpy as np
import pytest
from test_icm42688p import ConstantImu

from ahrs_service import config
from ahrs_service.drivers.boards import make_transport_board
from ahrs_service.drivers.buses.drdy import GpiodLine, parse_line_spec
from ahrs_service.drivers.buses.spi import SpidevSPI
from ahrs_service.drivers.sim.bus import SimulatedSPIBus, spi_answer
from ahrs_service.drivers.sim.clock import ManualClock
from ahrs_service.drivers.sim.drdy import SimulatedDataReadyLine
from ahrs_service.drivers.sim.icm42688p import SimulatedICM42688P
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice
from ahrs_service.drivers.transport import SPITransport
from ahrs_service.scheduler import DataReadyScheduler


# ----------------------------------------------------------------------------- spidev
class FakeSpiDev:
    """Stands in for spidev.SpiDev: records settings, answers from a simulated part."""

    instances: list["FakeSpiDev"] = []
    parts: dict = {}
    clock = None

    def __init__(self) -> None:
        self.mode = 0
        self.max_speed_hz = 0
        self.bits_per_word = 0
        self.opened = None
        self.closed = False
        self.transfers: list[list[int]] = []
        FakeSpiDev.instances.append(self)

    def open(self, bus: int, cs: int) -> None:
        self.opened = (bus, cs)

    def xfer2(self, data: list[int]) -> list[int]:
        assert all(isinstance(b, int) and 0 <= b <= 255 for b in data)
        self.transfers.append(list(data))
        part = FakeSpiDev.parts.get(self.opened)
        if part is None:
            return [0xFF] * len(data)
        return list(spi_answer(part, bytes(data), FakeSpiDev.clock.now()))

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_spidev(monkeypatch):
    FakeSpiDev.instances, FakeSpiDev.parts = [], {}
    monkeypatch.setitem(sys.modules, "spidev", types.SimpleNamespace(SpiDev=FakeSpiDev))
    monkeypatch.setattr("ahrs_service.drivers.buses.spi.os.path.exists", lambda p: p.startswith("/dev/spidev0."))
    return FakeSpiDev


def test_spidev_backend_opens_each_chip_select_with_mode_and_speed(fake_spidev):
    bus = SpidevSPI(0, (0, 1), mode=3, speed_hz=10_000_000)
    a, b = fake_spidev.instances
    assert (a.opened, b.opened) == ((0, 0), (0, 1))
    assert (a.mode, a.max_speed_hz, a.bits_per_word) == (3, 10_000_000, 8)
    t = SPITransport(bus, 1)
    assert t.where == "/dev/spidev0.1" and t.clock_hz == 10e6
    assert t.read(0x75, 2) == b"\xff\xff"
    assert b.transfers == [[0xF5, 0, 0]]  # 0x75 | read bit 0x80, then two clocks of data
    t.write(0x4E, 0x0F)
    assert b.transfers[-1] == [0x4E, 0x0F]  # write: bit 7 clear
    bus.close()
    assert a.closed and b.closed


def test_icm42688p_runs_through_the_spidev_backend(fake_spidev, monkeypatch):
    imu = ConstantImu()
    twin = SimulatedICM42688P(imu)
    twin.power_on_reset(0.0)
    fake_spidev.parts[(0, 0)], fake_spidev.clock = twin, imu.clock
    monkeypatch.setattr(SpidevSPI, "now_ns", lambda self: imu.clock.to_ns(imu.clock.now()))
    monkeypatch.setattr(SpidevSPI, "sleep", lambda self, s: None)
    b = make_transport_board("icm42688p", "spi", odr_hz=8000, watermark=8, spi_speed_hz=10_000_000)
    b.open()
    imu.clock.advance(0.002)
    blk = b.read_block()
    assert len(blk) == 16 and np.abs(blk.gyr - imu.gyr).max() < 1e-4
    dev = fake_spidev.instances[0]
    # the burst: status + count (3 bytes from 0x2D), then status, count and the FIFO (0x30)
    # again from 0x2D in one transfer, as PX4's FIFOTransferBuffer
    assert dev.transfers[-2][:1] == [0xAD] and len(dev.transfers[-2]) == 4
    assert dev.transfers[-1][0] == 0xAD and len(dev.transfers[-1]) == 1 + 3 + 16 * 20  # one transfer
    b.close()
    assert dev.closed


def test_spidev_errors_name_the_node_and_the_fix(fake_spidev, monkeypatch):
    with pytest.raises(FileNotFoundError, match=r"/dev/spidev1\.0 does not exist: enable SPI.*dtparam=spi=on"):
        SpidevSPI(1, (0,))

    def denied(self, bus, cs):
        raise PermissionError(errno.EACCES, "denied")

    monkeypatch.setattr(FakeSpiDev, "open", denied)
    with pytest.raises(PermissionError, match=r"/dev/spidev0\.0.*'spi' group"):
        SpidevSPI(0, (0,))


class DummyBytePart(SimulatedRegisterDevice):
    """A part that clocks one undefined byte before its data (as the BMI088 accelerometer)."""

    SPI_DUMMY_BYTES = 1
    POWER_ON = {0x00: 0x1E, 0x01: 0x5A}


def test_the_simulated_bus_counts_its_parts_cpu_apart_and_a_real_bus_has_none(fake_spidev, monkeypatch):
    """/loop's simulation_cpu_s: what a simulated part costs the process (making its samples,
    answering transfers), which benchmarks take off the service's own work."""
    import time

    imu = ConstantImu()
    b = make_transport_board("icm42688p", "spi", simulated_imu=imu, odr_hz=8000, fifo_read_hz=1000)
    b.open()
    counted = []
    for _ in range(5):
        imu.clock.advance(0.01)  # 80 samples for the part to make at the next transfer
        before_s, start_ns = b.simulation_cpu_s, time.thread_time_ns()
        assert 80 <= len(b.read_block()) <= 81  # the twin runs 0.42 % fast
        whole_ns = time.thread_time_ns() - start_ns
        counted.append(((b.simulation_cpu_s - before_s) * 1e9, whole_ns))
    # never more than the read's own CPU, and the most of it: making and packing 80 samples
    # costs the part more than decoding and timing them costs the driver
    assert all(0 < part <= whole for part, whole in counted), counted
    assert sum(p for p, _ in counted) > 0.4 * sum(w for _, w in counted), counted
    b.close()
    # a real bus (spidev, faked here) has no simulated hardware to count
    fake_spidev.parts[(0, 0)], fake_spidev.clock = SimulatedICM42688P(imu), imu.clock
    monkeypatch.setattr(SpidevSPI, "now_ns", lambda self: imu.clock.to_ns(imu.clock.now()))
    monkeypatch.setattr(SpidevSPI, "sleep", lambda self, s: None)
    fake_spidev.parts[(0, 0)].power_on_reset(imu.clock.now())
    real = make_transport_board("icm42688p", "spi", odr_hz=8000, watermark=8, spi_speed_hz=10_000_000)
    real.open()
    assert real.simulation_cpu_s is None
    real.close()


def test_dummy_byte_reads_are_framed_by_the_transport():
    clock = ManualClock()
    bus = SimulatedSPIBus(clock)
    bus.attach(DummyBytePart(), 2)
    plain = SPITransport(bus, 2)
    framed = SPITransport(bus, 2, dummy_bytes=1)
    assert framed.read(0x00, 2) == b"\x1e\x5a"
    assert plain.read(0x00, 2) == b"\xff\x1e"  # without it, every value is one byte late
    assert framed.wire_bytes(6) == 8 and framed.max_read == bus.max_transfer - 2


# ----------------------------------------------------------------------------- gpiod
class FakeRequest:
    def __init__(self, edges: list[int]) -> None:
        self.edges = edges  # timestamps of the pending edges, ns
        self.timeouts: list[float] = []
        self.released = False

    def wait_edge_events(self, timeout):
        self.timeouts.append(timeout)
        return bool(self.edges)

    def read_edge_events(self):
        out = [SimpleNamespace(timestamp_ns=t) for t in self.edges]
        self.edges = []
        return out

    def release(self):
        self.released = True


@pytest.fixture
def fake_gpiod(monkeypatch):
    calls = {}
    edge = SimpleNamespace(RISING="rising")
    direction = SimpleNamespace(INPUT="input")
    line_mod = types.SimpleNamespace(Edge=edge, Direction=direction)
    request = FakeRequest([])

    def request_lines(path, consumer, config):
        calls.update(path=path, consumer=consumer, config=config)
        if path == "/dev/gpiochip9":
            raise FileNotFoundError(errno.ENOENT, "no chip")
        return request

    gpiod = types.SimpleNamespace(request_lines=request_lines,
                                  LineSettings=lambda **kw: SimpleNamespace(**kw), line=line_mod)
    monkeypatch.setitem(sys.modules, "gpiod", gpiod)
    monkeypatch.setitem(sys.modules, "gpiod.line", line_mod)
    return calls, request


def test_gpiod_line_requests_rising_edges_and_reads_their_times(fake_gpiod):
    calls, request = fake_gpiod
    line = GpiodLine("gpiochip0:17")
    assert calls["path"] == "/dev/gpiochip0" and calls["consumer"] == "ahrs-service"
    settings = calls["config"][17]
    assert settings.edge_detection == "rising" and settings.direction == "input"
    assert line.wait(0.002) is False and line.timeouts == 1 and request.timeouts == [0.002]
    request.edges = [1_000, 2_000]
    assert line.wait(0.002) is True and line.edges == 2 and line.last_edge_ns == 2_000
    line.close()
    assert request.released
    with pytest.raises(FileNotFoundError, match="source.drdy_gpio: GPIO chip /dev/gpiochip9 does not exist"):
        GpiodLine("gpiochip9:3")


def test_line_spec_parsing():
    assert parse_line_spec("gpiochip0:17") == ("/dev/gpiochip0", 17)
    assert parse_line_spec("/dev/gpiochip4:5") == ("/dev/gpiochip4", 5)
    for bad in ("gpiochip0", "17", "gpiochip0:x", ":3"):
        with pytest.raises(ValueError, match="source.drdy_gpio"):
            parse_line_spec(bad)


def test_simulated_line_wakes_at_the_watermark_and_the_burst_holds_it():
    b = make_transport_board("icm42688p", "spi", simulated_imu=(imu := ConstantImu()), odr_hz=1000, watermark=10)
    b.open()
    twin = b.transport.bus.device(0)
    line = SimulatedDataReadyLine(twin, imu.clock)
    got = []
    for _ in range(20):
        assert line.wait(0.05) is True
        got.append(len(b.read_block()))
    assert got == [10] * 20  # woken exactly at each watermark: one burst of 10 each time
    assert line.edges == 20 and line.timeouts == 0
    assert imu.clock.now() == pytest.approx(200 / twin.rate_hz(), abs=1e-9)
    b.part.write_u8(0x65, 0x00)  # watermark not routed to INT1: the wait times out (timer fallback)
    assert line.wait(0.003) is False and line.timeouts == 1


def test_data_ready_scheduler_waits_on_the_line_with_a_timer_fallback():
    waits = []
    line = SimpleNamespace(wait=lambda timeout: waits.append(timeout) or True)
    sched = DataReadyScheduler(line, 125.0)
    t1 = sched.wait()
    sched.done()
    t2 = sched.wait()
    assert waits == [pytest.approx(2 / 125.0)] * 2 and t2 >= t1 and sched.ticks == 2


# ----------------------------------------------------------------------------- config
def _source(**kw):
    return config.validate({"source": kw}).source


def test_spi_source_keys_and_rate_limits_per_bus():
    src = _source(type="simulated_spi", board="icm42688p", spi_device=1, board_options={"odr_hz": 8000})
    assert (src["spi_bus"], src["spi_device"], src["spi_mode"], src["drdy_gpio"]) == (0, 1, 3, "")
    with pytest.raises(config.ConfigError, match=r"^source.board_options.odr_hz = 8000 Hz: the ICM-42688-P on /dev/i2c-1 address 0x68 .*I2C bus's 400 kHz"):
        _source(type="i2c", board="icm42688p", board_options={"odr_hz": 8000})
    _source(type="i2c", board="icm42688p", board_options={"odr_hz": 1000})  # 1 kHz fits fast mode
    with pytest.raises(config.ConfigError, match=r"odr_hz = 1000 Hz.*100 kHz"):
        _source(type="i2c", board="icm42688p", i2c_speed_hz=100_000, board_options={"odr_hz": 1000})
    with pytest.raises(config.ConfigError, match=r"^source.board: 'gy80' cannot be wired on spi"):
        _source(type="spi", board="gy80")
    with pytest.raises(config.ConfigError, match=r"^source.drdy_gpio: board 'mpu9250' has no FIFO"):
        _source(type="simulated_i2c", board="mpu9250", drdy_gpio="gpiochip0:17")
    with pytest.raises(config.ConfigError, match=r"^source.board_options: .*odr_hz must be one of"):
        _source(type="spi", board="icm42688p", board_options={"odr_hz": 3000})


def test_make_source_wires_the_simulated_line():
    from ahrs_service.sources import make_source

    src = _source(type="simulated_spi", board="icm42688p", drdy_gpio="gpiochip0:17",
                  board_options={"odr_hz": 2000, "fifo_read_hz": 500})
    board = make_source(src, 200.0)
    assert isinstance(board.data_ready_line, SimulatedDataReadyLine)
    assert board.wakeup_rate_hz == 500.0 and board.part.watermark == 4
    board.open()
    board.close()


def test_service_runs_on_the_simulated_spi_part_woken_by_its_watermark_line(tmp_path):
    """The whole service on the simulated SPI ICM-42688-P with the simulated watermark line:
    it paces its loop by the line and logs every sample it read (counters, not rates)."""
    from ahrs_service.logs.reader import read_log
    from ahrs_service.service import Service

    cfg = config.validate({
        "source": {"type": "simulated_spi", "board": "icm42688p", "drdy_gpio": "gpiochip0:17",
                   "sensor_errors": False, "board_options": {"odr_hz": 1000, "fifo_read_hz": 200}},
        "estimator": {"name": "madgwick"},
        "rates": {"estimation_hz": 200, "attitude_hz": 20, "attitude_quaternion_hz": 20},
        "mavlink": {"endpoints": ["udpout:127.0.0.1:9"]},
        "log": {"directory": str(tmp_path / "logs")},
    })
    svc = Service(cfg, duration_s=2.0)
    svc.start()
    try:
        assert isinstance(svc.scheduler, DataReadyScheduler)
        assert not svc.pipeline.use_mag  # no magnetometer on this part: no wait for one
        svc.run()
        line = svc.source.data_ready_line
        diag = svc.source.diagnostics
        # a wait ends on the line (its edges, one or several collected at once on a busy
        # host, or the level still above the watermark) or on a timeout: the line, not the
        # fallback timer, paced most of the loop
        woken_by_line = svc.scheduler.ticks - line.timeouts
        assert line.edges > 0 and woken_by_line > line.timeouts
        assert svc.pipeline.samples == diag.samples - len(svc.source._rows) > 0
        estimated = svc.pipeline.samples
    finally:
        svc.close()
    (log_path,) = (tmp_path / "logs").glob("*.mcap")
    log = read_log(log_path)
    assert len(log.t_ns) == estimated and (np.diff(log.t_ns) > 0).all()
    # the rows are the part's samples, 1 / (1000 Hz · 1.0042) apart once its rate is tracked
    late = log.t_ns[len(log.t_ns) // 2:]
    assert np.median(np.diff(late)) == pytest.approx(1e9 / 1004.2, rel=2e-3)
