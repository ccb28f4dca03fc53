"""Estimators of the first and third source papers: complementary (reduced, full), EKF, Valenti."""

import h5py
import numpy as np
import pytest
from analytic import FIELD_NED, constant_rotation, error_deg, measure, static

from ahrs_service import estimators
from ahrs_service.core.quaternion import (
    ned_to_enu_array,
    quat_conj_array,
    quat_from_euler_array,
    quat_mul_array,
)

RATE = 200.0
NINE_AXIS = ["complementary_full", "ekf", "valenti"]
ALL = ["complementary_reduced", *NINE_AXIS]
ATTITUDES = [
    (0.0, 0.0, 0.0),
    (0.5, -0.3, 2.0),
    (np.pi, 0.0, 0.0),  # upside down
    (2.5, 0.4, -3.0),  # upside down, yaw near ±180°
    (0.2, np.radians(89), 1.0),
    (-0.4, np.radians(-89), -2.5),
]


def _run(name, gyr, acc, mag, **params):
    return estimators.run(name, gyr, acc, mag if name != "complementary_reduced" else None, rate_hz=RATE, **params)


def _rms(a):
    return float(np.sqrt(np.mean(np.square(a))))


# ----------------------------------------------------------------------------- analytic


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("attitude", ATTITUDES)
def test_static_attitudes_held_from_first_sample(name, attitude):
    q, gyr, acc, mag = static(*attitude, n=400)
    est = _run(name, gyr, acc, mag)
    total, _, incl = error_deg(est, q)
    assert np.isfinite(est).all()
    assert np.allclose(np.linalg.norm(est, axis=1), 1.0)
    # perfect sensors at rest: every form starts on the truth and stays there
    if estimators.get(name).observes_heading:
        assert total.max() < 1e-3
    else:
        assert incl.max() < 1e-3


@pytest.mark.parametrize("name", ALL)
@pytest.mark.parametrize("axis", [0, 1, 2])
def test_constant_rate_about_each_axis(name, axis):
    omega = np.zeros(3)
    omega[axis] = 1.0  # rad/s; about y this passes pitch ±90° (gimbal lock of the Euler forms)
    q, gyr, acc, mag = constant_rotation(omega, RATE, 20.0, start=(0.1, 0.2, 0.3))
    est = _run(name, gyr, acc, mag)
    total, _, incl = error_deg(est, q)
    assert np.isfinite(est).all()
    # the complementary forms propagate exactly (the Euler change of the rotated estimate):
    # measured RMS 0.95e-6–1.24e-6°, the resolution of the acos in error_deg (steps of
    # ~1.7e-6° near 0); the quaternion filters to first order, corrected by their (small)
    # gains: measured ekf 3.9e-5–1.5e-4°, valenti 4.8e-4–8.5e-4° (over the three axes)
    bound = {"ekf": 5e-4, "valenti": 2.5e-3}.get(name, 4e-6)
    err = total if estimators.get(name).observes_heading else incl
    assert _rms(err) < bound


@pytest.mark.parametrize("name", ALL)
def test_fast_tumble_tracks(name):
    q, gyr, acc, mag = constant_rotation([3.0, -2.0, 4.0], RATE, 20.0, start=(0.1, 0.2, 0.3))
    est = _run(name, gyr, acc, mag)
    total, _, incl = error_deg(est, q)
    err = total if estimators.get(name).observes_heading else incl
    # 5.4 rad/s through gimbal lock many times; Valenti's small default gains leave the
    # first-order integration error of eq. 47 largest: 0.26° at the tuned α 0.0006 (0.14° at
    # the α 0.0023 tuned before the field gate and bias estimate; neither acts here)
    bound = {"ekf": 0.02, "valenti": 0.3}.get(name, 1e-3)
    assert np.isfinite(est).all()
    assert _rms(err) < bound


def test_complementary_yaw_crosses_180_without_jump():
    # level, turning at 0.5 rad/s about down from yaw 170°: yaw passes +180° → −180°
    q, gyr, acc, mag = constant_rotation([0.0, 0.0, 0.5], RATE, 4.0, start=(0.0, 0.0, np.radians(170)))
    for name in ["complementary_full", "complementary_reduced"]:
        est = _run(name, gyr, acc, mag)
        step = error_deg(est[1:], est[:-1])[0]
        # one sample turns 0.5 / 200 rad = 0.14°; no sample jumps
        assert step.max() < 0.2
        if name == "complementary_full":
            assert error_deg(est, q)[0].max() < 0.01


def test_complementary_full_declination_turns_heading():
    q, gyr, acc, mag = static(0.2, -0.1, 0.5, n=200)
    decl = np.radians(10.0)
    est = _run("complementary_full", gyr, acc, mag, declination=decl)
    # heading against true north = magnetic heading + declination (east positive)
    expected = quat_from_euler_array(np.array([[0.2, -0.1, 0.5 + decl]]))
    assert error_deg(est, np.repeat(expected, len(est), axis=0))[0].max() < 1e-3


