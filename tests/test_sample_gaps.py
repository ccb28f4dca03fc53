"""What every estimator does across a sample gap (docs/gaps.md, "Across a gap"): the rate is
carried across it interpolated, in steps of the usual length, never one huge integration step;
the reported variance grows with the rotation the gap left unobserved and shrinks as the
corrections remove it; nothing is learned across it.

Synthetic motion with a known answer: a roll whose rate rises linearly, which the bridge's
linear interpolation integrates exactly, while one step at the rate after the gap would be
wrong by half the change of rate times the gap's length. Gap-free and gapped runs see the
same samples, the gapped one without the rows of the gap.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.core.quaternion import quat_conj_array, quat_from_rotvec_array, quat_mul_array, quat_rotate_array
from ahrs_service.estimators import _kernel as K
from ahrs_service.evaluation import metrics

RATE = 200.0
GRAVITY_NED = np.array([0.0, 0.0, -9.81])  # specific force at rest in NED (FRD body, z down)
FIELD_NED = np.array([20.0, 0.0, 45.0])  # µT
GAP = (1360, 1420)  # rows 6.8-7.1 s: a 0.3 s gap while the rate rises
MEMORYLESS = {"triad", "quest"}


def rolling_recording(seconds: float = 20.0):
    """Level start, then from 6 s a roll rate rising at 1 rad/s² to 1.5 rad/s and back to 0 at
    13.5 s; a small steady pitch rate keeps the motion three-dimensional."""
    n = int(seconds * RATE)
    t = np.arange(n) / RATE
    roll_rate = np.clip(t - 6.0, 0.0, 1.5) - np.clip(t - 12.0, 0.0, 1.5)
    gyr = np.zeros((n, 3))
    gyr[:, 0] = roll_rate
    gyr[:, 1] = 0.02
    return recording_of_rates(t, gyr)


def recording_of_rates(t, gyr):
    """The sensor's samples (t, gyr, acc, mag, q_true) at rest in place but for the body rates
    ``gyr``, starting level and facing north."""
    n = len(t)
    # the attitude: the rates integrated exactly at a 10x finer step (trapezoid of the linear rate)
    q = np.empty((n, 4))
    q[0] = (1.0, 0.0, 0.0, 0.0)
    mid = 0.5 * (gyr[1:] + gyr[:-1]) / RATE
    steps = quat_from_rotvec_array(mid)
    for i in range(1, n):
        q[i] = quat_mul_array(q[i - 1 : i], steps[i - 1 : i])[0]
    to_body = quat_conj_array(q)
    acc = quat_rotate_array(to_body, np.broadcast_to(GRAVITY_NED, (n, 3)))
    mag = quat_rotate_array(to_body, np.broadcast_to(FIELD_NED, (n, 3)))
    return t, gyr, acc, mag, q


@pytest.fixture(scope="module")
def recording():
    return rolling_recording()


def run(name: str, t, gyr, acc, mag, keep=None):
    keep = np.ones(len(t), bool) if keep is None else keep
    est = estimators.create(name)
    m = mag[keep] if est.uses_mag else None
    dt = np.diff(t[keep], prepend=t[0] - 1.0 / RATE)
    return est, est.run(gyr[keep], acc[keep], m, dt=dt)


def without_gap(n: int) -> np.ndarray:
    keep = np.ones(n, bool)
    keep[GAP[0] : GAP[1]] = False
    return keep


@pytest.mark.parametrize("name", estimators.names())
def test_the_rate_is_carried_across_a_gap(recording, name):
    """Right after the gap the gapped estimate is where the gap-free one is: the rotation
    during the gap (the rate rising from 0.8 to 1.1 rad/s) is integrated as the samples would
    have; one step at the rate after the gap would be 2.6 degrees off."""
    t, gyr, acc, mag, _ = recording
    keep = without_gap(len(t))
    _, q_free = run(name, t, gyr, acc, mag)
    _, q_gap = run(name, t, gyr, acc, mag, keep)
    after = int(np.searchsorted(np.flatnonzero(keep), GAP[1]))
    total, _, incl = metrics.error_angles(q_gap[after : after + 1], q_free[GAP[1] : GAP[1] + 1])
    one_step = 0.5 * (gyr[GAP[1], 0] - gyr[GAP[0] - 1, 0]) * (t[GAP[1]] - t[GAP[0] - 1])
    assert math.degrees(one_step) > 2.5
    assert math.degrees(total[0]) < 0.25 * math.degrees(one_step)
    assert math.degrees(incl[0]) < 0.25 * math.degrees(one_step)


@pytest.mark.parametrize("name", sorted(set(estimators.names()) - MEMORYLESS))
def test_the_variance_grows_with_the_gap_and_shrinks_after_it(recording, name):
    """The reported roll variance right after the gap holds at least the rotation the gap
    left unobserved (half the change of rate times its length); corrected for a few seconds,
    it is back to what the estimator reported before the gap (within the drift of its model)."""
    t, gyr, acc, mag, _ = recording
    keep = without_gap(len(t))
    est = estimators.create(name)
    m = mag[keep] if est.uses_mag else None
    dt = np.diff(t[keep], prepend=t[0] - 1.0 / RATE)
    rows_before = int(np.searchsorted(np.flatnonzero(keep), GAP[0]))
    est.run(gyr[keep][:rows_before], acc[keep][:rows_before], None if m is None else m[:rows_before], dt=dt[:rows_before])
    before = est.attitude_variance().roll
    est.run(gyr[keep][rows_before : rows_before + 1], acc[keep][rows_before : rows_before + 1],
            None if m is None else m[rows_before : rows_before + 1], dt=dt[rows_before : rows_before + 1])
    after = est.attitude_variance().roll
    unobserved = 0.5 * (gyr[GAP[1], 0] - gyr[GAP[0] - 1, 0]) * (t[GAP[1]] - t[GAP[0] - 1])
    assert after >= before + unobserved**2
    later = rows_before + int(6 * RATE)
    est.run(gyr[keep][rows_before + 1 : later], acc[keep][rows_before + 1 : later],
            None if m is None else m[rows_before + 1 : later], dt=dt[rows_before + 1 : later])
    assert est.attitude_variance().roll < before + 0.05 * unobserved**2


@pytest.mark.parametrize("name", sorted(set(estimators.names()) - MEMORYLESS))
def test_a_gap_is_counted_and_bridged_in_usual_steps(recording, name):
    """One gap counted; its bridge's missing accelerometer and field are not the sensor's: the
    skipped-correction counters stay as they are without the gap."""
    t, gyr, acc, mag, _ = recording
    est_free, _ = run(name, t, gyr, acc, mag)
    est_gap, _ = run(name, t, gyr, acc, mag, without_gap(len(t)))
    assert est_gap.state[K.GAPS] == 1
    assert est_free.state[K.GAPS] == 0
    assert est_gap.diagnostics["acc_skipped"] == est_free.diagnostics["acc_skipped"]


@pytest.mark.parametrize("name", ["mahony_direct", "robust", "quaternion_kf", "valenti"])
def test_no_bias_is_learned_from_a_gap(recording, name):
    """An outage of 2 s while the rate changes leaves an error that is a step, not a drift:
    the gyro-bias estimate after it is the gap-free run's (the true bias is 0). Not the EKF:
    its bias is held only while ``gap_error`` says the error is uncorrected, and its own gain
    corrects a 30° step more slowly than that decays (docs/gaps.md, "Limits")."""
    t, gyr, acc, mag, _ = recording
    keep = np.ones(len(t), bool)
    keep[int(7.0 * RATE) : int(9.0 * RATE)] = False
    est_free, _ = run(name, t, gyr, acc, mag)
    est_gap, _ = run(name, t, gyr, acc, mag, keep)
    assert np.degrees(np.abs(est_gap.gyro_bias - est_free.gyro_bias)).max() < 0.05  # °/s


@pytest.mark.parametrize("name", sorted(set(estimators.names()) - MEMORYLESS))
def test_a_rotation_a_gap_hid_is_realigned_from_the_accelerometer(name):
    """A roll at 1.5 rad/s that stops inside a 0.4 s gap, then rest: the bridge carries the
    rate's mean across the gap and leaves 13° of roll unobserved (a shock or an outage does
    this on a vehicle). Its gap_error covers it, and within 0.75 s the tilt is realigned from
    the averaged specific force (``_kernel.realign_tilt``) to within 2°, whatever the
    estimator's own gain; the gap-free run, for comparison, stays within 0.5°."""
    t = np.arange(int(8.0 * RATE)) / RATE
    gyr = np.zeros((len(t), 3))
    gyr[(t >= 5.0) & (t < 5.45), 0] = 1.5
    t, gyr, acc, mag, q_true = recording_of_rates(t, gyr)
    keep = (t < 5.1) | (t >= 5.5)
    est, q_gap = run(name, t, gyr, acc, mag, keep)
    _, q_free = run(name, t, gyr, acc, mag)
    kept = np.flatnonzero(keep)
    after = int(np.searchsorted(kept, int(5.5 * RATE)))
    _, _, incl = metrics.error_angles(q_gap, q_true[keep])
    assert math.degrees(incl[after]) > 10.0  # the gap hid the rotation
    later = after + int(0.75 * RATE)
    assert math.degrees(incl[later:].max()) < 2.0
    assert est.diagnostics["realignments"] >= 1
    _, _, incl_free = metrics.error_angles(q_free, q_true)
    assert math.degrees(incl_free[kept[later]:].max()) < 0.5
