"""Time input of ``estimators.run``: implausible stamps are a clear ValueError naming the
problem and the expected unit; jittered stamps are recovered onto the sensor's clock."""

from __future__ import annotations

import re

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.estimators.base import time_steps

N = 400
RATE = 400.0


def still(n: int = N):
    gyr = np.zeros((n, 3))
    gyr[:, 0] = 0.5  # a steady roll rate, so time errors show in the attitude
    acc = np.tile([0.0, 0.0, 9.81], (n, 1))
    return gyr, acc


@pytest.mark.parametrize(
    "scale, unit, factor",
    [(1e9, "nanoseconds", "1e+09"), (1e6, "microseconds", "1e+06"), (1e3, "milliseconds", "1000")],
)
def test_stamps_in_another_unit_name_the_unit(scale, unit, factor):
    gyr, acc = still()
    t = np.arange(N) / RATE * scale
    with pytest.raises(ValueError, match=re.escape(f"look like {unit}, expected seconds (divide by {factor})")):
        estimators.run("madgwick", gyr, acc, None, timestamps=t)


@pytest.mark.parametrize(
    "scale, unit, factor",
    [(1e9, "nanoseconds", "1e+09"), (1e6, "microseconds", "1e+06"), (1e3, "milliseconds", "1000")],
)
def test_stamps_in_another_unit_read_in_bursts_name_the_unit(scale, unit, factor):
    """Issue 14 re-probe: host stamps of FIFO reads (ten samples a read, one stamp each) in
    nanoseconds ran without a word: nine steps in ten are 0, so the median step was 0."""
    gyr, acc = still()
    t = (np.arange(N) // 10) * (10 / RATE) * scale
    with pytest.raises(ValueError, match=re.escape(f"look like {unit}, expected seconds (divide by {factor})")):
        estimators.run("madgwick", gyr, acc, None, timestamps=t)


@pytest.mark.parametrize("per_read", [2, 10, 40])
def test_stamps_read_in_bursts_recover_positive_steps_without_a_nominal_rate(per_read):
    """Issue 14 re-probe: bursts in seconds without rate_hz: the starting period was the 1 Hz
    fallback (the median step is 0) and a quarter of the steps came out negative (to -1.2 s)."""
    t = (np.arange(N) // per_read) * (per_read / RATE)
    dt = time_steps(N, None, t)
    assert np.all(dt > 0)
    if per_read <= 10:  # 40 a read: ten reads in all, the causal fit is still settling
        assert np.mean(dt) == pytest.approx(1 / RATE, rel=0.03)


def test_stamps_that_are_all_equal_are_an_error():
    """All stamps equal (a clock read once, a truncated cast) ran with made-up steps of ~0.5 s."""
    gyr, acc = still()
    with pytest.raises(ValueError, match=r"^timestamps: all 400 are equal \(12 s\): no time passes"):
        estimators.run("madgwick", gyr, acc, None, timestamps=np.full(N, 12.0))


def test_non_monotonic_stamps_are_an_error():
    gyr, acc = still()
    t = np.arange(N) / RATE
    t[200] = t[198]
    with pytest.raises(ValueError, match=r"not increasing at sample 200 .* 1 step\(s\) negative; expected non-decreasing sample times in seconds"):
        estimators.run("robust", gyr, acc, None, timestamps=t)
    t = np.arange(N) / RATE
    t[10] = t[9]  # a repeated stamp is not a time step when integrated raw
    with pytest.raises(ValueError, match="not increasing at sample 10 .* zero or negative"):
        time_steps(N, None, t, recover_clock=False)
    # recovered, it is a burst (two samples read at once) and gets its own time
    dt = time_steps(N, None, t)
    assert np.all(dt > 0)


def test_nan_stamps_are_an_error():
    gyr, acc = still()
    t = np.arange(N) / RATE
    t[[5, 7]] = np.nan
    with pytest.raises(ValueError, match=r"2 NaN or infinite value\(s\), first at sample 5; expected finite sample times in seconds"):
        estimators.run("ekf", gyr, acc, None, timestamps=t)


def test_uniform_stamps_give_the_rate_result_bit_for_bit():
    gyr, acc = still()
    t = np.arange(N) * 0.0025
    by_rate = estimators.run("robust", gyr, acc, None, rate_hz=1.0 / np.median(np.diff(t)))
    by_stamps = estimators.run("robust", gyr, acc, None, timestamps=t, recover_clock=False)
    recovered = estimators.run("robust", gyr, acc, None, timestamps=t)
    assert np.array_equal(recovered, by_stamps)
    assert np.abs(by_stamps - by_rate).max() < 1e-12  # steps differ from 1/rate by rounding only


def test_jittered_stamps_are_recovered_by_default():
    """A steady 0.5 rad/s yaw for 10 s (level, so the accelerometer does not correct it)
    stamped with one-sided host latency: with the raw steps the integrated yaw wanders with
    the jitter; recovered, five times less, and it grows at the true rate to 0.1 %."""
    n = 4000
    gyr = np.zeros((n, 3))
    gyr[:, 2] = 0.5
    acc = np.tile([0.0, 0.0, -9.81], (n, 1))  # FRD at rest: specific force points up (−z)
    rng = np.random.default_rng(11)
    true_t = np.arange(n) / RATE
    # arrival stamps: one-sided latency of 0.3-2.3 ms (less than a period: stamps stay in order)
    t = true_t + 0.3e-3 + rng.uniform(0.0, 2.0e-3, n)

    def yaw(q):
        return np.abs(np.unwrap(2.0 * np.arctan2(q[:, 3], q[:, 0])))

    truth = 0.5 * (true_t + 1.0 / RATE)
    raw = yaw(estimators.run("complementary_reduced", gyr, acc, None, rate_hz=RATE, timestamps=t, recover_clock=False))
    rec = yaw(estimators.run("complementary_reduced", gyr, acc, None, rate_hz=RATE, timestamps=t))
    # the first stamp's latency offsets every later angle alike: compare the wander
    raw_wander = np.ptp((raw - truth)[800:])
    rec_wander = np.ptp((rec - truth)[800:])
    assert raw_wander > 5 * rec_wander
    # the angle grows at the true rate to 0.1 %
    assert (rec[-1] - rec[800]) / (truth[-1] - truth[800]) == pytest.approx(1.0, abs=1e-3)
