"""Estimators of the second source paper: TRIAD, QUEST, Kalman roll/pitch, quaternion KF,
Mahony direct/passive, immersion and invariance (eq. 15–37)."""

import dataclasses
import math

import h5py
import numpy as np
import pytest
from analytic import FIELD_NED, constant_rotation, error_deg, measure, static

from ahrs_service import estimators
from ahrs_service.core.quaternion import (
    ned_to_enu_array,
    quat_conj_array,
    quat_from_euler,
    quat_from_euler_array,
    quat_from_rotvec_array,
    quat_mul_array,
    quat_rotate_inv,
)
from ahrs_service.estimators.quest import quest_quat
from ahrs_service.estimators.triad import triad_quat


def _paper(name: str) -> str | None:
    """The paper's values (the convergence and bias properties below are the paper's filters'
    at its gains; the tuned defaults are slower by design): None for TRIAD and QUEST."""
    return None if name in ("triad", "quest") else "paper"

RATE = 200.0
MAG = ["triad", "quest", "quaternion_kf", "mahony_direct", "mahony_passive"]
IMU = ["kalman_roll_pitch", "immersion_invariance"]
ALL = MAG + IMU
ATTITUDES = [
    (0.0, 0.0, 0.0),
    (0.5, -0.3, 2.0),
    (math.pi, 0.0, 0.0),  # upside down
    (math.pi, 0.3, -2.0),
    (0.2, math.radians(89), 1.0),
    (-0.4, math.radians(-89), -2.5),
]


def jittered_rotation(omega, seconds, start, seed=1):
    """Constant body rate sampled with a jittering time step (±40 %): (q, gyr, acc, mag, dt)."""
    rng = np.random.default_rng(seed)
    dt = (1.0 / RATE) * (1.0 + 0.4 * rng.uniform(-1, 1, int(seconds * RATE)))
    t = np.cumsum(dt) - dt[0]
    q = quat_mul_array(quat_from_euler_array(np.array([start])), quat_from_rotvec_array(t[:, None] * np.asarray(omega)))
    gyr, acc, mag = measure(q, np.broadcast_to(np.asarray(omega, float), (len(t), 3)))
    return q, gyr, acc, mag, dt


# ----------------------------------------------------------------------------- analytic accuracy


@pytest.mark.parametrize("name", MAG)
@pytest.mark.parametrize("attitude", ATTITUDES)
def test_static_attitude_exact_with_magnetometer(name, attitude):
    q, gyr, acc, mag = static(*attitude, n=400)
    est = estimators.run(name, gyr, acc, mag, rate_hz=RATE)
    total, _, _ = error_deg(est, q)
    assert np.isfinite(est).all()
    assert total.max() < 1e-4


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("attitude", ATTITUDES)
def test_static_inclination_exact_without_magnetometer(name, attitude):
    q, gyr, acc, _ = static(*attitude, n=400)
    est = estimators.run(name, gyr, acc, None, rate_hz=RATE)
    _, _, incl = error_deg(est, q)
    assert np.isfinite(est).all()
    assert np.allclose(np.linalg.norm(est, axis=1), 1.0, atol=1e-12)
    assert incl.max() < 1e-4


@pytest.mark.parametrize("name", MAG)
@pytest.mark.parametrize("omega", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.3, -0.5, 1.0]])
def test_constant_rotation_with_magnetometer(name, omega):
    q, gyr, acc, mag = constant_rotation(omega, RATE, 20.0, start=(0.1, 0.2, 0.3))
    # the KF at the paper's σ's, which this bound was set for (its tuned σ_ξ trusts QUEST 6×
    # less, so the first-order prediction error below builds up to about 1.1e-3°)
    preset = "paper" if name == "quaternion_kf" else None
    est = estimators.run(name, gyr, acc, mag, rate_hz=RATE, preset=preset)
    total, _, _ = error_deg(est, q)
    # algebraic fixes are exact; the KF's prediction A = I + (h/2)Ω is first order, and its
    # renormalised error stays below 2e-4°
    assert total.max() < 1e-3


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("omega", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.3, -0.5, 1.0]])
def test_constant_rotation_without_magnetometer_yaw_from_gyro(name, omega):
    # start yaw 0 is what every estimator assumes without a field, so the total error is
    # what the gyro integration (yaw) and the gravity correction (roll, pitch) leave
    q, gyr, acc, _ = constant_rotation(omega, RATE, 20.0, start=(0.1, 0.2, 0.0))
    est = estimators.run(name, gyr, acc, None, rate_hz=RATE, preset=_paper(name))
    total, _, incl = error_deg(est, q)
    if name == "kalman_roll_pitch":
        # Euler angles integrated with first-order steps (eq. 27–28 with eq. 7's rates): the
        # pitch turn passes 84°, where the yaw and roll rates grow as 1/cos θ; measured
        # 0.35° inclination and 4.1° total there, under 0.2° on the other turns
        big = omega == [0, 1.0, 0]
        assert incl.max() < (0.4 if big else 0.15)
        assert total.max() < (4.5 if big else 0.2)
    elif name == "quaternion_kf":
        # A = I + (h/2)Ω is a first-order step: yaw, which nothing corrects here, drifts by
        # 0.003° in 20 s (measured)
        assert incl.max() < 1e-3
        assert total.max() < 0.005
    else:
        assert incl.max() < 1e-3
        assert total.max() < 1e-3


