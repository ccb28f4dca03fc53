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