def test_complementary_reduced_yaw_is_gyro_only():
    q, gyr, acc, mag = static(0.1, 0.1, 0.0, n=400)
    gyr[:, 2] = 0.1  # a yaw rate no sensor of the reduced form sees
    # without the rest bias estimate, which would take a constant rate at rest for a bias
    est = _run("complementary_reduced", gyr, acc, None, bias_rate=0.0)
    yaw = np.degrees(np.unwrap(2 * np.arctan2(est[:, 3], est[:, 0])))
    # 0.1 rad/s over 399 steps of 5 ms, with roll/pitch coupling ≈ 11.4°
    assert 10.0 < yaw[-1] - yaw[0] < 12.0


def test_ekf_estimates_constant_gyro_bias():
    bias = np.array([0.02, -0.015, 0.01])
    q, gyr, acc, mag = constant_rotation([0.2, -0.1, 0.3], RATE, 120.0, start=(0.1, 0.2, 0.3))
    est = estimators.create("ekf")
    out = est.run(gyr + bias, acc, mag, dt=1 / RATE)
    assert np.allclose(est.gyro_bias, bias, atol=1e-3)
    total, _, _ = error_deg(out[-2000:], q[-2000:])
    assert total.max() < 0.1


def test_valenti_magnetometer_cannot_tilt():
    # a magnet swings the field by 60° about north: inclination must stay untouched
    q, gyr, acc, _ = static(0.3, -0.2, 1.0, n=2000)
    disturbed = FIELD_NED + np.array([0.0, 40.0, -30.0])
    mag = measure(q, np.zeros((len(q), 3)))[2]
    mag[200:] = quat_rotate_body(q[200:], disturbed)
    for name, params in [("valenti", {"mag_gate": 1e9}), ("ekf", {"mag_gate": 1e9})]:
        est = _run(name, gyr, acc, mag, **params)
        _, heading, incl = error_deg(est, q)
        assert incl.max() < 1e-4, name  # acos resolution near 0 is ~2e-6°
        assert heading[-1] > 10.0, name  # the heading did follow the disturbed field


def test_ekf_gate_ignores_a_field_of_another_magnitude():
    q, gyr, acc, _ = static(0.3, -0.2, 1.0, n=2000)
    mag = measure(q, np.zeros((len(q), 3)))[2]
    mag[200:] = quat_rotate_body(q[200:], FIELD_NED + np.array([0.0, 40.0, -30.0]))
    est = _run("ekf", gyr, acc, mag)
    assert error_deg(est, q)[0].max() < 1e-3
    # the same disturbance through an open gate turns the heading (see the test above)
    assert error_deg(_run("ekf", gyr, acc, mag, mag_gate=1e9), q)[1][-1] > 10.0


def test_complementary_full_gate_ignores_a_field_of_another_magnitude():
    # the EKF's field gate (K.mag_gate_accepts), a named variant of the full form
    q, gyr, acc, _ = static(0.3, -0.2, 1.0, n=2000)
    mag = measure(q, np.zeros((len(q), 3)))[2]
    mag[200:] = quat_rotate_body(q[200:], FIELD_NED + np.array([0.0, 40.0, -30.0]))
    assert error_deg(_run("complementary_full", gyr, acc, mag, mag_gate=0.1), q)[0].max() < 1e-3
    # the paper's form (no gate) turns its heading to the disturbed field
    assert error_deg(_run("complementary_full", gyr, acc, mag, mag_gate=1e9), q)[1][-1] > 10.0


def test_acc_lowpass_passes_vibration_and_gates_sustained_acceleration():
    # K.acc_disturbance, the gate of complementary_*, kalman_roll_pitch, immersion_invariance:
    # |‖f̄‖/g − 1| with f̄ the specific force low-passed in a frame turned with the gyro
    from ahrs_service.estimators import SAMPLE_ROW
    from ahrs_service.estimators._kernel import acc_disturbance

    dt, n = 1.0 / RATE, 400
    t = np.arange(n) * dt
    q, _, acc, _ = constant_rotation([0.0, 0.0, 8.0], RATE, n / RATE, start=(0.4, -0.3, 0.0))
    rows = np.zeros((n, SAMPLE_ROW.end))
    rows[:, 2], rows[:, 3:6], rows[:, -1] = 8.0, acc, dt

    def last_dev(extra, tau):
        """The largest deviation over the last second."""
        s = np.zeros(3)
        rows[:, 3:6] = acc + extra
        return max([acc_disturbance(s, 0, r, tau) for r in rows][-int(RATE):])

    vibration = np.outer(np.sin(2 * np.pi * 50.0 * t), [0.0, 0.4, 3.0])  # 50 Hz, 0.3 g
    push = np.broadcast_to([2.0, 0.0, 0.0], (n, 3))  # a sustained 0.2 g, body x
    assert last_dev(0.0, 0.05) < 1e-9  # 8 rad/s turn: the gyro-turned low-pass keeps g
    # a first-order low-pass of 0.05 s leaves 1/16 of a 50 Hz vibration (measured 0.29, 0.015)
    assert last_dev(vibration, 0.0) > 0.25 and last_dev(vibration, 0.05) < 0.025
    assert last_dev(push, 0.0) > 0.05 and last_dev(push, 0.05) > 0.05  # measured 0.11, 0.10


