"""The robust estimator ("robust", GIMLET): BROAD acceptance against VQF, one simulated test
per robustness feature, bad samples, and per-sample == batch.

Simulated motions are generated here in the style of tests/analytic.py (earth NED, body FRD):
the true attitude is integrated from the true rate with the same convention the estimators
use (the gyro sample k is the rate over (t_{k-1}, t_k]), then sensor errors and disturbances
are added with a fixed seed.

Error bounds commented "measured X; other seeds up to Y" are about three times the error
measured with the test's seed (X), and at least 1.5 times the largest error measured with
six other seeds (Y), so that they follow the result without depending on the seed.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.core.quaternion import (
    ned_to_enu_array,
    quat_conj_array,
    quat_mul_array,
    quat_rotate_array,
)
from ahrs_service.estimators import robust as R
from ahrs_service.estimators.base import stack_rows
from tests.analytic import FIELD_NED, G, error_deg, simulate, wobble

DEG = math.pi / 180.0

# ----------------------------------------------------------------------------- simulation


def sense(q, omega, seed=1, field_earth=None, hard_iron=None, gyro_bias=None):
    """Noisy gyro, accelerometer (specific force at rest) and magnetometer for attitudes q.

    field_earth: (N, 3) earth field (default FIELD_NED everywhere); hard_iron: (N, 3) body-fixed
    offset added to the magnetometer; gyro_bias: (N, 3) added to the gyro.
    """
    rng = np.random.default_rng(seed)
    n = len(q)
    qc = quat_conj_array(q)
    field = np.broadcast_to(FIELD_NED, (n, 3)) if field_earth is None else field_earth
    gyr = omega + rng.normal(0, 0.003, (n, 3))
    acc = quat_rotate_array(qc, np.broadcast_to([0.0, 0.0, -G], (n, 3))) + rng.normal(0, 0.05, (n, 3))
    mag = quat_rotate_array(qc, field) + rng.normal(0, 0.5, (n, 3))
    if hard_iron is not None:
        mag = mag + hard_iron
    if gyro_bias is not None:
        gyr = gyr + gyro_bias
    return gyr, acc, mag


def run_robust(gyr, acc, mag, dt, **params):
    est = estimators.create("robust", **params)
    return est, est.run(gyr, acc, mag, dt=dt)


def rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# ----------------------------------------------------------------------------- BROAD acceptance

GROUPS = {
    "rotation": ("02", "07", "09"),
    "translation": ("11", "15", "18"),
    "tapping": ("24",),
    "vibration": ("27",),
    "stationary magnet": ("30",),
    "attached magnet": ("32", "34", "36"),
}


def broad_rmse(q_enu, ref, movement):
    """(total, heading, inclination) RMSE in degrees over the movement samples (BROAD metric)."""
    e = quat_mul_array(q_enu, quat_conj_array(ref))
    w, z = np.abs(e[:, 0]), e[:, 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        per = (
            2 * np.arccos(np.clip(w, 0, 1)),
            2 * np.arctan(np.abs(z / w)),
            2 * np.arccos(np.clip(np.sqrt(e[:, 0] ** 2 + z**2), 0, 1)),
        )
    return tuple(float(np.degrees(np.sqrt(np.nanmean(a[movement] ** 2)))) for a in per)


def test_broad_acceptance_against_vqf(broad_dir):
    """Defaults, no latency compensation: no regression from the flight changes of issue 21
    (mean total ≤ 1.95°, mean inclination ≤ 0.69°; measured 1.911° / 0.672°, before them
    1.910° / 0.678°), inclination no worse than VQF's and no group worse than VQF (same run).
    The issue's 0.6° inclination target is not reached this way; see docs/robust-estimator.md."""
    h5py = pytest.importorskip("h5py")
    vqf = pytest.importorskip("vqf")
    files = sorted(broad_dir.glob("*.hdf5"))
    trials = {f.name[:2]: f for f in files}
    missing = [t for ts in GROUPS.values() for t in ts if t not in trials]
    if missing:
        pytest.skip(f"BROAD trials {missing} not in {broad_dir}")
    ours, theirs = {}, {}
    for name, f in trials.items():
        with h5py.File(f, "r") as h:
            gyr, acc, mag = (np.ascontiguousarray(h[k][()], dtype=np.float64) for k in ("imu_gyr", "imu_acc", "imu_mag"))
            ref, movement, rate = h["opt_quat"][()], h["movement"][()].astype(bool), float(h.attrs["sampling_rate"])
        q = ned_to_enu_array(estimators.run("robust", gyr, acc, mag, rate_hz=rate))
        ours[name] = broad_rmse(q, ref, movement)
        theirs[name] = broad_rmse(vqf.VQF(1.0 / rate).updateBatch(gyr, acc, mag)["quat9D"], ref, movement)
    mean_ours = np.mean(list(ours.values()), axis=0)
    mean_vqf = np.mean(list(theirs.values()), axis=0)
    assert mean_ours[0] <= 1.95, ours
    assert mean_ours[2] <= 0.69, ours
    assert mean_ours[2] <= mean_vqf[2], (mean_ours, mean_vqf)
    for group, names in GROUPS.items():
        g_ours = np.mean([ours[n][0] for n in names])
        g_vqf = np.mean([theirs[n][0] for n in names])
        assert g_ours <= g_vqf, (group, g_ours, g_vqf)


