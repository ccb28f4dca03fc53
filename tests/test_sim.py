"""The motion simulator, the sensor error models and the simulated source."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from analytic import error_deg

from ahrs_service import estimators
from ahrs_service.core.calibration import apply_calibration
from ahrs_service.core.quaternion import (
    quat_angle_array,
    quat_conj,
    quat_conj_array,
    quat_from_euler_array,
    quat_integrate,
    quat_mul,
    quat_rotate_array,
)
from ahrs_service.core.samples import ACC_SATURATED, ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID
from ahrs_service.drivers.sim.clock import ManualClock, MonotonicClock
from ahrs_service.drivers.sim.imu import SimulatedImu
from ahrs_service.drivers.sim.motion import (
    FigureEight,
    FunctionTrajectory,
    StaticTrajectory,
    ValidationManoeuvre,
    WaypointTrajectory,
    profile,
)
from ahrs_service.drivers.sim.sensor_model import (
    PART_MODELS,
    SensorErrorModel,
    board_models,
    part_model,
)
from ahrs_service.drivers.sim.source import SimulatedSource

G_EARTH = np.array([0.0, 0.0, 9.81])


def _angle(q1, q2) -> float:
    """Angle (rad) of the rotation between two attitudes."""
    e = quat_mul(quat_conj(tuple(q1)), tuple(q2))
    return 2.0 * math.acos(min(1.0, abs(e[0])))


def _waypoints() -> WaypointTrajectory:
    return WaypointTrajectory(
        [0.0, 2.0, 5.0, 6.0],
        np.radians([[0, 0, 0], [30, -20, 90], [-10, 45, -170], [0, 0, 10]]),
        [[0, 0, 0], [5, 2, -1], [10, -3, -4], [10, -3, -4]],
    )


def _attitude_fn(t: float):
    return quat_from_euler_array(np.array([0.4 * math.sin(t), 0.3 * math.cos(0.7 * t), 0.5 * t]))


TRAJECTORIES = {
    "validation": (lambda: ValidationManoeuvre(hold=0.5, move=0.8), None),
    "figure8": (lambda: FigureEight(period=8.0), 8.0),
    "waypoints": (_waypoints, None),
    "function": (lambda: FunctionTrajectory(_attitude_fn, lambda t: [t * t, math.sin(t), 0.0]), 6.0),
}


# --------------------------------------------------------------------------- motion


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_integrated_rate_reproduces_attitude(name):
    make, span = TRAJECTORIES[name]
    tr = make()
    span = span or tr.duration
    dt = 2e-3
    q = tuple(tr.state(0.0).q)
    worst = 0.0
    n = int(round(span / dt))
    for i in range(n):
        # midpoint rate: second-order accurate, so the drift left is O(dt²)
        q = quat_integrate(q, *tr.state((i + 0.5) * dt).omega_body, dt)
        if i % 50 == 49:
            worst = max(worst, _angle(q, tr.state((i + 1) * dt).q))
    # the midpoint rule leaves ≈ dt²/24·|ω̈|·T (a few 1e-6 rad here); a rate that is not the
    # derivative of q(t) drifts by orders of magnitude more
    assert worst < 1e-5


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_specific_force_is_second_derivative_of_position(name):
    make, span = TRAJECTORIES[name]
    tr = make()
    span = span or tr.duration
    h = 1e-3
    rng = np.random.default_rng(3)
    for t in rng.uniform(2 * h, span - 2 * h, 40):
        p = [tr.state(t + k * h).position for k in (-1, 0, 1)]
        a_num = (p[0] - 2 * p[1] + p[2]) / h**2
        s = tr.state(t)
        # a = R f + g: what an accelerometer at rest would not see is the kinematic acceleration
        a_from_f = quat_rotate_array(s.q, s.specific_force_body) + G_EARTH
        np.testing.assert_allclose(a_from_f, a_num, atol=2e-4)
        v_num = (p[2] - p[0]) / (2 * h)
        np.testing.assert_allclose(s.velocity, v_num, atol=1e-4)
        np.testing.assert_allclose(s.mag_body, quat_rotate_array(quat_conj_array(s.q), [20.0, 0.0, 45.0]), atol=1e-12)


def test_level_at_rest_reads_minus_g():
    s = StaticTrajectory().state(5.0)
    np.testing.assert_allclose(s.specific_force_body, [0.0, 0.0, -9.81], atol=1e-12)
    np.testing.assert_allclose(s.mag_body, [20.0, 0.0, 45.0], atol=1e-12)
    np.testing.assert_array_equal(s.omega_body, 0.0)
    s = StaticTrajectory(roll=math.pi / 2).state(0.0)  # right wing down: gravity along +y body
    np.testing.assert_allclose(s.specific_force_body, [0.0, -9.81, 0.0], atol=1e-12)


def test_configurable_field_and_gravity():
    s = StaticTrajectory(field_ned=(30.0, -5.0, 10.0), gravity=9.7).state(0.0)
    np.testing.assert_allclose(s.mag_body, [30.0, -5.0, 10.0])
    np.testing.assert_allclose(s.specific_force_body, [0.0, 0.0, -9.7])


def test_validation_reaches_plus_and_minus_90_about_each_axis():
    tr = ValidationManoeuvre()
    assert [p[0] for p in tr.phases] == ["x+90", "x-90", "x0", "y+90", "y-90", "y0", "z+90", "z-90", "z0"]
    for label, t0, t1 in tr.phases:
        axis = np.eye(3)["xyz".index(label[0])]
        target = 0.0 if label[1:] == "0" else float(label[1:])
        for t in np.linspace(t0, t1, 5):
            s = tr.state(t)
            # the attitude is a pure rotation about the axis, by the target angle
            angle = math.degrees(2 * math.atan2(s.q[1:] @ axis, s.q[0]))
            assert angle == pytest.approx(target, abs=1e-9)
            assert np.allclose(s.omega_body, 0.0)
    # no overshoot beyond ±90° during the moves (minimum-jerk profile is monotone)
    qs = np.array([tr.state(t).q for t in np.linspace(0, tr.duration, 4001)])
    assert quat_angle_array(qs).max() <= math.radians(90) + 1e-9
    assert tr.duration == pytest.approx(2 + 3 * (4 * 2 + 3 * 2))


def test_validation_loops_and_rests_after_end():
    once = ValidationManoeuvre(hold=0.5, move=0.5)
    loop = ValidationManoeuvre(hold=0.5, move=0.5, looping=True)
    d = once.duration
    for t in (0.3, 1.1, 4.7):
        np.testing.assert_allclose(loop.state(t + 2 * d).q, once.state(t).q, atol=1e-12)
    end = once.state(d + 10.0)
    np.testing.assert_allclose(end.q, [1, 0, 0, 0], atol=1e-12)
    np.testing.assert_array_equal(end.omega_body, 0.0)


def test_figure_eight_has_linear_acceleration_and_banked_turns():
    tr = FigureEight()
    states = [tr.state(t) for t in np.linspace(0.0, tr.period, 801)]
    acc = np.array([s.acceleration for s in states])
    speed = np.linalg.norm([s.velocity for s in states], axis=1)
    f = np.array([s.specific_force_body for s in states])
    roll = np.degrees([math.atan2(2 * (s.q[0] * s.q[1] + s.q[2] * s.q[3]), 1 - 2 * (s.q[1] ** 2 + s.q[2] ** 2)) for s in states])
    assert np.linalg.norm(acc, axis=1).max() > 3.0  # m/s²: the accelerometer sees more than gravity
    assert np.ptp(np.linalg.norm(f, axis=1)) > 1.0
    assert speed.max() - speed.min() > 3.0  # the speed changes along the path
    assert roll.max() > 20.0 and roll.min() < -20.0  # banked both ways
    # coordinated: the lateral specific force stays small against the banked one
    assert np.abs(f[:, 1]).max() < 0.02 * np.linalg.norm(f, axis=1).min()
    # periodic
    np.testing.assert_allclose(tr.state(3.0).q, tr.state(3.0 + tr.period).q, atol=1e-9)
    assert math.isinf(tr.duration) and FigureEight(laps=2).duration == pytest.approx(2 * tr.period)


def test_waypoints_pass_through_keyframes_at_rest():
    tr = _waypoints()
    expected = quat_from_euler_array(np.radians([[30, -20, 90], [-10, 45, -170]]))
    for t, q, p in zip((2.0, 5.0), expected, ([5, 2, -1], [10, -3, -4])):
        s = tr.state(t)
        assert _angle(s.q, q) < 1e-9
        np.testing.assert_allclose(s.position, p, atol=1e-12)
        np.testing.assert_allclose(s.omega_body, 0.0, atol=1e-12)
        np.testing.assert_allclose(s.acceleration, 0.0, atol=1e-12)


def test_waypoints_from_config_keyframes():
    tr = profile("waypoints", keyframes=[{"t": 0, "rpy_deg": [0, 0, 0]}, {"t": 3, "rpy_deg": [0, 0, 90], "position": [1, 2, 3]}])
    s = tr.state(3.0)
    np.testing.assert_allclose(s.q, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)], atol=1e-12)
    with pytest.raises(ValueError, match="rpy"):
        profile("waypoints", keyframes=[{"t": 0, "rpy": [0, 0, 0]}])


def test_profile_names_and_errors():
    assert isinstance(profile("static", roll=0.1), StaticTrajectory)
    assert isinstance(profile("validation", hold=1.0), ValidationManoeuvre)
    assert isinstance(profile("figure8", looping=True), FigureEight)
    with pytest.raises(ValueError, match="static, validation, figure8"):
        profile("circle")
    with pytest.raises(ValueError, match="periode"):
        profile("figure8", periode=3.0)
    with pytest.raises(ValueError, match="t must be"):
        StaticTrajectory().state(-1.0)


# --------------------------------------------------------------------------- error models


def _readings(model: SensorErrorModel, true, n: int, rate_hz: float, **kw) -> np.ndarray:
    return np.array([model.apply(true, 1.0 / rate_hz, **kw) for _ in range(n)])


def test_noise_std_matches_density_times_sqrt_half_rate():
    rate, density, n = 200.0, 0.01, 20000
    x = _readings(SensorErrorModel(noise_density=density, seed=5), np.zeros(3), n, rate)
    expected = density * math.sqrt(rate / 2)
    # the sample std of n normal draws has a relative std of 1/√(2n) = 0.5 %: 3 % is six of them
    np.testing.assert_allclose(x.std(axis=0), expected, rtol=0.03)
    assert np.abs(x.mean(axis=0)).max() < 5 * expected / math.sqrt(n)
    # a fixed bandwidth overrides the sampling rate
    y = _readings(SensorErrorModel(noise_density=density, bandwidth_hz=20.0, seed=5), np.zeros(3), n, rate)
    np.testing.assert_allclose(y.std(axis=0), density * math.sqrt(20.0), rtol=0.03)


def test_constant_and_turn_on_bias():
    m = SensorErrorModel(bias=[0.1, -0.2, 0.3])
    np.testing.assert_allclose(m.apply([1.0, 2.0, 3.0], 0.01), [1.1, 1.8, 3.3])
    # turn-on biases over many seeds have the configured spread, and a seed fixes them
    draws = np.array([SensorErrorModel(bias_sigma=0.5, seed=s).turn_on_bias for s in range(600)])
    assert draws.std() == pytest.approx(0.5, rel=0.1)  # 1800 draws: 1.7 % relative std
    np.testing.assert_array_equal(SensorErrorModel(bias_sigma=0.5, seed=7).turn_on_bias, draws[7])


def test_bias_random_walk_variance_grows_linearly():
    rw, dt, steps = 0.02, 0.01, 100
    finals = []
    for seed in range(300):
        m = SensorErrorModel(bias_random_walk=rw, seed=seed)
        x = _readings(m, np.zeros(3), steps, 1 / dt)
        finals.append(x[-1])
    # after T = steps·dt the drift has variance rw²·T; 900 draws: ±5 % std of the variance
    assert np.var(finals) == pytest.approx(rw**2 * steps * dt, rel=0.2)


def test_saturation_clips_and_flags():
    m = SensorErrorModel(range=2.0)
    np.testing.assert_array_equal(m.apply([1.0, -1.5, 0.0], 0.01), [1.0, -1.5, 0.0])
    assert not m.saturated
    np.testing.assert_array_equal(m.apply([3.0, -2.5, 0.5], 0.01), [2.0, -2.0, 0.5])
    assert m.saturated


def test_quantisation_steps():
    step = 0.05
    m = SensorErrorModel(quantisation=step, noise_density=0.3, seed=2)
    true = np.array([0.123, -0.456, 9.81])
    x = _readings(m, true, 500, 100.0)
    np.testing.assert_allclose(x / step, np.round(x / step), atol=1e-9)
    exact = SensorErrorModel(quantisation=step).apply(true, 0.01)
    np.testing.assert_allclose(exact, [0.1, -0.45, 9.8])
    assert np.abs(exact - true).max() <= step / 2


def test_hard_and_soft_iron_scale_and_misalignment():
    soft = np.array([[1.1, 0.05, 0.0], [0.05, 0.9, 0.02], [0.0, 0.02, 1.05]])
    hard = np.array([12.0, -7.0, 30.0])
    m = SensorErrorModel(hard_iron=hard, soft_iron=soft)
    true = np.array([20.0, 3.0, 45.0])
    np.testing.assert_allclose(m.apply(true, 0.01), soft @ true + hard)
    mis = np.array([[0.0, 0.01, -0.02], [0.003, 0.0, 0.01], [0.0, -0.01, 0.0]])
    m = SensorErrorModel(scale_factor=[1.02, 0.97, 1.0], misalignment=mis)
    np.testing.assert_allclose(m.apply(true, 0.01), (np.eye(3) + mis) @ np.diag([1.02, 0.97, 1.0]) @ true)


def test_temperature_coefficient():
    m = SensorErrorModel(temp_coeff=[0.01, 0.0, -0.02], reference_temp_c=25.0)
    np.testing.assert_allclose(m.apply(np.zeros(3), 0.01, temperature_c=35.0), [0.1, 0.0, -0.2])
    np.testing.assert_allclose(m.apply(np.zeros(3), 0.01, temperature_c=25.0), 0.0)


def test_models_are_deterministic_given_seed():
    a = _readings(part_model("L3GD20", seed=4), [0.1, 0.2, 0.3], 50, 100.0)
    b = _readings(part_model("L3GD20", seed=4), [0.1, 0.2, 0.3], 50, 100.0)
    c = _readings(part_model("L3GD20", seed=5), [0.1, 0.2, 0.3], 50, 100.0)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_part_presets_present_and_copied():
    for name in ("L3G4200D", "ADXL345", "HMC5883L", "L3GD20", "LSM303DLHC_ACC", "LSM303DLHC_MAG",
                 "MPU9250_GYRO", "MPU9250_ACC", "AK8963", "ideal"):
        assert name in PART_MODELS
    # datasheet figures: L3GD20 0.03 dps/√Hz, ±250 dps; HMC5883L 1090 LSB/gauss
    assert PART_MODELS["L3GD20"].noise_density == pytest.approx(math.radians(0.03))
    assert PART_MODELS["L3GD20"].range == pytest.approx(math.radians(250))
    assert PART_MODELS["HMC5883L"].quantisation == pytest.approx(100 / 1090)
    m = part_model("MPU9250_ACC", seed=1)
    m.apply(np.zeros(3), 0.01)
    assert m is not PART_MODELS["MPU9250_ACC"]
    with pytest.raises(ValueError, match="BMI088"):
        part_model("BMI088")
    with pytest.raises(ValueError, match="bias"):
        SensorErrorModel(bias=[1.0, 2.0])


# --------------------------------------------------------------------------- imu, clocks, source


def test_physics_same_t_same_values_and_fresh_noise_per_t():
    imu = SimulatedImu(StaticTrajectory(), board_models("GY-80"), clock=ManualClock(), seed=3)
    a = imu.physics(0.5)
    b = imu.physics(0.5)
    assert a is b
    c = imu.physics(0.51)
    assert not np.array_equal(a["gyr"], c["gyr"])
    assert set(a) >= {"gyr", "acc", "mag", "temperature_c", "truth"}
    again = SimulatedImu(StaticTrajectory(), board_models("GY-80"), clock=ManualClock(), seed=3)
    np.testing.assert_array_equal(again.physics(0.5)["acc"], a["acc"])


def _stacked(readings, key):
    return np.array([r[key] for r in readings])


@pytest.mark.parametrize("errors", ["analog", "quantised"])
def test_physics_block_is_the_per_time_physics_draw_for_draw(errors):
    """A FIFO burst's readings in one call are those of one ``physics`` call per time, bit for
    bit (noise, drift, quantisation, saturation, truth), and leave the simulator where those
    calls leave it — with another part's reading (an earlier time) in between."""
    def imu():
        models = board_models("MPU9250", seed=4)
        if errors == "analog":
            models = {k: m.analog() for k, m in models.items()}
        return SimulatedImu(profile("figure8", looping=True), models, clock=ManualClock(), seed=7,
                            temperature_c=lambda t: 25.0 + 0.5 * t)

    one, block = imu(), imu()
    rng = np.random.default_rng(1)
    t0 = 0.0
    for _ in range(40):
        period = 1 / 1007.0
        t = t0 + period * np.arange(1, int(rng.integers(1, 45)) + 1)
        want = [one.physics(x, period) for x in t.tolist()]
        got = block.physics_block(t, period)
        assert len(got) == len(t)
        for key in ("gyr", "acc", "mag"):
            np.testing.assert_array_equal(getattr(got, key), _stacked(want, key))
            np.testing.assert_array_equal(got.saturated[key], [w["saturated"][key] for w in want])
        np.testing.assert_array_equal(got.temperature_c, _stacked(want, "temperature_c"))
        np.testing.assert_array_equal([s.q for s in got.truth], [w["truth"].q for w in want])
        # the magnetometer reads at its own (earlier) time between two bursts
        tm = float(t[-1]) - 0.0043
        np.testing.assert_array_equal(one.physics(tm, 0.01)["mag"], block.physics(tm, 0.01)["mag"])
        t0 = float(t[-1])
    for key in ("gyr", "acc", "mag"):
        np.testing.assert_array_equal(one.models[key].drift, block.models[key].drift)
    # a burst that starts at the previous call's time gets that reading again, then moves on
    last = block.physics(t0 + 0.001)
    again = block.physics_block([t0 + 0.001, t0 + 0.002])
    np.testing.assert_array_equal(again.gyr[0], last["gyr"])
    assert not np.array_equal(again.gyr[1], last["gyr"])