def test_complementary_soft_gate_weights_the_gravity_angles():
    # acc_soft 1: a tilt seen by an accelerometer reading 1.2 g is followed, slowly (weight
    # 1/(1 + (0.2/acc_gate)²)); the hard gate ignores it; both follow it at exactly 1 g
    _, gyr, acc, _ = static(0.0, 0.0, 0.0, n=int(RATE))
    _, _, acc1, _ = static(np.radians(20), 0.0, 0.0, n=int(4 * RATE))
    gyr = np.zeros((5 * int(RATE), 3))
    rolls = {}
    for g in (1.0, 1.2):
        for soft in (0.0, 1.0):
            est = _run("complementary_reduced", gyr, np.vstack([acc, g * acc1]), None, omega0=1.0, acc_gate=0.1,
                       acc_lowpass=0.0, acc_soft=soft)
            rolls[g, soft] = np.degrees(2 * np.arctan2(est[-1, 1], est[-1, 0]))
    assert rolls[1.0, 0.0] == pytest.approx(20.0, abs=0.5) and rolls[1.0, 1.0] == pytest.approx(20.0, abs=0.5)
    assert abs(rolls[1.2, 0.0]) < 1e-9  # gated out
    assert 9.0 < rolls[1.2, 1.0] < 13.0  # weight 0.2: 1 − e^(−0.2·ω0·4 s) = 55 % of 20° (11.0° measured)
    with pytest.raises(ValueError, match="acc_soft must be 0"):
        estimators.create("complementary_full", acc_soft=0.5)


def quat_rotate_body(q, v_earth):
    from ahrs_service.core.quaternion import quat_rotate_array

    return quat_rotate_array(quat_conj_array(q), np.broadcast_to(v_earth, (len(q), 3)))


@pytest.mark.parametrize("name", ALL)
def test_bad_samples_skipped_and_counted(name):
    q, gyr, acc, mag = static(0.3, 0.2, 0.1, n=300)
    acc[100] = np.nan
    acc[101] = 0.0
    mag[150] = np.inf
    gyr[200] = np.nan
    est = estimators.create(name)
    out = est.run(gyr, acc, mag if est.uses_mag else None, dt=1 / RATE)
    assert np.isfinite(out).all()
    assert np.isfinite(est.state).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    d = est.diagnostics
    assert d["acc_skipped"] == 2
    assert d["gyr_skipped"] == 1
    assert d["mag_skipped"] == (1 if est.uses_mag else 0)
    total, _, incl = error_deg(out, q)
    assert (total if est.observes_heading else incl).max() < 1e-3


@pytest.mark.parametrize("name", ALL)
def test_starts_from_first_usable_sample(name):
    q, gyr, acc, mag = static(-0.6, 0.3, 2.0, n=50)
    acc[:5] = np.nan
    out = _run(name, gyr, acc, mag)
    assert np.allclose(out[:5], [1.0, 0.0, 0.0, 0.0])
    total, _, incl = error_deg(out[5:], q[5:])
    assert (total if estimators.get(name).observes_heading else incl).max() < 1e-3


@pytest.mark.parametrize("name", ALL)
def test_uses_real_time_step(name):
    # the same motion sampled at 100 Hz with every other step doubled must agree with 200 Hz
    q, gyr, acc, mag = constant_rotation([0.4, -0.3, 0.6], RATE, 5.0, start=(0.2, 0.1, 0.0))
    keep = np.sort(np.r_[np.arange(0, len(q), 2), np.arange(1, len(q), 4)])
    dt = np.diff(keep, prepend=-1) / RATE
    cls = estimators.get(name)
    est = estimators.create(name).run(gyr[keep], acc[keep], mag[keep] if cls.uses_mag else None, dt=dt)
    total, _, incl = error_deg(est, q[keep])
    # measured RMS: complementary 0.77e-6 / 0.81e-6° (acos resolution), ekf 1.75e-4°,
    # valenti 3.6e-4°; fed the nominal 5 ms instead of the real steps they are off by 16–34°
    bound = {"ekf": 5e-4, "valenti": 1.1e-3}.get(name, 3e-6)
    assert _rms(total if cls.observes_heading else incl) < bound


