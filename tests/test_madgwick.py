import numpy as np
import pytest

from ahrs_service import estimators
from analytic import constant_rotation, error_deg, static

RATE = 200.0


@pytest.mark.parametrize(
    "attitude",
    [(0, 0, 0), (0.5, -0.3, 2.0), (np.pi, 0, 0), (0.2, np.radians(89), 1.0), (-0.4, np.radians(-89), -2.5)],
)
def test_static_attitudes_exact_from_first_sample(attitude):
    q, gyr, acc, mag = static(*attitude, n=400)
    est = estimators.run("madgwick", gyr, acc, mag, rate_hz=RATE)
    total, _, _ = error_deg(est, q)
    # normalised gradient steps chatter by about β·dt (0.03°) around the true attitude
    assert total.max() < 0.1


def test_constant_rotation_tracks():
    q, gyr, acc, mag = constant_rotation([0.3, -0.5, 1.0], RATE, 20.0, start=(0.1, 0.2, 0.3))
    est = estimators.run("madgwick", gyr, acc, mag, rate_hz=RATE)
    total, _, _ = error_deg(est, q)
    assert np.sqrt(np.mean(total**2)) < 0.5


def test_imu_form_without_magnetometer_keeps_inclination():
    q, gyr, acc, _ = constant_rotation([0.0, 0.0, 0.8], RATE, 10.0, start=(0.3, -0.2, 0.0))
    est = estimators.run("madgwick", gyr, acc, None, rate_hz=RATE)
    _, _, incl = error_deg(est, q)
    assert incl.max() < 0.5


def test_bad_samples_skipped_and_counted():
    q, gyr, acc, mag = static(0.3, 0.2, 0.1, n=300)
    acc[100] = np.nan
    acc[101] = 0.0
    mag[150] = np.inf
    gyr[200] = np.nan
    est = estimators.create("madgwick")
    out = est.run(gyr, acc, mag, dt=1 / RATE)
    assert np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert est.diagnostics["acc_skipped"] == 2
    assert est.diagnostics["mag_skipped"] == 1
    assert est.diagnostics["gyr_skipped"] == 1
    assert error_deg(out, q)[0].max() < 0.1  # β·dt chatter, as at rest


def test_unknown_parameter_is_a_clear_error():
    with pytest.raises(ValueError, match="gain.*accepted: beta"):
        estimators.run("madgwick", np.zeros((2, 3)), np.ones((2, 3)), rate_hz=100, gain=0.1)
    with pytest.raises(ValueError, match="unknown estimator"):
        estimators.create("kalmann")