def test_imu_mounting_rotates_truth_into_sensor_axes():
    m = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # x↔y, z flipped
    imu = SimulatedImu(StaticTrajectory(roll=0.2), mounting=m, clock=ManualClock())
    ph = imu.physics(0.0)
    np.testing.assert_allclose(m @ ph["acc"], ph["truth"].specific_force_body, atol=1e-12)
    with pytest.raises(ValueError, match="models"):
        SimulatedImu(StaticTrajectory(), {"gyro": SensorErrorModel()})


def test_clocks():
    c = ManualClock()
    assert c.now() == 0.0 and c.advance(0.25) == 0.25 and c.to_ns(0.25) == 250_000_000
    with pytest.raises(ValueError):
        c.set(0.1)
    m = MonotonicClock()
    t1 = m.now()
    assert m.now() >= t1 >= 0.0


def test_source_never_delivers_twice():
    clock = ManualClock()
    src = SimulatedSource(SimulatedImu(StaticTrajectory(), clock=clock), rate_hz=100.0, mag_rate_hz=25.0)
    first = src.read()
    assert first is not None and first.t_ns == 0
    assert src.read() is None  # same instant: nothing new
    clock.advance(0.004)
    assert src.read() is None  # not yet 10 ms
    clock.advance(0.006)
    s = src.read()
    assert s is not None and s.t_ns == 10_000_000
    assert src.read() is None
    clock.advance(0.055)  # late: samples at 20…60 ms due, only the newest is delivered
    s = src.read()
    assert s.t_ns == 60_000_000 and src.diagnostics.dropped_frames == 4
    assert src.diagnostics.lost.host_stall == 4  # lost to the late read, counted by cause
    assert src.read() is None
    assert src.diagnostics.samples == 3


