"""Analytic trajectories with exact ground truth for estimator tests (earth NED, body FRD)."""

from __future__ import annotations

import numpy as np

from ahrs_service.core.quaternion import (
    quat_conj_array,
    quat_from_euler,
    quat_from_euler_array,
    quat_from_rotvec_array,
    quat_integrate,
    quat_mul_array,
    quat_rotate_array,
)

G = 9.81
#: Earth field in NED, µT: 20 north, 45 down (mid-latitude, inclination ≈ 66°)
FIELD_NED = np.array([20.0, 0.0, 45.0])


def measure(q: np.ndarray, omega: np.ndarray):
    """Perfect gyro, accelerometer (specific force at rest) and magnetometer for attitudes q."""
    qc = quat_conj_array(q)
    acc = quat_rotate_array(qc, np.broadcast_to([0.0, 0.0, -G], (len(q), 3)))
    mag = quat_rotate_array(qc, np.broadcast_to(FIELD_NED, (len(q), 3)))
    return np.array(omega, dtype=float), acc, mag


def static(roll: float, pitch: float, yaw: float, n: int = 2000):
    """At rest in one attitude (rad): returns (q_true, gyr, acc, mag)."""
    q = np.repeat(quat_from_euler_array(np.array([[roll, pitch, yaw]])), n, axis=0)
    gyr, acc, mag = measure(q, np.zeros((n, 3)))
    return q, gyr, acc, mag


def constant_rotation(omega_body, rate_hz: float, seconds: float, start=(0.0, 0.0, 0.0)):
    """Constant body rate (rad/s) from a start attitude (roll, pitch, yaw): (q, gyr, acc, mag)."""
    n = int(round(seconds * rate_hz))
    t = np.arange(n) / rate_hz
    omega = np.asarray(omega_body, dtype=float)
    q0 = quat_from_euler_array(np.array([start]))
    q = quat_mul_array(q0, quat_from_rotvec_array(t[:, None] * omega))
    gyr, acc, mag = measure(q, np.broadcast_to(omega, (n, 3)))
    return q, gyr, acc, mag


def error_deg(q_est: np.ndarray, q_true: np.ndarray):
    """(total, heading, inclination) errors in degrees, per sample, as the BROAD metric defines them."""
    e = quat_mul_array(q_est, quat_conj_array(q_true))
    w, z = np.abs(e[:, 0]), e[:, 3]
    total = 2 * np.arccos(np.clip(w, 0, 1))
    heading = 2 * np.arctan(np.abs(z / np.where(w == 0, 1e-300, w)))
    incl = 2 * np.arccos(np.clip(np.sqrt(e[:, 0] ** 2 + z**2), 0, 1))
    return np.degrees(total), np.degrees(heading), np.degrees(incl)


def wobble(t: np.ndarray, amp_dps: float = 60.0) -> np.ndarray:
    """A smooth body rate about all three axes (rad/s), enough rotation to observe hard iron."""
    a = amp_dps * (np.pi / 180.0)
    return np.stack([a * np.sin(0.9 * t), a * np.sin(0.65 * t + 1.0), 0.8 * a * np.sin(0.4 * t + 2.0)], axis=1)


def simulate(t: np.ndarray, omega: np.ndarray, start=(0.1, -0.2, 1.0)) -> np.ndarray:
    """True q_earth←body (N, 4) on timestamps t (s): omega[k] (rad/s) is the rate over (t_{k−1}, t_k]."""
    q = np.empty((len(t), 4))
    qk = quat_from_euler(*start)
    q[0] = qk
    for k in range(1, len(t)):
        qk = quat_integrate(qk, omega[k, 0], omega[k, 1], omega[k, 2], t[k] - t[k - 1])
        q[k] = qk
    return q
