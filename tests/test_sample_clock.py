"""Sample-clock recovery on synthetic stamps with known jitter, bursts, gaps and drift.

The bounds asserted (see docs/timing.md): after the first second (two with one stamp per
FIFO block of 8), each recovered time lies
within a fifth of a period of the true sample time plus the mean latency, and each recovered
step within 0.5 % of the true period; the tracked rate within 0.1 %.
"""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service.core.sample_clock import SampleClock, recover_times

RATE = 400.0
T = 1.0 / RATE


def latency(rng: np.random.Generator, n: int) -> np.ndarray:
    """One-sided host latency like the DIDO flights': 0.3 ms floor, exponential tail (mean
    0.9 ms), a 6 ms stall every few hundred samples."""
    lat = 0.3e-3 + rng.exponential(0.6e-3, n)
    stalls = rng.random(n) < 0.004
    lat[stalls] += 6e-3
    return lat


def settled(true_t: np.ndarray, rec: np.ndarray, lat_mean: float, period: float, skip: int):
    err = rec[skip:] - true_t[skip:] - lat_mean
    step_err = np.diff(rec[skip:]) / np.diff(true_t[skip:]) - 1.0
    return np.abs(err).max() / period, np.abs(step_err).max()


def test_clean_uniform_stamps_come_back_bit_for_bit():
    t = 1_700_000_000.0 + np.arange(20_000) * 0.0035  # epoch seconds, 285.7 Hz
    out = recover_times(t)
    assert out.dtype == np.float64
    assert np.array_equal(out, t)
    ns = 12_345_678_901 + np.arange(5000, dtype=np.int64) * 2_500_000
    clock = SampleClock(RATE)
    got = np.concatenate([clock.stamp(int(s)) for s in ns])
    assert got.dtype == np.int64
    assert np.array_equal(got, ns)
    assert clock.lost_samples == 0
    assert clock.rate_hz == pytest.approx(RATE, rel=1e-12)


def test_jitter_is_removed_within_bound():
    rng = np.random.default_rng(1)
    n = 12_000
    true_t = 100.0 + np.arange(n) * T
    lat = latency(rng, n)
    rec = recover_times(true_t + lat)
    worst_t, worst_step = settled(true_t, rec, lat.mean(), T, skip=int(RATE))
    raw_step = np.abs(np.diff(true_t + lat) / T - 1).max()
    assert raw_step > 1.0  # the raw steps are off by more than a whole period
    assert worst_t < 0.2
    assert worst_step < 0.005
    assert np.all(np.diff(rec) > 0)


def test_batch_equals_feeding_one_stamp_at_a_time_and_is_causal():
    rng = np.random.default_rng(2)
    t = 5.0 + np.arange(3000) * T + latency(rng, 3000)
    batch = recover_times(t, nominal_rate_hz=RATE)
    clock = SampleClock(RATE, unit="s")
    one = np.concatenate([clock.stamp(float(s)) for s in t])
    assert np.array_equal(batch, one)
    # a sample's time depends only on the stamps up to it
    assert np.array_equal(recover_times(t[:1700], nominal_rate_hz=RATE), batch[:1700])


def test_ns_and_seconds_agree_within_a_nanosecond():
    rng = np.random.default_rng(3)
    true_ns = 10**12 + np.arange(4000, dtype=np.int64) * 2_500_000
    stamps = true_ns + (latency(rng, 4000) * 1e9).astype(np.int64)
    clock = SampleClock(RATE)
    ns = np.concatenate([clock.stamp(int(s)) for s in stamps])
    sec = recover_times((stamps - 10**12) * 1e-9, nominal_rate_hz=RATE)
    assert np.abs((ns - 10**12) - sec * 1e9).max() <= 1.0