def test_source_magnetometer_every_kth_sample_and_truth():
    clock = ManualClock()
    tr = ValidationManoeuvre(hold=0.2, move=0.3)
    src = SimulatedSource(SimulatedImu(tr, clock=clock), rate_hz=100.0, mag_rate_hz=25.0)
    samples = []
    for _ in range(12):
        samples.append(src.read())
        clock.advance(0.01)
    new = [bool(s.flags & MAG_NEW) for s in samples]
    assert new == [i % 4 == 0 for i in range(12)]
    assert all(s.flags & MAG_VALID for s in samples)
    np.testing.assert_array_equal(samples[3].mag, samples[0].mag)  # held between readings
    for s in samples:
        np.testing.assert_allclose(s.truth_q, tr.state(s.t_ns * 1e-9).q)


def test_source_flags_saturation():
    clock = ManualClock()
    models = {"acc": SensorErrorModel(range=2 * 9.80665)}
    tr = FunctionTrajectory(lambda t: [1, 0, 0, 0], lambda t: [0.0, 0.0, 15.0 * t * t])  # 3 g up
    src = SimulatedSource(SimulatedImu(tr, models, clock=clock), rate_hz=50.0, mag_rate_hz=0)
    s = src.read()
    assert s.flags & ACC_SATURATED and not s.flags & ACC_VALID and s.flags & GYR_VALID
    assert s.mag is None and not src.has_mag
    assert src.diagnostics.saturated == 1


