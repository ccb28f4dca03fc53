"""The sensor clock's timestamps against the simulator's true sample times (issue 18's target):
an MPU-9250 running 1 % fast, read through its FIFO by a host that calls late by a jittering
amount, on a simulated clock (``benchmarks/fifo_timestamps.py``, which prints the other boards
beside the host-read-time reference): p99 of |t_ns − true| within 50 µs after 10 s.
"""

from __future__ import annotations

import numpy as np

from benchmarks.fifo_timestamps import BOARDS, run


def test_mpu9250_fifo_times_within_50_us_p99_of_the_true_sample_times():
    name, bus, options, _ = BOARDS[0]
    err = run(name, bus, options, clock_error=0.01, seconds=12.0, settle_s=10.0, seed=1)
    sensor = np.abs(err["sensor_clock"])
    assert len(sensor) > 1900
    assert np.percentile(sensor, 99) <= 50_000
    # the reference (the host's read time, nominal spacing back from it) is far off: the
    # bound above is the sensor clock's doing
    assert np.percentile(np.abs(err["host_read"]), 99) > 400_000
