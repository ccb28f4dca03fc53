"""Attitude uncertainty: every estimator reports it (NaN where it must), the covariance-based
ones follow their P, the error models follow what the filter observes (time without
corrections, angle turned, linear acceleration, field disturbance), and on the recordings
(BROAD, DIDO; each skipped without its data) the σ of ``robust`` and ``ekf`` is not
overconfident on either data set (the scale is the largest either needs), nor absurdly
conservative on BROAD, also held out (leave-one-recording-out)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.core.quaternion import quat_from_euler
from ahrs_service.estimators.uncertainty import ErrorModel, euler_jacobian, euler_variance_of_quaternion_covariance

pytestmark = pytest.mark.timeout(300)

RATE = 200.0


def still(n: int, mag: bool = True):
    rng = np.random.default_rng(3)
    gyr = rng.normal(0.0, 0.002, (n, 3))
    acc = np.tile([0.0, 0.0, -9.81], (n, 1)) + rng.normal(0.0, 0.02, (n, 3))
    field = np.tile([20.0, 0.0, 40.0], (n, 1)) + rng.normal(0.0, 0.2, (n, 3)) if mag else None
    return gyr, acc, field


@pytest.mark.parametrize("name", estimators.names())
def test_every_estimator_reports_variances_and_nan_where_unknown(name):
    est = estimators.create(name)
    assert all(math.isnan(v) for v in est.attitude_variance().as_dict().values())  # not initialised
    gyr, acc, mag = still(400)
    est.run(gyr, acc, mag if est.uses_mag else None, dt=1.0 / RATE)
    var = est.attitude_variance()
    assert var.roll > 0 and var.pitch > 0
    if est.observes_heading and est.uses_mag:
        assert var.yaw > 0
    else:
        assert math.isnan(var.yaw)  # heading of a 6D filter: the gyro's, from an arbitrary start
    logged = est.diagnostics["attitude_variance"]
    assert logged.keys() == {"roll", "pitch", "yaw"}
    np.testing.assert_array_equal([logged[k] for k in ("roll", "pitch", "yaw")], [var.roll, var.pitch, var.yaw])


def test_error_model_grows_with_the_time_without_corrections():
    est = estimators.create("madgwick")
    gyr, acc, mag = still(400)
    est.run(gyr, acc, mag, dt=1.0 / RATE)
    m = ErrorModel()
    assert est.attitude_variance().yaw == pytest.approx(m.heading_sigma**2)
    # 10 s without a usable field sample (NaN field): heading σ² = floor² + (drift · 10 s)²
    est.run(np.tile(gyr, (5, 1)), np.tile(acc, (5, 1)), None, dt=1.0 / RATE)
    var = est.attitude_variance()
    assert var.yaw == pytest.approx(m.heading_sigma**2 + (m.drift * 10.0) ** 2, rel=1e-6)
    assert var.roll == pytest.approx(m.tilt_sigma**2)  # the accelerometer still corrects


def test_quaternion_covariance_maps_onto_euler_angles():
    q = np.array(quat_from_euler(0.3, -0.2, 1.0))
    # a small rotation about body x only: roll error only (at this attitude, ZYX)
    jac = euler_jacobian(q)
    xi = 0.5 * np.array([[-q[1]], [q[0]], [q[3]], [-q[2]]])  # ∂q/∂θx of q ⊗ (1, θx/2, 0, 0)
    d = jac @ xi
    assert d[0, 0] == pytest.approx(1.0, abs=1e-5) and abs(d[1, 0]) < 1e-5 and abs(d[2, 0]) < 1e-5
    var = euler_variance_of_quaternion_covariance(q, (0.01**2) * (xi @ xi.T))
    assert var.roll == pytest.approx(0.01**2, rel=1e-4) and var.pitch < 1e-12 and var.yaw < 1e-12


def test_ekf_variance_follows_its_p_and_falls_after_corrections():
    est = estimators.create("ekf", init_attitude_std=0.2)
    gyr, acc, mag = still(2)
    est.run(gyr, acc, mag, dt=1.0 / RATE)
    early = est.attitude_variance()
    gyr, acc, mag = still(2000)
    est.run(gyr, acc, mag, dt=1.0 / RATE)
    late = est.attitude_variance()
    assert late.roll < early.roll and late.yaw < early.yaw
    m = est.observed_error_model
    assert late.roll > (m.tilt_scale * m.tilt_floor) ** 2  # the floor stays under P
    assert math.isfinite(late.yaw)


def test_ekf_yaw_is_unknown_without_a_field():
    est = estimators.create("ekf")
    gyr, acc, _ = still(400)
    est.run(gyr, acc, None, dt=1.0 / RATE)
    var = est.attitude_variance()
    assert math.isfinite(var.roll) and math.isnan(var.yaw)


def shaken(n: int, amplitude: float, mag: bool = True):
    """Still sensor (level, field north-down) whose accelerometer also sees a horizontal
    linear acceleration of ``amplitude`` m/s² at 1 Hz (at its peak on the last sample, which
    is all a single-sample solution sees)."""
    gyr, acc, field = still(n, mag)
    t = np.arange(n) / RATE
    acc = acc.copy()
    acc[:, 0] += amplitude * np.cos(2.0 * np.pi * 1.0 * (t - t[-1]))
    return gyr, acc, field


@pytest.mark.parametrize("name", ["ekf", "triad", "quest"])
def test_tilt_sigma_grows_with_the_linear_acceleration_the_filter_sees(name):
    calm = estimators.create(name)
    calm.run(*shaken(2000, 0.0), dt=1.0 / RATE)
    moved = estimators.create(name)
    moved.run(*shaken(2000, 3.0), dt=1.0 / RATE)
    v0, v1 = calm.attitude_variance(), moved.attitude_variance()
    assert v1.roll > 4.0 * v0.roll and v1.yaw > v0.yaw


def accelerated(n: int, amplitude: float, freq_hz: float):
    """``shaken`` at another frequency: horizontal linear acceleration of ``amplitude`` m/s²
    at ``freq_hz``, at its peak on the last sample."""
    gyr, acc, field = still(n)
    t = np.arange(n) / RATE
    acc = acc.copy()
    acc[:, 0] += amplitude * np.cos(2.0 * np.pi * freq_hz * (t - t[-1]))
    return gyr, acc, field


@pytest.mark.parametrize("name", ["ekf", "robust"])
def test_tilt_sigma_grows_with_sustained_acceleration_not_with_vibration(name):
    """The filters that low-pass the accelerometer follow sustained acceleration (0.5 Hz, a
    vehicle's turn) into their tilt, not vibration (25 Hz) of the same size: their tilt σ
    counts the vector mean of the specific force's horizontal part (``uncertainty``)."""
    v = {}
    for label, amplitude, freq in (("calm", 0.0, 0.5), ("sustained", 2.0, 0.5), ("vibration", 2.0, 25.0)):
        est = estimators.create(name)
        est.run(*accelerated(4000, amplitude, freq), dt=1.0 / RATE)
        v[label] = est.attitude_variance().roll
    assert v["sustained"] > 4.0 * v["calm"], v
    assert v["vibration"] < 0.25 * v["sustained"], v


@pytest.mark.parametrize("name", ["triad", "quest"])
def test_single_sample_heading_sigma_grows_with_a_field_disturbance(name):
    gyr, acc, mag = still(2000)
    clean = estimators.create(name)
    clean.run(gyr, acc, mag, dt=1.0 / RATE)
    disturbed = estimators.create(name)
    mag2 = mag.copy()
    mag2[-1] += [15.0, 0.0, 0.0]  # a magnet's 15 µT on the newest sample
    disturbed.run(gyr, acc, mag2, dt=1.0 / RATE)
    assert disturbed.attitude_variance().yaw > 4.0 * clean.attitude_variance().yaw
    assert disturbed.attitude_variance().roll == pytest.approx(clean.attitude_variance().roll, rel=1e-6)


def test_robust_heading_sigma_grows_while_the_field_is_missing_and_shrinks_when_it_returns():
    # mag_new_first_time=0: the start-up field corrects at once (by default it must first be
    # confirmed while turning, and until then the heading runs on the gyro and σ grows)
    est = estimators.create("robust", mag_new_first_time=0.0)
    gyr, acc, mag = still(4000)
    est.run(gyr, acc, mag, dt=1.0 / RATE)  # 20 s: start-up done
    settled = est.attitude_variance().yaw
    est.run(gyr, acc, None, dt=1.0 / RATE)  # 20 s without a field: the gyro carries heading
    missing = est.attitude_variance().yaw
    assert missing > 1.2 * settled  # at rest the bias is well known: the growth is modest
    est.run(np.tile(gyr, (3, 1)), np.tile(acc, (3, 1)), np.tile(mag, (3, 1)), dt=1.0 / RATE)  # 60 s with it
    assert est.attitude_variance().yaw < 0.5 * (settled + missing)


def test_robust_heading_sigma_counts_the_angle_turned_without_a_field_not_the_back_and_forth():
    """The gyro's scale error turns heading in proportion to the net angle turned: a full
    turn (360°) without a field adds to σ; 180° there and 180° back (same |ω|, same time)
    adds little."""
    def after(turns):
        est = estimators.create("robust", mag_new_first_time=0.0)
        gyr, acc, mag = still(4000)
        est.run(gyr, acc, mag, dt=1.0 / RATE)
        for rate in turns:  # 1 s each about the vertical (level sensor: body z is NED down)
            g, a, _ = still(int(RATE))
            g = g.copy()
            g[:, 2] += rate
            est.run(g, a, None, dt=1.0 / RATE)
        return est.attitude_variance().yaw

    still_only = after([0.0] * 4)
    one_way = after([math.pi / 2] * 4)
    there_and_back = after([math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2])
    assert one_way > 1.5 * still_only
    assert there_and_back < 0.5 * (still_only + one_way)


#: the checks on the recordings (skipped without them). The scale of each σ is the largest
#: any data set needs for its claimed 1σ share (docs/autopilot.md "Attitude covariance"), so
#: no data set may be overconfident beyond a small margin, and the one that did not bind is
#: conservative but not absurdly so.
CLAIM_1 = {"heading": 0.683, "inclination": 0.393}
#: how far below the claimed 1σ share a data set may fall (the scales are rounded, and held out
#: each recording is scored under a scale chosen without it)
MARGIN = 0.03
#: at most this share within 1σ on BROAD: conservative, not absurd
BROAD_MAX_1 = {"heading": 0.90, "inclination": 0.75}
#: the shipped scales are the rule's choice: re-choosing them on the same data must land within
#: this factor of the shipped value
SCALE_TOLERANCE = 0.05
CHECKED = ("robust", "ekf")


def _coverages(source, data_dir):
    from ahrs_service.evaluation.coverage import Coverage, trial_coverage

    covs = {name: Coverage(name) for name in CHECKED}
    for t in source.list_trials(data_dir):
        trial = source.load_trial(data_dir, t)
        for name, cov in covs.items():
            trial_coverage(name, trial, cov)
    return covs


@pytest.fixture(scope="module")
def broad_coverages(broad_dir):
    from ahrs_service.evaluation import broad

    return _coverages(broad, broad_dir)


@pytest.fixture(scope="module")
def dido_coverages():
    from ahrs_service.evaluation import dido

    reason = dido.missing_reason(dido.default_dir())
    if reason:
        pytest.skip(reason)
    return _coverages(dido, dido.default_dir())


@pytest.mark.timeout(900)
def test_reported_sigma_is_not_overconfident_on_broad(broad_coverages):
    for name, cov in broad_coverages.items():
        for angle in ("heading", "inclination"):
            a = cov.angles[angle]
            assert a.n > 10_000, (name, angle, a.n)
            assert CLAIM_1[angle] - MARGIN <= a.frac_1 <= BROAD_MAX_1[angle], (name, angle, a.frac_1)


@pytest.mark.timeout(900)
def test_reported_inclination_sigma_is_not_overconfident_on_dido(dido_coverages):
    for name, cov in dido_coverages.items():
        a = cov.angles["inclination"]
        assert a.n > 1_000, (name, a.n)
        assert a.frac_1 >= CLAIM_1["inclination"] - MARGIN, (name, a.frac_1, a.rms_error_deg, a.rms_sigma_deg)
        assert cov.angles["heading"].n == 0  # no magnetometer: heading not scored


@pytest.mark.timeout(900)
def test_shipped_scales_are_the_largest_need_of_the_data_sets(broad_coverages, dido_coverages):
    """The rule, re-run: inclination's scale the larger of BROAD's and DIDO's needs, heading's
    BROAD's alone; held out (each recording under the scale chosen without it) no data set is
    overconfident beyond the margin."""
    from ahrs_service.evaluation.coverage import calibrate_across

    for name in CHECKED:
        for angle in ("heading", "inclination"):
            cal = calibrate_across({"broad": broad_coverages[name], "dido": dido_coverages[name]}, angle)
            assert cal is not None
            assert set(cal.needed) == ({"broad", "dido"} if angle == "inclination" else {"broad"}), (name, angle, cal.needed)
            assert cal.chosen == max(cal.needed.values())
            assert abs(cal.chosen / cal.current - 1.0) <= SCALE_TOLERANCE, (name, angle, cal.chosen, cal.current)
            for ds, (one, _) in cal.held_out.items():
                assert one >= CLAIM_1[angle] - MARGIN, (name, angle, ds, one)


#: the gap benchmark's patterns the coverage with gaps is checked under (docs/gaps.md)
GAP_PATTERNS = ("bursts:20-100ms:10%", "bursts:20-400ms:10%", "outage:2s")


@pytest.mark.timeout(900)
@pytest.mark.parametrize("pattern", GAP_PATTERNS)
def test_reported_inclination_sigma_is_not_overconfident_with_gaps_on_dido(pattern):
    """With samples lost as the gap benchmark loses them the error grows, and so must the σ:
    the reported variance adds gap_sigma (``_kernel``, "sample gaps"), and on the DIDO flights
    the share of inclination errors within 1σ stays at the claim, as without gaps. With the
    corrections' own 1 s time constant instead (gap_error) it fell to 34 % (20–400 ms bursts)
    and 23 % (the outage) for robust, 28 % and 24 % for the EKF."""
    from ahrs_service.evaluation import dido
    from ahrs_service.evaluation.coverage import broad_coverage

    reason = dido.missing_reason(dido.default_dir())
    if reason:
        pytest.skip(reason)
    for name in CHECKED:
        a = broad_coverage(name, dido.default_dir(), dataset="dido", drop_pattern=pattern).angles["inclination"]
        assert a.n > 1_000, (name, a.n)
        assert a.frac_1 >= CLAIM_1["inclination"] - MARGIN, (name, pattern, a.frac_1, a.rms_error_deg, a.rms_sigma_deg)