def test_source_stops_at_end_of_finite_trajectory():
    clock = ManualClock()
    src = SimulatedSource(SimulatedImu(StaticTrajectory(duration=0.1), clock=clock), rate_hz=100.0)
    clock.advance(5.0)
    assert src.read().t_ns == 100_000_000
    clock.advance(1.0)
    assert src.read() is None


# --------------------------------------------------------------------------- end to end


def test_validation_manoeuvre_through_madgwick_tracks_truth():
    """Noisy MPU-9250 over the first paper's manoeuvre, through the service's calibration path.

    The accelerometer and magnetometer are calibrated as a perfect six-position / ellipsoid
    fit would (``ideal_calibration``); the gyro bias is estimated from the first 2 s hold, as
    the service does at start-up. What is left is noise, quantisation, bias drift and the
    filter's own lag (0.25° RMS with perfect sensors).
    """
    clock = ManualClock()
    imu = SimulatedImu(ValidationManoeuvre(), board_models("MPU9250"), clock=clock, seed=11)
    src = SimulatedSource(imu, rate_hz=200.0, mag_rate_hz=100.0)
    samples = []
    while (s := src.read()) is not None or clock.now() <= imu.trajectory.duration:
        if s is not None:
            samples.append(s)
        clock.advance(0.005)
    assert len(samples) == int(imu.trajectory.duration * 200) + 1
    t = np.array([s.t_ns for s in samples]) * 1e-9
    gyr = np.array([s.gyr for s in samples])
    at_rest = t < 1.9  # the first hold lasts 2 s
    cal = dataclasses.replace(imu.ideal_calibration(), gyro_bias=gyr[at_rest].mean(axis=0))
    body = [apply_calibration(s, cal) for s in samples]
    q = estimators.run(
        "madgwick",
        np.array([b.gyr for b in body]),
        np.array([b.acc for b in body]),
        np.array([b.mag for b in body]),
        timestamps=t,
    )
    truth = np.array([s.truth_q for s in samples])
    total, _, incl = error_deg(q, truth)
    assert np.sqrt(np.mean(total**2)) < 0.6
    assert np.sqrt(np.mean(incl**2)) < 0.4
    assert total.max() < 4.0