def test_fifo_blocks_and_bursts():
    """Blocks of 8 samples read every 20 ms (stamp(t, n=8)), and the same samples stamped
    one by one with the block's read time (a burst of equal stamps)."""
    rng = np.random.default_rng(4)
    n_blocks, size = 1500, 8
    true_t = np.arange(n_blocks * size) * T
    newest = true_t[size - 1 :: size]
    read = newest + latency(rng, n_blocks)
    clock = SampleClock(RATE, unit="s")
    rec = np.concatenate([clock.stamp(float(r), n=size) for r in read])
    lat_mean = float((read - newest).mean())
    # one stamp per block: the line settles in stamps, so skip the first 2 s (100 stamps)
    worst_t, worst_step = settled(true_t, rec, lat_mean, T, skip=int(2 * RATE))
    assert worst_t < 0.2 and worst_step < 0.005
    burst = recover_times(np.repeat(read, size), nominal_rate_hz=RATE)
    # a burst stamps every sample with its newest one's read time: on average 3.5 periods late
    worst_t, worst_step = settled(true_t, burst, lat_mean + (size - 1) * T / 2, T, skip=int(2 * RATE))
    assert worst_t < 0.2 and worst_step < 0.005


def test_gaps_without_counter_are_whole_missing_periods():
    rng = np.random.default_rng(5)
    n = 12_000
    k = np.arange(n)
    keep = np.ones(n, bool)
    keep[3000:3003] = False  # 3 samples lost
    keep[7000] = False  # 1 sample lost
    true_t = 20.0 + k[keep] * T
    lat = latency(rng, true_t.size)
    clock = SampleClock(RATE, unit="s")
    rec = np.concatenate([clock.stamp(float(s)) for s in true_t + lat])
    assert clock.lost_samples == 4
    # away from the confirmation runs (gap_confirm_s = 0.25 s after each gap), within bound
    ok = np.ones(true_t.size, bool)
    ok[:400] = False
    for g in (3000, 6997):
        ok[g - 1 : g + 110] = False
    err = np.abs(rec - true_t - lat.mean())[ok] / T
    assert err.max() < 0.2
    # the step across a confirmed gap is whole periods: no sample is squeezed in
    steps = np.round(np.diff(rec) / T)
    assert steps.sum() == pytest.approx((true_t[-1] - true_t[0]) / T, abs=1)


def test_a_gap_of_several_periods_is_placed_at_its_own_step():
    """Bursts of lost samples (a FIFO overflow): the step across each gap carries the gap's
    whole time at once, where the estimators integrate it, and the samples after it keep
    their times; without that, the index moved only after gap_confirm_s, and the samples in
    between came out squeezed by up to the gap's length."""
    rng = np.random.default_rng(8)
    n = 20_000
    keep = np.ones(n, bool)
    starts = rng.choice(np.arange(800, n - 200, 97), 60, replace=False)
    for g in starts:
        keep[g : g + rng.integers(8, 40)] = False  # 20-100 ms at 400 Hz
    true_t = 30.0 + np.flatnonzero(keep) * T
    lat = latency(rng, true_t.size)
    rec = recover_times(true_t + lat, nominal_rate_hz=RATE)
    # one stamp decides the step, and a stamp may be a period late (the latency's tail): the
    # step is right to within that period, which the confirmation runs then take back
    err = np.abs(rec - true_t - lat.mean())[400:] / T
    assert err.max() < 1.1
    assert np.median(err) < 0.1
    steps = np.diff(rec) / T
    true_steps = np.diff(true_t) / T
    gap = true_steps > 4
    assert np.abs(steps[gap] - true_steps[gap]).max() < 1.1
    assert np.mean(np.abs(steps[gap] - true_steps[gap]) < 0.5) > 0.8


def test_stamps_in_fifo_bursts_are_not_taken_for_gaps():
    """Blocks of 8 samples each stamped with their read time scatter ±3.5 periods about the
    line: a gap at once must stand out of that scatter, so none is found."""
    rng = np.random.default_rng(9)
    size = 8
    true_t = np.arange(1500 * size) * T
    read = true_t[size - 1 :: size] + latency(rng, 1500)
    clock = SampleClock(RATE, unit="s")
    for r in np.repeat(read, size):
        clock.stamp(float(r))
    assert clock.lost_samples == 0


