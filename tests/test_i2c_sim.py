"""End to end: the motion simulator behind simulated I2C registers, read by the real drivers.

The first paper's validation manoeuvre (±90° about x, y, z) drives a simulated GY-80; the
board's samples, read on a stepped ManualClock, go through Madgwick's filter, which must
reproduce the simulator's truth.
"""

from __future__ import annotations

import numpy as np
import pytest

sim = pytest.importorskip("ahrs_service.drivers.sim", reason="motion simulator (drivers/sim) not available")

from analytic import error_deg  # noqa: E402

from ahrs_service import estimators  # noqa: E402
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID  # noqa: E402
from ahrs_service.drivers.boards import make_simulated_board

RATE = 100.0  # Hz: the L3G4200D's slowest rate keeps the test short


def _collect(board, imu, duration):
    samples = []
    for _ in range(int(round(duration * RATE))):
        imu.clock.advance(1.0 / RATE)
        s = board.read()
        if s is not None:
            samples.append(s)
    return samples


def test_gy80_validation_manoeuvre_through_registers_and_madgwick():
    traj = sim.profile("validation")
    imu = sim.SimulatedImu(traj, clock=sim.ManualClock())
    board = make_simulated_board("gy80", imu, gyro_rate_hz=RATE, acc_rate_hz=RATE, mag_rate_hz=75)
    for addr in (0x69, 0x53):
        # on the nominal grid, so each row's time is its sample's: the values are compared
        # with the truth at the row's time (the sensor clock's tracking is tested apart)
        board.bus.device(addr).clock_error = 0.0
    with board:
        samples = _collect(board, imu, traj.duration)

    n = len(samples)
    # one row per gyro sample, none twice: every sample the gyro produced is a row, still
    # waiting (FIFO, host queue), or older than the accelerometer's first sample (the pairing
    # rule has no value for it)
    gyro, acc = board.bus.device(0x69), board.bus.device(0x53)
    older = int(np.ceil(gyro.sampling_rate_hz() / acc.sampling_rate_hz())) - 1
    assert n + board.pending + gyro.fifo_frames + older == gyro.samples_due
    t = np.array([s.t_ns for s in samples]) * 1e-9
    assert np.all(np.diff(t) > 0)
    assert all(s.flags & GYR_VALID and s.flags & ACC_VALID for s in samples)
    gyr = np.array([s.gyr for s in samples])
    acc = np.array([s.acc for s in samples])
    mag = np.array([s.mag if s.mag is not None else [np.nan] * 3 for s in samples])
    q_true = np.array([s.truth_q for s in samples])
    with_mag = np.array([s.mag is not None for s in samples])
    assert all(s.flags & MAG_NEW and s.flags & MAG_VALID for s in samples if s.mag is not None)
    # 75 Hz under a 100 Hz gyro: at most 3 in 4 samples carry a new field (see the next check)
    assert 0.55 < with_mag.mean() <= 0.75

    # the register path is faithful: within quantisation of the simulator's truth
    truth = [traj.state(ti) for ti in t]
    np.testing.assert_allclose(gyr, [s.omega_body for s in truth], atol=70e-3 * np.pi / 180)
    np.testing.assert_allclose(acc, [s.specific_force_body for s in truth], atol=9.80665 / 256)
    # the magnetometer runs on its own 75 Hz grid: compare where the body holds still
    still = np.zeros(n, bool)
    for _, start, end in traj.phases:
        still |= (t > start + 0.05) & (t <= end)
    check = with_mag & still
    # at rest the readings repeat, so only the pacing (a period + 5 %, polled every 10 ms) makes
    # one new: every second sample
    assert abs(check.sum() / still.sum() - 0.5) < 0.02
    np.testing.assert_allclose(mag[check], [truth[i].mag_body for i in np.flatnonzero(check)],
                               atol=100 / 1090)

    q = estimators.run("madgwick", gyr, acc, mag, timestamps=t)
    total, heading, incl = error_deg(q, q_true)
    assert np.max(total) < 2.0
    assert np.mean(total) < 0.5
    assert np.max(incl) < 1.5


def test_counts_array_rounds_and_clips_as_to_counts():
    """The twins' vectorised digitisation is the per-value one: ties to even, clipped to the
    register's range, +inf to the top, −inf and NaN to the bottom."""
    from ahrs_service.drivers.sim.register_device import counts_array, to_counts

    values = np.array([0.0, 0.5, 1.5, 2.5, -0.5, -1.5, 0.49999999, 1e9, -1e9, np.inf, -np.inf, np.nan,
                       32767.4, 32767.6, -32768.5, -32769.0, 123.456])
    for lsb in (1.0, 0.25, 1 / 333.87):
        assert counts_array(values, lsb, -32768, 32767).tolist() == \
            [to_counts(v, lsb, -32768, 32767) for v in values.tolist()]