def test_imu_copies_models_and_leaves_presets_untouched():
    preset = PART_MODELS["L3GD20"]
    before = (preset.seed, preset.turn_on_bias.copy())
    shared = part_model("ADXL345", seed=9)
    imu = SimulatedImu(StaticTrajectory(), {"gyr": preset, "acc": shared, "mag": shared}, clock=ManualClock(), seed=1)
    imu.physics(0.0)
    imu.physics(0.01)
    assert (preset.seed, preset.turn_on_bias.tolist()) == (before[0], before[1].tolist())
    assert imu.models["acc"] is not imu.models["mag"] and imu.models["gyr"] is not preset
    assert imu.models["acc"].seed == 2 and imu.models["mag"].seed == 3


def test_analog_copy_drops_digitisation_only():
    a = part_model("L3G4200D", seed=2).analog()
    assert a.quantisation == 0.0 and math.isinf(a.range)
    assert a.noise_density == PART_MODELS["L3G4200D"].noise_density and a.seed == 2
    np.testing.assert_array_equal(a.turn_on_bias, part_model("L3G4200D", seed=2).turn_on_bias)


def test_imu_temperature_callable_drives_coefficient():
    models = {"gyr": SensorErrorModel(temp_coeff=[0.001, 0.002, 0.003])}
    imu = SimulatedImu(StaticTrajectory(), models, clock=ManualClock(), temperature_c=lambda t: 25.0 + 10.0 * t)
    ph = imu.physics(2.0)
    assert ph["temperature_c"] == 45.0
    np.testing.assert_allclose(ph["gyr"], [0.02, 0.04, 0.06])