def test_stamp_indexed_counts_gaps_at_once():
    rng = np.random.default_rng(6)
    idx = np.concatenate([np.arange(0, 2000), np.arange(2005, 4000)])
    true_t = idx * T
    stamps = ((true_t + latency(rng, idx.size)) * 1e9).astype(np.int64)
    clock = SampleClock(RATE)
    rec = np.array([clock.stamp_indexed(int(s), int(i)) for s, i in zip(stamps, idx)])
    assert clock.lost_samples == 5
    after = np.searchsorted(idx, 2005)
    assert (rec[after] - rec[after - 1]) / 2.5e6 == pytest.approx(6.0, abs=0.02)
    with pytest.raises(ValueError, match="sample index must increase"):
        clock.stamp_indexed(int(stamps[-1]) + 10, int(idx[-1]))


def test_rate_drift_is_tracked():
    """The sensor's period drifts by 0.5 % over 30 s (a warming oscillator, exaggerated)."""
    rng = np.random.default_rng(7)
    n = 12_000
    period = T * (1.0 + 0.005 * np.arange(n) / n)
    true_t = np.concatenate([[0.0], np.cumsum(period[1:])])
    lat = latency(rng, n)
    clock = SampleClock(RATE, unit="s")
    rec = np.concatenate([clock.stamp(float(s)) for s in true_t + lat])
    assert clock.rate_hz == pytest.approx(1.0 / period[-1], rel=1e-3)
    worst_t, worst_step = settled(true_t, rec, lat.mean(), T, skip=int(RATE))
    assert worst_t < 0.2 and worst_step < 0.005
    assert clock.lost_samples == 0


def test_bad_arguments_are_clear_errors():
    with pytest.raises(ValueError, match="nominal_rate_hz must be positive"):
        SampleClock(0.0)
    with pytest.raises(ValueError, match="unknown tuning window"):
        SampleClock(RATE, window=1.0)
    with pytest.raises(ValueError, match="window_s must be a positive number"):
        SampleClock(RATE, window_s=-1.0)
    clock = SampleClock(RATE)
    with pytest.raises(ValueError, match="integer nanoseconds"):
        clock.stamp(1.5)
    with pytest.raises(ValueError, match="n must be at least 1"):
        clock.stamp(10, n=0)
    clock.stamp(10)
    with pytest.raises(ValueError, match="do not mix"):
        clock.stamp_indexed(20, 1)


def test_blocks_of_many_samples_from_the_start_are_exact_and_increasing():
    """FIFO blocks of 10 at 1 kHz read every 10 ms exactly: the second block must follow the
    first (it once started 1.5 ms before the first block's newest sample)."""
    clock = SampleClock(1000)
    times = np.concatenate([clock.stamp(k * 10_000_000, 10) for k in range(1, 51)])
    assert np.all(np.diff(times) > 0)
    np.testing.assert_array_equal(times, np.arange(1, 501, dtype=np.int64) * 1_000_000)


def test_a_block_read_early_never_goes_back_in_time():
    clock = SampleClock(1000)
    clock.stamp(10_000_000, 10)
    early = clock.stamp(12_000_000, 10)  # ten samples claimed 2 ms later: impossible at 1 kHz
    assert early[0] > 10_000_000 and np.all(np.diff(early) > 0)


def test_whole_periods_rounds_to_the_nearest_with_halves_up():
    from ahrs_service.core.sample_clock import whole_periods

    assert [whole_periods(d, 2.0) for d in (0.0, 0.99, 1.0, 2.9, 3.0, -1.0, -1.01, 1e9 + 1.0)] == \
        [0, 0, 1, 1, 2, 0, -1, 500_000_001]


def test_every_source_kind_gets_its_times_from_the_sample_clock_package():
    """One place for sample times (#21): the FIFO boards' clock and the CAN node's clock map
    are the package's classes, not copies of their own."""
    from test_icm42688p import ConstantImu

    from ahrs_service.core import sample_clock
    from ahrs_service.drivers.boards import make_transport_board
    from ahrs_service.protocols.dronecan.imu_source import DroneCanImuSource

    imu = ConstantImu()
    board = make_transport_board("icm42688p", "spi", simulated_imu=imu, odr_hz=1000)
    try:
        board.open()
        imu.clock.advance(0.05)
        assert len(board.read_block()) > 0
        assert type(board.clock) is sample_clock.SensorClock
    finally:
        board.close()
    assert type(DroneCanImuSource(bus=lambda: None).clock_map) is sample_clock.SensorClockMap
