"""Attitude uncertainty: every estimator reports it (NaN where it must), the covariance-based
ones follow their P, the error models grow without corrections, and on BROAD (skipped without
the recordings) the σ of ``robust`` and ``ekf`` covers the actual error within a stated band."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.estimators.uncertainty import ErrorModel, euler_jacobian, euler_variance_of_quaternion_covariance
from ahrs_service.quaternion import quat_from_euler

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


def test_robust_heading_grows_with_its_bias_sigma_while_the_field_is_missing():
    est = estimators.create("robust")
    gyr, acc, mag = still(400)
    est.run(gyr, acc, mag, dt=1.0 / RATE)
    before = est.attitude_variance().yaw
    est.run(gyr, acc, None, dt=1.0 / RATE)
    after = est.attitude_variance().yaw
    assert after > before and math.isfinite(after)


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
    floor = ErrorModel()
    assert late.roll > floor.tilt_sigma**2 and late.yaw > floor.heading_sigma**2


#: the band the BROAD check holds robust and ekf to: the σ may be conservative (up to 3× the
#: RMS error) but must not claim much more than it delivers
HEADING_MIN = (0.50, 0.80)  # fractions within 1σ, 2σ (calibrated: 0.683, 0.954)
INCLINATION_MIN = (0.25, 0.70)  # (calibrated Rayleigh: 0.393, 0.865)
SIGMA_OVER_ERROR = (0.5, 3.0)  # RMS σ / RMS error


def test_reported_sigma_covers_the_broad_errors(broad_dir):
    from ahrs_service.evaluation import broad
    from ahrs_service.evaluation.coverage import Coverage, trial_coverage

    covs = {name: Coverage(name) for name in ("robust", "ekf")}
    for t in broad.list_trials(broad_dir):
        trial = broad.load_trial(broad_dir, t)
        for name, cov in covs.items():
            trial_coverage(name, trial, cov)
    for name, cov in covs.items():
        for angle, (min_1, min_2) in (("heading", HEADING_MIN), ("inclination", INCLINATION_MIN)):
            a = cov.angles[angle]
            assert a.n > 10_000, (name, angle, a.n)
            assert a.frac_1 >= min_1 and a.frac_2 >= min_2, (name, angle, a.frac_1, a.frac_2)
            ratio = a.rms_sigma_deg / a.rms_error_deg
            assert SIGMA_OVER_ERROR[0] <= ratio <= SIGMA_OVER_ERROR[1], (name, angle, ratio)