def test_source_on_looping_trajectory_runs_past_the_end():
    clock = ManualClock()
    tr = ValidationManoeuvre(hold=0.5, move=0.5, looping=True)
    src = SimulatedSource(SimulatedImu(tr, clock=clock), rate_hz=50.0)
    clock.set(tr.duration + 1.2)
    s = src.read()
    assert s.t_ns == round((tr.duration + 1.2) * 1e9)
    np.testing.assert_allclose(s.truth_q, ValidationManoeuvre(hold=0.5, move=0.5).state(1.2).q, atol=1e-9)


def test_vibration_on_a_looping_trajectory_still_loops():
    # source.vibration_mss wraps the profile (loop_profile defaults to true): the shaken
    # trajectory loops as its base does, the source runs past the base's duration
    from ahrs_service.drivers.sim.motion import Vibrating

    clock = ManualClock()
    base = ValidationManoeuvre(hold=0.5, move=0.5, looping=True)
    tr = Vibrating(base, [1.0, 0.0, 0.0], 50.0)
    assert tr.looping
    src = SimulatedSource(SimulatedImu(tr, clock=clock), rate_hz=50.0)
    clock.set(base.duration + 1.2)
    s = src.read()
    assert s is not None and s.t_ns == round((base.duration + 1.2) * 1e9)
    np.testing.assert_allclose(s.truth_q, base.state(1.2).q, atol=1e-9)
    assert not Vibrating(ValidationManoeuvre(hold=0.5, move=0.5), [1.0, 0.0, 0.0], 50.0).looping


def test_a_parts_noise_does_not_depend_on_when_another_part_reads():
    """Two parts whose sample grids lie 1 µs apart: each reading's noise is drawn over the
    reading part's own band (``period``), not over the 1 µs since the other part's reading —
    which made the accelerometer 30× noisier and the gyro calibration's rest check fail
    whenever the start-up put the two grids close together (a busy machine does)."""
    from ahrs_service.config import validate
    from ahrs_service.sources import simulated_imu

    source = validate({"source": {"profile": "static", "sensor_errors": True}}).source
    alone, interleaved = simulated_imu(source), simulated_imu(source)
    norms_alone, norms_interleaved = [], []
    for k in range(2000):
        t = k / 800
        norms_alone.append(np.linalg.norm(alone.physics(t, period=1 / 800)["acc"]))
        interleaved.physics(t, period=1 / 800)
        norms_interleaved.append(np.linalg.norm(interleaved.physics(t + 1e-6, period=1 / 800)["acc"]))
    ratio = np.std(norms_interleaved) / np.std(norms_alone)
    assert 0.8 < ratio < 1.25