@pytest.mark.parametrize("name", ALL)
def test_pitch_89_and_upside_down_noisy_no_nan(name):
    rng = np.random.default_rng(7)
    for attitude in [(0.3, np.radians(89.9), 0.5), (np.pi, np.radians(-89.99), 0.0), (np.pi, 0.0, np.pi)]:
        q, gyr, acc, mag = static(*attitude, n=1000)
        gyr = gyr + rng.normal(0, 0.05, gyr.shape)
        acc = acc + rng.normal(0, 0.2, acc.shape)
        mag = mag + rng.normal(0, 0.5, mag.shape)
        est = _run(name, gyr, acc, mag)
        assert np.isfinite(est).all()
        assert np.allclose(np.linalg.norm(est, axis=1), 1.0)
        _, _, incl = error_deg(est, q)
        assert np.median(incl) < 3.0


def test_params_validated():
    with pytest.raises(ValueError, match="omega0"):
        estimators.create("complementary_full", omega0=0.0)
    with pytest.raises(ValueError, match="alpha"):
        estimators.create("valenti", alpha=1.5)
    with pytest.raises(ValueError, match="acc_noise"):
        estimators.create("ekf", acc_noise=0.0)
    with pytest.raises(ValueError, match="unknown parameter"):
        estimators.create("ekf", beta=0.1)


def test_declination_settable_live():
    est = estimators.create("complementary_full")
    est.set_params(declination=0.1)
    assert est.get_params()["declination"] == 0.1


# ----------------------------------------------------------------------------- BROAD

# RMSE (deg) at the values that were the defaults before the tuned presets (PRE_TUNING: the
# accuracy of today's defaults is tests/test_tuned_accuracy.py's) on two recordings, as
# measured plus about 10 % (measured: total / inclination)
PRE_TUNING = {
    "complementary_reduced": {"omega0": 0.2, "acc_gate": 0.1, "acc_lowpass": 0.0, "acc_soft": 0.0},
    "complementary_full": {"omega0": 0.2, "acc_gate": 0.1, "acc_lowpass": 0.0, "acc_soft": 0.0, "mag_gate": 1e9},
    "ekf": {"gyro_noise": 0.01, "bias_noise": 1e-5, "acc_noise": 0.2, "mag_noise": 0.3, "mag_gate": 0.1},
    "valenti": {"alpha": 0.002, "beta": 0.001, "adaptive_low": 0.1, "adaptive_high": 0.2},
}
BROAD_BOUNDS = {
    # inclination only: no magnetometer (measured 1.42, 2.90)
    "complementary_reduced": {"02": (None, 1.6), "07": (None, 3.2)},
    # measured 3.04 / 1.42 and 5.09 / 2.90
    "complementary_full": {"02": (3.4, 1.6), "07": (5.6, 3.2)},
    # measured 1.63 / 0.60 and 2.88 / 1.24
    "ekf": {"02": (1.8, 0.67), "07": (3.2, 1.4)},
    # measured 2.67 / 1.35 and 4.12 / 3.04
    "valenti": {"02": (3.0, 1.5), "07": (4.6, 3.4)},
}


def _broad_rmse(path, name):
    with h5py.File(path) as f:
        gyr, acc, mag = f["imu_gyr"][:], f["imu_acc"][:], f["imu_mag"][:]
        ref, movement = f["opt_quat"][:], f["movement"][:].astype(bool)
        rate = float(f.attrs["sampling_rate"])
    use_mag = estimators.get(name).uses_mag
    q = estimators.run(name, gyr, acc, mag if use_mag else None, rate_hz=rate, **PRE_TUNING[name])
    e = quat_mul_array(ned_to_enu_array(q), quat_conj_array(ref))
    total = np.degrees(2 * np.arccos(np.clip(np.abs(e[:, 0]), 0, 1)))
    incl = np.degrees(2 * np.arccos(np.clip(np.sqrt(e[:, 0] ** 2 + e[:, 3] ** 2), 0, 1)))

    def rmse(a):
        a = a[movement]
        return float(np.sqrt(np.mean(a[np.isfinite(a)] ** 2)))

    return rmse(total), rmse(incl)


@pytest.mark.parametrize("name", ALL)
def test_broad_accuracy(broad_dir, name):
    for trial, (max_total, max_incl) in BROAD_BOUNDS[name].items():
        (path,) = broad_dir.glob(f"{trial}_*.hdf5")
        total, incl = _broad_rmse(path, name)
        assert incl < max_incl, (trial, incl)
        if max_total is not None:
            assert total < max_total, (trial, total)