@pytest.mark.parametrize("name", ALL)
def test_jittering_time_steps(name):
    q, gyr, acc, mag, dt = jittered_rotation([0.4, -0.7, 0.9], 10.0, (0.3, -0.2, 0.0))
    est = estimators.create(name, preset=_paper(name)).run(gyr, acc, mag, dt=dt)
    total, _, incl = error_deg(est, q)
    # measured: 0.24° for the Euler-angle Kalman filter (first-order steps of up to 7 ms),
    # 2.5e-4° for the quaternion KF, float rounding for the others
    bound = 0.3 if name == "kalman_roll_pitch" else 1e-3
    assert (total if name in MAG else incl).max() < bound


@pytest.mark.parametrize("name", ["mahony_direct", "mahony_passive"])
@pytest.mark.parametrize("gains", [{}, {"kp": 1.0, "ki": 0.3}])
def test_mahony_estimates_constant_gyro_bias(name, gains):
    bias = np.array([0.02, -0.03, 0.015])
    q, gyr, acc, mag = constant_rotation([0.3, -0.2, 0.5], RATE, 60.0, start=(0.2, 0.1, -0.4))
    est = estimators.create(name, preset="paper", **gains)
    out = est.run(gyr + bias, acc, mag, dt=1 / RATE)
    assert np.abs(est.gyro_bias - bias).max() < 1e-4
    # the paper's gains (kp 25, ki 10) converge within seconds, kp 1 / ki 0.3 within a minute
    total, _, _ = error_deg(out[-int(RATE) :], q[-int(RATE) :])
    assert total.max() < (1e-4 if not gains else 0.01)  # measured 3e-6° and 0.009°


@pytest.mark.parametrize("name", ["mahony_direct", "mahony_passive"])
def test_mahony_imu_form_estimates_bias_across_gravity(name):
    # without a field the heading is unobservable, but the bias on the horizontal axes is not
    bias = np.array([0.02, -0.03, 0.01])
    q, gyr, acc, _ = static(0.2, -0.1, 0.0, n=int(60 * RATE))
    est = estimators.create(name, preset="paper", kp=1.0, ki=0.3)
    out = est.run(gyr + bias, acc, None, dt=1 / RATE)
    # only the bias about the gravity axis stays unobserved: compare the part across it
    down = quat_rotate_inv(q[0], (0.0, 0.0, 1.0))
    err = est.gyro_bias - bias
    assert np.abs(err - np.dot(err, down) * np.asarray(down)).max() < 1e-5
    assert abs(np.dot(err, down)) > 1e-3  # and the unobserved part was indeed not learned
    assert error_deg(out[-100:], q[-100:])[2].max() < 0.01


@pytest.mark.parametrize("name", ALL)
def test_converges_from_wrong_attitude(name):
    q, gyr, acc, mag = constant_rotation([0.2, 0.3, -0.4], RATE, 30.0, start=(0.3, 0.2, 0.0))
    m = mag if name in MAG else None
    est = estimators.create(name, preset=_paper(name))
    est.update(gyr[0], acc[0], None if m is None else m[0], dt=1 / RATE)
    est.state[:4] = quat_from_euler(0.3 + 0.5, 0.2 - 0.4, 0.0)  # 30° off in roll and pitch
    if name == "kalman_roll_pitch":
        est.state[11:14] = (0.8, -0.2, 0.0)
    if name == "immersion_invariance":
        est.state[11:14] = quat_rotate_inv(quat_from_euler(0.8, -0.2, 0.0), (0.0, 0.0, 1.0))
    out = est.run(gyr[1:], acc[1:], None if m is None else m[1:], dt=1 / RATE)
    _, _, incl = error_deg(out[-200:], q[1:][-200:])
    assert incl.max() < 0.05


# ----------------------------------------------------------------------------- QUEST solver