# ----------------------------------------------------------------------------- robustness features


def test_gyro_bias_step_is_learned_at_rest_and_in_motion():
    """A bias that appears mid-run is estimated (rest and motion) and the attitude recovers."""
    rate = 200.0
    t = np.arange(0, 150, 1 / rate)
    omega = wobble(t) * ((t > 30) & (t < 110))[:, None]  # rest, motion, rest
    q = simulate(t, omega)
    bias = np.where((t >= 10)[:, None], np.array([0.4, -0.3, 0.5]) * DEG, 0.0)
    gyr, acc, mag = sense(q, omega, seed=2, gyro_bias=bias)
    est, q_est = run_robust(gyr, acc, mag, 1 / rate)
    # measured 0.0013°/s; other seeds up to 0.005°/s
    assert np.all(np.abs(est.gyro_bias - bias[-1]) < 0.01 * DEG)
    total, _, incl = error_deg(q_est, q)
    tail = t > 120
    assert rms(total[tail]) < 0.5  # measured 0.154°; other seeds up to 0.179°
    assert rms(incl[t > 60]) < 0.5
    # without the bias the gyro would have turned the estimate by 0.7 °/s × 140 s; it must not
    assert total.max() < 5.0


def test_tapping_bursts_do_not_tilt_the_inclination():
    """Taps twice a second (3 g for 10 ms in a random direction, then the rebound: the sensor
    does not travel away) barely move the inclination."""
    rate = 285.714
    t = np.arange(0, 60, 1 / rate)
    omega = wobble(t, 20.0)
    q = simulate(t, omega)
    gyr, acc, mag = sense(q, omega, seed=3)
    phase = t % 0.5
    burst = (t > 10) & (t < 50)
    rng = np.random.default_rng(4)
    direction = rng.normal(size=(len(t) // 100 + 1, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    tap_dir = direction[(t // 0.5).astype(int) % len(direction)]
    pulse = np.where(phase < 0.01, 1.0, np.where(phase < 0.02, -1.0, 0.0)) * burst
    acc_tapped = acc + 3 * G * pulse[:, None] * tap_dir
    _, q_clean = run_robust(gyr, acc, mag, 1 / rate)
    _, q_tap = run_robust(gyr, acc_tapped, mag, 1 / rate)
    _, _, incl_tap = error_deg(q_tap, q)
    _, _, incl_clean = error_deg(q_clean, q)
    during = (t > 10) & (t < 50)
    assert rms(incl_tap[during]) < 0.5
    assert rms(incl_tap[during]) < rms(incl_clean[during]) + 0.3
    # the same filter low-passing over 50 ms instead of seconds is visibly tilted by the taps
    _, q_fast = run_robust(gyr, acc_tapped, mag, 1 / rate, tau_acc=0.05, tau_acc_max=0.05)
    assert rms(error_deg(q_fast, q)[2][during]) > 2 * rms(incl_tap[during])


def circling(amp_dps, seed=3):
    """A vehicle circling: at rest for 5 s, then tilting (wobble of ``amp_dps``) while a
    centripetal 3 m/s² that turns once every 3.9 s in the earth frame ramps in from 10 s
    (the sustained acceleration of a quadrotor on a 1.5 m circle at 2 m/s). (t, q, gyr, acc)."""
    rate = 200.0
    t = np.arange(0, 80, 1 / rate)
    omega = wobble(t, amp_dps) * (t > 5)[:, None]
    q = simulate(t, omega)
    gyr, acc, _ = sense(q, omega, seed=seed)
    ramp = np.clip((t - 10) / 5, 0, 1)[:, None]
    a_earth = 3.0 * ramp * np.stack([np.cos(1.6 * t), np.sin(1.6 * t), np.zeros_like(t)], axis=1)
    return t, q, gyr, acc + quat_rotate_array(quat_conj_array(q), a_earth)


def test_accelerometer_time_constant_follows_the_tilt_rate():
    """Sustained, turning accelerations while the sensor tilts slowly (flight): the longer time
    constant the tilt rate allows averages them out; while it tilts fast, tau_acc holds."""
    p = estimators.create("robust").params
    t, q, gyr, acc = circling(8.0)
    est, q_adapt = run_robust(gyr, acc, None, 1 / 200.0)
    _, q_fixed = run_robust(gyr, acc, None, 1 / 200.0, tilt_rate_ref=0.0)
    late = t > 40
    adapt, fixed = rms(error_deg(q_adapt, q)[2][late]), rms(error_deg(q_fixed, q)[2][late])
    # measured 0.54° against 1.52° with the fixed 3 s; other seeds up to 0.36×
    assert adapt < 0.5 * fixed and adapt < 1.0
    # the time constant in force is the law's, from the low-passed tilt rate (≈ 7.5 °/s here)
    tilt = est.state[R.ST.tilt_rate]
    tau = est.state[R.ST.coef_tau_acc]
    assert 5 * DEG < tilt < 10 * DEG
    expected = max(p.tau_acc, p.tau_acc_max / math.sqrt(1 + tilt / (p.tilt_rate_ref * DEG)))
    assert tau == pytest.approx(expected, abs=0.026)  # rounded to 0.05 s for the cache
    # tilting at ≈ 45 °/s the time constant stays near tau_acc and nothing gets worse
    t, q, gyr, acc = circling(60.0)
    est, q_adapt = run_robust(gyr, acc, None, 1 / 200.0)
    _, q_fixed = run_robust(gyr, acc, None, 1 / 200.0, tilt_rate_ref=0.0)
    assert p.tau_acc <= est.state[R.ST.coef_tau_acc] < 1.2 * p.tau_acc  # measured 3.35 s
    # measured 1.42° against 1.52°
    assert rms(error_deg(q_adapt, q)[2][t > 40]) <= rms(error_deg(q_fixed, q)[2][t > 40])


def _bump(t, t0, t1, ramp=1.0):
    """0 → 1 → 0 with cosine ramps of ``ramp`` seconds, full between t0 and t1."""
    up = np.clip((t - t0 + ramp) / ramp, 0, 1)
    down = np.clip((t1 + ramp - t) / ramp, 0, 1)
    return 0.5 - 0.5 * np.cos(np.pi * np.minimum(up, down))


def test_passing_magnet_is_rejected_and_heading_recovers():
    """An earth-fixed field disturbance of 35 µT for 15 s: rejected, heading kept and recovered."""
    rate = 200.0
    t = np.arange(0, 120, 1 / rate)
    omega = wobble(t, 30.0)
    q = simulate(t, omega)
    dist = _bump(t, 50, 65)[:, None] * np.array([-20.0, 25.0, 15.0])
    gyr, acc, mag = sense(q, omega, seed=5, field_earth=FIELD_NED + dist)
    est, q_est = run_robust(gyr, acc, mag, 1 / rate)
    _, heading, _ = error_deg(q_est, q)
    during = (t > 49) & (t < 66)
    assert heading[during].max() < 2.0
    assert rms(heading[t > 90]) < 0.3  # measured 0.100°; other seeds up to 0.186°
    # the same disturbance seen by a filter without rejection
    q_mad = estimators.run("madgwick", gyr, acc, mag, rate_hz=rate)
    assert error_deg(q_mad, q)[1][during].max() > 10.0


def test_attached_magnet_hard_iron_is_learned_used_and_forgotten():
    """A body-fixed offset is attached at 40 s and removed at 140 s: it is estimated while
    turning, the heading uses m − h meanwhile, and after the removal the raw field again."""
    rate = 200.0
    t = np.arange(0, 200, 1 / rate)
    omega = wobble(t, 60.0)
    q = simulate(t, omega)
    h = np.array([22.0, -28.0, 12.0])
    attached = (t >= 40) & (t < 140)
    gyr, acc, mag = sense(q, omega, seed=6, hard_iron=attached[:, None] * h)
    n_on = int(np.searchsorted(t, 130.0))
    est = estimators.create("robust")
    q_on = est.run(gyr[:n_on], acc[:n_on], mag[:n_on], dt=1 / rate)
    diag = est.diagnostics
    assert diag["hard_iron_trusted"]
    assert np.linalg.norm(diag["hard_iron_ut"] - h) < 0.1  # µT; measured 0.034; other seeds up to 0.030
    assert diag["mag_used"] == 2  # the corrected field feeds the heading
    q_off = est.run(gyr[n_on:], acc[n_on:], mag[n_on:], dt=1 / rate)
    diag = est.diagnostics
    assert np.linalg.norm(diag["hard_iron_ut"]) < 1.0
    assert diag["mag_used"] == 1  # magnet gone: the raw field again
    _, heading, _ = error_deg(np.vstack([q_on, q_off]), q)
    assert rms(heading[(t > 100) & (t < 140)]) < 0.15  # measured 0.029°; other seeds up to 0.076°
    assert rms(heading[t > 170]) < 0.15  # measured 0.032°; other seeds up to 0.072°
    assert heading.max() < 5.0
    # learning switched off: the offset field is rejected, then accepted as a "new field"
    # after mag_new_time, which turns the heading away
    _, q_nohi = run_robust(gyr, acc, mag, 1 / rate, hard_iron_tau=0.0)
    assert rms(error_deg(q_nohi, q)[1][(t > 100) & (t < 140)]) > 3 * rms(heading[(t > 100) & (t < 140)])


def test_field_changing_without_rotation_fails_gyro_consistency():
    """After turning (which confirms the field), the sensor rests while the field's horizontal
    direction swings fast around a 10° offset (norm and dip unchanged, as next to a vibrating
    phone): only the gyro-consistency test can tell, and it keeps the heading."""
    rate = 200.0
    t = np.arange(0, 100, 1 / rate)
    omega = wobble(t, 40.0) * (t < 30)[:, None]
    q = simulate(t, omega)
    swing = 10 * DEG * (1 + np.sin(2 * np.pi * 2.0 * t)) * _bump(t, 45, 80)
    c, s = np.cos(swing), np.sin(swing)
    field = np.stack([c * FIELD_NED[0] - s * FIELD_NED[1], s * FIELD_NED[0] + c * FIELD_NED[1], np.full_like(t, FIELD_NED[2])], 1)
    gyr, acc, mag = sense(q, omega, seed=7, field_earth=field)
    est, q_est = run_robust(gyr, acc, mag, 1 / rate)
    _, q_off = run_robust(gyr, acc, mag, 1 / rate, consistency_th=0.0)
    during = (t > 44) & (t < 82)
    h_on = error_deg(q_est, q)[1][during]
    h_off = error_deg(q_off, q)[1][during]
    assert h_on.max() < 1.0
    assert h_off.max() > 3.0
    # once the field is steady again it is used again
    assert est.diagnostics["mag_used"] == 1


def test_jittering_time_steps():
    """Sample instants jitter by ±40 % of the period: the actual dt is used, errors stay small."""
    rng = np.random.default_rng(8)
    dt0 = 1 / 200.0
    dt = dt0 * (1 + rng.uniform(-0.4, 0.4, 24000))
    t = np.cumsum(dt) - dt[0]
    omega = wobble(t, 60.0)
    q = simulate(t, omega)
    gyr, acc, mag = sense(q, omega, seed=9)
    _, q_est = run_robust(gyr, acc, mag, dt)
    total, _, _ = error_deg(q_est, q)
    assert rms(total[t > 20]) < 0.45  # measured 0.142°; other seeds up to 0.225°
    # pretending the rate were constant is clearly worse: the estimator needs each dt
    _, q_const = run_robust(gyr, acc, mag, dt0)
    assert rms(error_deg(q_const, q)[0][t > 20]) > 2 * rms(total[t > 20])


def test_slow_magnetometer_between_nan_rows():
    """1 kHz gyro and accelerometer, 50 Hz magnetometer (NaN rows between): heading converges
    from a start without field, skipped rows are counted."""
    rate = 1000.0
    t = np.arange(0, 60, 1 / rate)
    omega = wobble(t, 40.0)
    q = simulate(t, omega, start=(0.1, -0.2, 2.0))
    gyr, acc, mag = sense(q, omega, seed=10)
    slow = mag.copy()
    no_field = (np.arange(len(t)) % 20) != 5  # first field sample only at row 5
    slow[no_field] = np.nan
    est, q_est = run_robust(gyr, acc, slow, 1 / rate)
    assert est.diagnostics["mag_skipped"] == int(no_field.sum())
    total, heading, _ = error_deg(q_est, q)
    assert heading[0] > 90.0  # started without a field: yaw 0 against a true 115°
    assert rms(total[t > 20]) < 1.0
    # and equal to the full-rate magnetometer within a fraction of a degree
    _, q_full = run_robust(gyr, acc, mag, 1 / rate)
    assert abs(rms(error_deg(q_full, q)[0][t > 20]) - rms(total[t > 20])) < 0.3


# ----------------------------------------------------------------------------- samples and paths


def test_bad_samples_are_skipped_and_counted():
    rate = 200.0
    t = np.arange(0, 40, 1 / rate)
    omega = wobble(t, 30.0)
    q = simulate(t, omega)
    gyr, acc, mag = sense(q, omega, seed=11)
    gyr[1000:1003] = np.nan
    acc[2000:2010] = 0.0
    acc[2010] = np.inf
    mag[3000:3020] = np.nan
    dt = np.full(len(t), 1 / rate)
    dt[4000] = -1.0  # a clock step backwards is not integrated
    est, q_est = run_robust(gyr, acc, mag, dt)
    d = est.diagnostics
    assert d["gyr_skipped"] == 4
    assert d["acc_skipped"] == 11
    assert d["mag_skipped"] == 20
    assert np.all(np.isfinite(q_est))
    assert np.allclose(np.linalg.norm(q_est, axis=1), 1.0)
    total, _, _ = error_deg(q_est, q)
    assert rms(total[t > 30]) < 0.65  # measured 0.213°; other seeds up to 0.315°


def test_per_sample_updates_equal_batch_bit_for_bit():
    rate = 285.714
    t = np.arange(0, 20, 1 / rate)
    omega = wobble(t, 80.0)
    q = simulate(t, omega)
    gyr, acc, mag = sense(q, omega, seed=12, hard_iron=np.array([10.0, 5.0, -8.0]))
    mag[::3] = np.nan
    batch = estimators.create("robust")
    out_batch = batch.run(gyr, acc, mag, dt=1 / rate)
    single = estimators.create("robust")
    rows = stack_rows(gyr, acc, mag, 1 / rate)
    out_rows = np.array([single.update_row(r).copy() for r in rows])
    assert np.array_equal(out_batch, out_rows)
    assert np.array_equal(batch.state, single.state)
    other = estimators.create("robust")
    out_update = np.array(
        [other.update(g, a, None if np.isnan(m[0]) else m, dt=1 / rate).copy() for g, a, m in zip(gyr, acc, mag)]
    )
    assert np.array_equal(out_batch, out_update)


def test_parameters_are_validated_and_registered():
    assert "robust" in estimators.names()
    with pytest.raises(ValueError):
        estimators.create("robust", not_a_parameter=1.0)
    with pytest.raises(ValueError):
        estimators.create("robust", tau_acc=0.0)
    est = estimators.create("robust")
    assert len(est.state) == R.STATE_SIZE
