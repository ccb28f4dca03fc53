"""The NumPy Levenberg–Marquardt solver of the calibration fits, and the fits without scipy.

The magnetometer and accelerometer fits refined with scipy's ``least_squares`` until the
solver replaced it; the values scipy gave on two of tests/test_calibration_fit.py's simulated
sensors are pinned here, and the NumPy solver must land on the same minimum (within 1e-8
relative; measured 4e-11).
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from ahrs_service.calibration.accelerometer import fit_accelerometer
from ahrs_service.calibration.least_squares import (
    TRIU,
    levenberg_marquardt,
    sphere_residuals,
    symmetric_from,
)
from ahrs_service.calibration.magnetometer import fit_magnetometer
from tests.test_calibration_fit import (
    F_TRUE,
    SIX_POSES,
    acc_gyr_readings,
    mag_readings,
    pose_sequence,
    sphere_attitudes,
)

# scipy.optimize.least_squares' results (scipy 1.x, before the NumPy solver), same data
SCIPY_MAG_HARD_IRON = np.array([12.00468041696423, -29.9994599737416, 24.97450706850545])
SCIPY_MAG_SOFT_IRON = np.array([
    [0.9122898137160342, -0.05080231733762563, 0.028583117026215875],
    [-0.05080231733762563, 1.092683129740708, -0.044103976238910866],
    [0.028583117026215875, -0.044103976238910866, 0.9828665179888375],
])
SCIPY_MAG_RESIDUAL_RMS = 0.27998437960716416
SCIPY_ACC_BIAS = np.array([0.29854176920748227, -0.20092607407605773, 0.4493470802696129])
SCIPY_ACC_SCALE = np.array([
    [0.9713761581806734, -0.010986344435342105, 0.01950560984696163],
    [-0.010986344435342105, 1.0314397732956437, -0.015267262842899148],
    [0.01950560984696163, -0.015267262842899148, 0.9905877933424632],
])
SCIPY_ACC_RESIDUAL_RMS = 0.0006444529508384622


def _rosenbrock(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = np.array([10.0 * (p[1] - p[0] ** 2), 1.0 - p[0]])
    J = np.array([[-20.0 * p[0], 10.0], [-1.0, 0.0]])
    return r, J


def test_solver_finds_the_rosenbrock_minimum_from_far_away():
    sol = levenberg_marquardt(_rosenbrock, np.array([-1.2, 1.0]))
    assert sol.converged, sol.message
    assert np.allclose(sol.x, [1.0, 1.0], atol=1e-10)
    assert sol.cost < 1e-20
    assert 2 <= sol.iterations < 100


def test_solver_stops_at_its_budget_and_says_so():
    sol = levenberg_marquardt(_rosenbrock, np.array([-1.2, 1.0]), max_iterations=8)
    assert not sol.converged and "8 evaluations" in sol.message
    assert sol.iterations == 8
    assert sol.cost < 0.5 * float(np.sum(_rosenbrock(np.array([-1.2, 1.0]))[0] ** 2))  # it did descend


def test_solver_rejects_a_trial_point_whose_residuals_are_not_finite():
    def log_residual(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # log is undefined below 0: a full Gauss-Newton step from 10 lands there
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.array([np.log(p[0]) - np.log(0.01)]), np.array([[1.0 / p[0]]])

    sol = levenberg_marquardt(log_residual, np.array([10.0]))
    assert sol.converged, sol.message
    assert sol.x[0] == pytest.approx(0.01, rel=1e-9)


def test_solver_refuses_a_start_point_it_cannot_evaluate():
    with pytest.raises(ValueError, match="not finite"):
        levenberg_marquardt(lambda p: (np.array([np.nan]), np.array([[1.0]])), np.array([0.0]))
    with pytest.raises(ValueError, match="jacobian"):
        levenberg_marquardt(lambda p: (np.zeros(3), np.zeros((3, 1))), np.zeros(2))


def test_sphere_jacobian_matches_finite_differences():
    rng = np.random.default_rng(5)
    points = rng.normal(0.0, 3.0, (40, 3))
    model = sphere_residuals(points, 2.5)
    p = np.concatenate([rng.normal(0.0, 0.5, 3), symmetric_from(np.array([1.1, 0.1, -0.2, 0.9, 0.05, 1.2]))[TRIU]])
    _, J = model(p)
    step = 1e-6
    numeric = np.stack([(model(p + step * e)[0] - model(p - step * e)[0]) / (2 * step) for e in np.eye(9)], axis=1)
    assert np.abs(J - numeric).max() < 1e-7


def test_sphere_fit_recovers_an_exact_ellipsoid():
    rng = np.random.default_rng(6)
    directions = rng.normal(size=(200, 3))
    directions /= np.linalg.norm(directions, axis=1)[:, None]
    T_true = symmetric_from(np.array([1.2, 0.05, -0.03, 0.9, 0.02, 1.05]))
    centre_true = np.array([0.4, -0.3, 0.2])
    points = directions @ np.linalg.inv(T_true) + centre_true  # |T (x − c)| = 1 exactly
    sol = levenberg_marquardt(sphere_residuals(points, 1.0), np.concatenate([np.zeros(3), np.eye(3)[TRIU]]))
    assert sol.converged, sol.message
    assert np.abs(sol.x[:3] - centre_true).max() < 1e-10
    assert np.abs(symmetric_from(sol.x[3:]) - T_true).max() < 1e-10


def test_magnetometer_fit_matches_scipy_least_squares():
    mag = mag_readings(sphere_attitudes(2000), np.random.default_rng(1))
    res = fit_magnetometer(mag, field_strength=F_TRUE)
    assert res.accepted, res.reason
    assert np.abs(res.hard_iron - SCIPY_MAG_HARD_IRON).max() < 1e-8 * np.abs(SCIPY_MAG_HARD_IRON).max()
    assert np.abs(res.soft_iron - SCIPY_MAG_SOFT_IRON).max() < 1e-8
    assert res.residual_rms == pytest.approx(SCIPY_MAG_RESIDUAL_RMS, rel=1e-9)


def test_accelerometer_refinement_matches_scipy_least_squares():
    _, f, w = pose_sequence(SIX_POSES + [(45, 0, 0), (0, 45, 0), (30, 30, 0), (-45, -30, 0)])
    acc, gyr = acc_gyr_readings(f, w, np.random.default_rng(10))
    res = fit_accelerometer(acc, gyr, sample_rate_hz=100.0)
    assert res.accepted and res.refined, res.reason
    assert np.abs(res.bias - SCIPY_ACC_BIAS).max() < 1e-8
    assert np.abs(res.scale - SCIPY_ACC_SCALE).max() < 1e-8
    assert res.residual_rms == pytest.approx(SCIPY_ACC_RESIDUAL_RMS, rel=1e-8)


_WITHOUT_SCIPY = textwrap.dedent(
    """
    import sys

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] == "scipy":
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, Block())
    sys.path.insert(0, sys.argv[1])
    from tests.test_least_squares import (
        test_accelerometer_refinement_matches_scipy_least_squares,
        test_magnetometer_fit_matches_scipy_least_squares,
    )

    test_magnetometer_fit_matches_scipy_least_squares()
    test_accelerometer_refinement_matches_scipy_least_squares()
    print("SCIPY LOADED", sorted(m for m in sys.modules if m.split(".")[0] == "scipy"))
    """
)


def test_the_fits_run_where_scipy_is_not_installed():
    """The lean install has no scipy: both fits (the refining steps included) run without it."""
    from pathlib import Path

    root = str(Path(__file__).resolve().parent.parent)
    proc = subprocess.run([sys.executable, "-c", _WITHOUT_SCIPY, root], capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "SCIPY LOADED []" in proc.stdout