@pytest.mark.parametrize("attitude", ATTITUDES + [(math.pi, 0.0, math.pi), (0.0, math.pi - 1e-9, 0.0)])
def test_quest_solver_equals_triad_for_consistent_vectors(attitude):
    # near 180° from identity (upside down, turned) the sequential rotations keep it exact
    q = quat_from_euler(*attitude)
    d = quat_rotate_inv(q, (0.0, 0.0, 1.0))
    dip = math.atan2(FIELD_NED[2], FIELD_NED[0])
    rm = (math.cos(dip), 0.0, math.sin(dip))
    m = quat_rotate_inv(q, (3 * rm[0], 0.0, 3 * rm[2]))
    qq, ok = quest_quat(d, m, rm, 2.0, 2.0)
    qt, ok_t = triad_quat(d, m[0], m[1], m[2])
    assert ok and ok_t
    assert abs(abs(np.dot(qq, q)) - 1.0) < 1e-12
    assert abs(abs(np.dot(qt, q)) - 1.0) < 1e-12


def test_quest_weights_share_the_misfit():
    # field reference 10° off the measured one: the heavier vector is matched more closely
    q = quat_from_euler(0.3, -0.2, 1.0)
    d = quat_rotate_inv(q, (0.0, 0.0, 1.0))
    dip = math.radians(60)
    m = quat_rotate_inv(q, (math.cos(dip), 0.0, math.sin(dip)))
    rm = (math.cos(dip + math.radians(10)), 0.0, math.sin(dip + math.radians(10)))
    tilt = []
    for w_acc, w_mag in [(1.0, 1.0), (100.0, 1.0), (1.0, 100.0)]:
        qq, _ = quest_quat(d, m, rm, w_acc, w_mag)
        down = quat_rotate_inv(qq, (0.0, 0.0, 1.0))
        tilt.append(math.degrees(math.acos(min(1.0, np.dot(down, d)))))
    # equal weights: the 10° misfit is split evenly; ρ ratio 100: the heavier one keeps ~0.1°
    assert tilt[0] == pytest.approx(5.0, abs=1e-6)
    assert tilt[1] < 0.11
    assert tilt[2] > 9.89


def test_quaternion_kf_output_has_no_sign_flips():
    # 20 s at 1 rad/s passes 180° three times: QUEST's ±q must be resolved against the prediction
    q, gyr, acc, mag = constant_rotation([0.0, 0.0, 1.0], RATE, 20.0)
    est = estimators.run("quaternion_kf", gyr, acc, mag, rate_hz=RATE)
    assert (np.sum(est[1:] * est[:-1], axis=1) > 0.99).all()


def test_kalman_roll_pitch_gain_follows_sigma_ratio():
    # a tilt seen by the accelerometer only (gyro silent) is followed faster when the gyro is
    # trusted less: 1 s after a 20° step, the larger σ_ζ/σ_ξ has closed more of the gap
    q0, gyr, acc, _ = static(0.0, 0.0, 0.0, n=int(RATE))
    _, _, acc1, _ = static(math.radians(20), 0.0, 0.0, n=int(RATE))
    acc_all = np.vstack([acc, acc1])
    gyr_all = np.zeros_like(acc_all)
    rolls = []
    for sz in (1.0, 5.0, 25.0):
        est = estimators.run("kalman_roll_pitch", gyr_all, acc_all, rate_hz=RATE, sigma_zeta=sz)
        rolls.append(math.degrees(2 * math.atan2(est[-1, 1], est[-1, 0])))
    assert 0.0 < rolls[0] < rolls[1] < rolls[2] < 20.0 + 1e-9
    assert rolls[2] > 19.0


@pytest.mark.parametrize("omega", [[6.0, -4.0, 8.0], [0.5, 9.0, 0.3]])
def test_kalman_roll_pitch_gyro_step_is_exact_in_fast_turns(omega):
    # A fast tumble (BROAD's fast-rotation trials reach 25 rad/s) through pitch ±90° with the
    # accelerometer gated out (|f| = 1.5 g): the gyro alone carries roll and pitch. The default
    # step takes the Euler angles of the attitude turned by h ω (exact_step 1) and keeps it to
    # rounding; the first-order step x + h·B(Θ)ω (exact_step 0, preset "paper") loses it
    # (measured 67° and 19° here; on BROAD's fast-rotation trial, gyro alone: 82° inclination
    # RMSE against 17°).
    rate = 285.7
    q, gyr, acc, _ = constant_rotation(omega, rate, 10.0, start=(0.1, 0.2, 0.0))  # yaw 0: no field
    exact = estimators.run("kalman_roll_pitch", gyr, 1.5 * acc, None, rate_hz=rate)
    first = estimators.run("kalman_roll_pitch", gyr, 1.5 * acc, None, rate_hz=rate, exact_step=0.0)
    assert error_deg(exact, q)[0].max() < 1e-4  # measured 3e-6°
    assert error_deg(first, q)[2].max() > 10.0


# ----------------------------------------------------------------------------- robustness


