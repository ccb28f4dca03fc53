"""The fixed-rate scheduler's logic on a fake clock: absolute deadlines, overrun counting,
and the per-second statistics (no timing assertions: the clock here is simulated)."""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service import scheduler as scheduler_mod
from ahrs_service.scheduler import FixedRateScheduler


class FakeTime:
    """monotonic_ns/sleep with a clock that only moves when told (sleep moves it exactly)."""

    def __init__(self) -> None:
        self.now = 1_000_000_000

    def monotonic_ns(self) -> int:
        self.now += 1  # reading the clock takes a nanosecond: the spin loop terminates
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += int(seconds * 1e9)

    cpu = 0  # the loop thread's CPU clock, moved by the test

    def thread_time_ns(self) -> int:
        return self.cpu


@pytest.fixture
def clock(monkeypatch) -> FakeTime:
    fake = FakeTime()
    monkeypatch.setattr(scheduler_mod, "time", fake)
    return fake


def test_deadlines_are_absolute_and_a_late_tick_is_one_overrun(clock):
    s = FixedRateScheduler(1000.0)
    start = s.wait()
    for k in range(1, 10):
        assert abs(s.wait() - (start + k * 1_000_000)) < 100  # on the grid, no drift
        s.done()
    clock.now += 3_500_000  # the work of this tick took 3.5 periods
    woke = s.wait()
    assert s.overruns == 1 and s.missed_ticks == 2
    assert 0 < woke - (start + 12_000_000) < 1_000_000  # ticks 10 and 11 skipped; 12 runs late
    nxt = s.wait()
    assert abs(nxt - (start + 13_000_000)) < 100  # and the next is back on the original grid
    assert s.overruns == 1


def test_stats_describe_the_last_second(clock):
    s = FixedRateScheduler(100.0)  # the window is one second: 100 ticks
    s.wait()
    periods = []
    rng = np.random.default_rng(1)
    for _ in range(300):
        late = int(rng.integers(0, 2_000_000))  # up to 2 ms late, then back on the grid
        clock.now += late
        before = s._wake
        now = s.wait()
        periods.append(now - before)
        s.done()
    st = s.stats()
    jitter = np.abs(np.array(periods[-100:]) - 10_000_000) / 1e3
    assert st.period_jitter_p50_us == pytest.approx(np.percentile(jitter, 50))
    assert st.period_jitter_p99_us == pytest.approx(np.percentile(jitter, 99))
    assert st.period_jitter_max_us == pytest.approx(jitter.max())
    assert st.ticks == 301 and st.overruns == 0


def test_an_overruns_whole_delay_is_its_lateness_and_the_cpu_share_is_the_threads(clock):
    s = FixedRateScheduler(100.0)
    s.wait()
    for _ in range(150):  # each tick busy 2.5 ms of its 10 ms, 1 ms of it on the CPU (preempted)
        clock.now += 2_500_000
        clock.cpu += 1_000_000
        s.done()
        s.wait()
    st = s.stats()
    assert st.lateness_max_us < 10
    # busy: 99 ended ticks of 2.5 ms and the current one, not ended yet; CPU: the ended ones only
    assert st.load_percent == pytest.approx(24.75, abs=0.01) and st.cpu_percent == pytest.approx(10.0, abs=0.01)
    clock.now += 2_500_000 + 35_000_000  # this tick's work, then a 35 ms stall of the host
    clock.cpu += 1_000_000
    s.done()
    s.wait()
    st = s.stats()
    # woken 37.5 ms after the tick's start: 27.5 ms after the first deadline it missed
    assert st.overruns == 1 and st.lateness_max_us == pytest.approx(27_500, abs=10)


def _health_reports(tolerance_s, lateness_ms: float, rate_hz: float = 200.0) -> list[str]:
    import types

    from ahrs_service.health import ServiceHealth
    from ahrs_service.scheduler import LoopStats

    said: list[str] = []
    health = ServiceHealth(lambda text, severity=6, kind=None: said.append(text))
    st = LoopStats(rate_hz, 1000, 3, 5, 10.0, 100.0, 1000.0, 100.0, 20.0, lateness_max_us=lateness_ms * 1e3)
    health.report_samples_at_risk(st, types.SimpleNamespace(late_tolerance_s=tolerance_s))
    return said


def test_a_late_tick_warns_only_when_the_fifo_nears_its_depth():
    # a FIFO holding 35 ms: 10 ms late is absorbed (counted, not warned); 20 ms is at risk
    assert _health_reports(0.035, 10.0) == []
    (text,) = _health_reports(0.035, 20.0)
    assert text.startswith("loop overruns:") and "20 ms late" in text and "holds 35 ms" in text
    # a source whose buffer the loop cannot approach (a socket, a log) never warns of a late tick
    assert _health_reports(None, 500.0) == []
    # a FIFO that holds less than a period: only a tick late by a period (an overrun) warns
    assert _health_reports(0.001, 3.0) == [] and len(_health_reports(0.001, 6.0)) == 1


def test_fifo_boards_say_how_late_the_loop_may_come():
    from ahrs_service import config as config_mod
    from ahrs_service.sources import make_source

    cfg = config_mod.validate({})  # the embedded default: the simulated GY-80 through its FIFOs
    board = make_source(cfg.source, cfg.rates["estimation_hz"])
    spans = [p.fifo_layout.depth_frames / p.rate_hz for p in board.parts.values() if hasattr(p, "fifo_layout")]
    assert len(spans) == 2 and board.late_tolerance_s == pytest.approx(min(spans) - 1 / board.fifo_read_hz)
    assert 0.005 < board.late_tolerance_s < 0.5
    polled = make_source(dict(cfg.source, board_options={"fifo": False}), cfg.rates["estimation_hz"])
    assert polled.late_tolerance_s is None  # each skipped tick is counted lost instead


def test_rate_must_be_positive():
    with pytest.raises(ValueError, match="rate_hz"):
        FixedRateScheduler(0.0)


@pytest.mark.parametrize("fifo, spin_ns", [(True, 0), (False, FixedRateScheduler.SPIN_NS)])
def test_the_loop_spins_before_its_wake_up_only_for_a_source_timed_by_it(tmp_path, fifo, spin_ns):
    """A polled part's sample is stamped at the wake-up (spinning the last 20 µs makes that
    instant exact); a FIFO's rows carry their own times, so its loop sleeps to the deadline."""
    from ahrs_service import config
    from ahrs_service.service import Service

    cfg = config.validate({
        "source": {"type": "simulated_i2c", "board": "mpu9250", "board_options": {"fifo": fifo}},
        "mavlink": {"endpoints": ["udpout:127.0.0.1:9"]},
        "log": {"directory": str(tmp_path)},
    })
    service = Service(cfg, duration_s=0.2)
    service.start()
    try:
        assert service.source.times_on_sensor_clock is fifo
        assert service.scheduler.spin_ns == spin_ns
        service.run()
    finally:
        service.close()