@pytest.mark.parametrize("name", ALL)
def test_bad_samples_skipped_and_counted(name):
    q, gyr, acc, mag = static(0.3, 0.2, 0.1, n=300)
    acc[100] = np.nan
    acc[101] = 0.0
    mag[150] = np.inf
    gyr[200] = np.nan
    est = estimators.create(name)
    dt = np.full(300, 1 / RATE)
    dt[250] = -1.0
    out = est.run(gyr, acc, mag, dt=dt)
    assert np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-12)
    assert est.diagnostics["acc_skipped"] == 2
    assert est.diagnostics["gyr_skipped"] == 2
    if name in MAG:
        assert est.diagnostics["mag_skipped"] == 1
        assert error_deg(out, q)[0].max() < 1e-4
    else:
        assert error_deg(out, q)[2].max() < 1e-4


@pytest.mark.parametrize("name", ALL)
def test_no_nan_from_garbage_and_gimbal_lock(name):
    rng = np.random.default_rng(3)
    n = 2000
    gyr = rng.normal(0, 3.0, (n, 3))
    acc = rng.normal(0, 9.81, (n, 3))
    mag = rng.normal(0, 40.0, (n, 3))
    acc[::7] = 0.0
    mag[::5] = 3.0 * acc[::5]  # field parallel to gravity
    dt = rng.uniform(1e-5, 0.2, n)
    out = estimators.create(name).run(gyr, acc, mag, dt=dt)
    assert np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-9)


def test_parameter_values_are_checked():
    with pytest.raises(ValueError, match="w_acc"):
        estimators.create("quest", w_acc=0.0)
    with pytest.raises(ValueError, match="sigma_xi"):
        estimators.create("kalman_roll_pitch", sigma_xi=0.0)
    with pytest.raises(ValueError, match="gamma2"):
        estimators.create("immersion_invariance", gamma2=-1.0)
    with pytest.raises(ValueError, match="ki"):
        estimators.create("mahony_passive", ki=-1.0)
    with pytest.raises(ValueError, match="exact_step must be 0"):
        estimators.create("kalman_roll_pitch", exact_step=0.5)
    with pytest.raises(ValueError, match="acc_lowpass"):
        estimators.create("immersion_invariance", acc_lowpass=-0.1)
    # a form, not a gain: never tuned
    field = {f.name: f for f in dataclasses.fields(estimators.get("kalman_roll_pitch").Params)}["exact_step"]
    assert "search" not in field.metadata


# ----------------------------------------------------------------------------- BROAD


def _broad_rmse(path, name, **params):
    with h5py.File(path) as f:
        gyr, acc, mag = f["imu_gyr"][()], f["imu_acc"][()], f["imu_mag"][()]
        ref, moving, rate = f["opt_quat"][()], f["movement"][()].astype(bool), f.attrs["sampling_rate"]
    use_mag = estimators.get(name).uses_mag
    q = ned_to_enu_array(estimators.run(name, gyr, acc, mag if use_mag else None, rate_hz=rate, **params))
    e = quat_mul_array(q, quat_conj_array(ref))
    total = 2 * np.arccos(np.clip(np.abs(e[:, 0]), 0, 1))
    incl = 2 * np.arccos(np.clip(np.sqrt(e[:, 0] ** 2 + e[:, 3] ** 2), 0, 1))
    rmse = lambda x: math.degrees(math.sqrt(np.nanmean(x[moving] ** 2)))  # noqa: E731
    return rmse(total), rmse(incl)


# measured RMSE (°) with the paper's values (preset "paper"; the defaults until the tuned
# presets, whose accuracy tests/test_tuned_accuracy.py checks) on trial 02 (slow rotation) and 24 (tapping):
# total for estimators with a magnetometer, inclination for the others; bound = measured + ~10 %
BROAD_BOUNDS = {
    "triad": {"02": 9.8, "24": 23.3},  # measured 8.92, 21.19
    "quest": {"02": 9.5, "24": 22.4},  # 8.62, 20.39
    "kalman_roll_pitch": {"02": 0.8, "24": 1.9},  # 0.70, 1.74
    "quaternion_kf": {"02": 2.35, "24": 4.0},  # 2.11, 3.61
    "mahony_direct": {"02": 3.6, "24": 6.7},  # 3.27, 6.09
    "mahony_passive": {"02": 3.6, "24": 6.6},  # 3.23, 6.00
    "immersion_invariance": {"02": 0.82, "24": 1.45},  # 0.74, 1.29
}


@pytest.mark.parametrize("name", ALL)
def test_broad_accuracy(broad_dir, name):
    for trial, bound in BROAD_BOUNDS[name].items():
        path = next(broad_dir.glob(f"{trial}_*.hdf5"))
        total, incl = _broad_rmse(path, name, preset=_paper(name))
        assert (total if name in MAG else incl) < bound, (name, trial, total, incl)
