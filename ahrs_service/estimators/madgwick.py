"""Madgwick's gradient-descent orientation filter, IMU and MARG forms.

S.O.H. Madgwick, "An efficient orientation filter for inertial and inertial/magnetic sensor
arrays", 2010; as presented in the third source paper, eq. 30–46 (numbers below refer to it).

The paper writes the objective for an earth frame whose z axis points *up* (the accelerometer
reads +g on it at rest). Our earth frame is NED, so the measured "down" direction −f/|f| is
what is matched against earth z; the magnetic reference b = (b_x, 0, b_z) keeps its form with
b_z positive downwards. With a magnetometer sample the MARG form runs, without one (or with a
bad one) the IMU form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.core.layout import param_index
from ahrs_service.core.quaternion import quat_mul, quat_normalize, quat_rotate
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable


@dataclass
class MadgwickParams:
    """Tuning of :class:`Madgwick`.

    beta: gain of the gradient step, rad/s — the assumed gyroscope measurement error
        (eq. 45). Paper (Madgwick's own value): 0.1; BROAD's authors found a slightly larger
        value best over their whole benchmark (docs/estimators-paper1-3.md, "Why the defaults:
        measured figures"). Defaults: the preset tuned on BROAD and DIDO together (docs/tuning.md); the paper's values
        are ``preset="paper"``.
    """

    # paper: Madgwick's own value 0.1 (his reference implementation's betaDef)
    beta: float = tunable(0.07710439415510881, paper=0.1, search=SearchRange(0.005, 1.0, log=True))  # rad/s

    def __post_init__(self) -> None:
        if self.beta < 0:
            raise ValueError(f"beta must be >= 0, got {self.beta}")


_P = param_index(MadgwickParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def madgwick_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _madgwick_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _madgwick_update(s, p, x)


@njit(cache=True)
def _madgwick_update(s, p, x):
    # β raised while a gap's error is corrected (_kernel.recovery_gain)
    beta = p[_P.beta] * K.recovery_gain(s)
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok) or not gyro_ok:
        return
    q0, q1, q2, q3 = K.load_quat(s)
    gx, gy, gz, dt = x[0], x[1], x[2], x[K.DT]

    # eq. 30: rate of change of orientation from the gyroscope, ½ q ⊗ (0, ω)
    qd = quat_mul((q0, q1, q2, q3), (0.0, 0.5 * gx, 0.5 * gy, 0.5 * gz))

    if acc_ok:
        na = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
        # NED: the direction matched to earth z is "down", i.e. minus the specific force
        ax, ay, az = -x[3] / na, -x[4] / na, -x[5] / na
        # eq. 36: f_g, the third row of R(q) minus the measured direction
        f1 = 2.0 * (q1 * q3 - q0 * q2) - ax
        f2 = 2.0 * (q0 * q1 + q2 * q3) - ay
        f3 = 2.0 * (0.5 - q1 * q1 - q2 * q2) - az
        # eq. 35/37/41: ∇f = J_gᵀ f_g
        g0 = -2.0 * q2 * f1 + 2.0 * q1 * f2
        g1 = 2.0 * q3 * f1 + 2.0 * q0 * f2 - 4.0 * q1 * f3
        g2 = -2.0 * q0 * f1 + 2.0 * q3 * f2 - 4.0 * q2 * f3
        g3 = 2.0 * q1 * f1 + 2.0 * q2 * f2
        if mag_ok:
            nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
            mx, my, mz = x[6] / nm, x[7] / nm, x[8] / nm
            # magnetic distortion compensation: the field in the earth frame, h = q ⊗ m ⊗ q*,
            # keeps only its horizontal magnitude and vertical part, b = (√(hx²+hy²), 0, hz)
            hx, hy, hz = quat_rotate((q0, q1, q2, q3), (mx, my, mz))
            bx = math.sqrt(hx * hx + hy * hy)
            bz = hz
            # eq. 38: f_b
            h1 = 2.0 * bx * (0.5 - q2 * q2 - q3 * q3) + 2.0 * bz * (q1 * q3 - q0 * q2) - mx
            h2 = 2.0 * bx * (q1 * q2 - q0 * q3) + 2.0 * bz * (q0 * q1 + q2 * q3) - my
            h3 = 2.0 * bx * (q0 * q2 + q1 * q3) + 2.0 * bz * (0.5 - q1 * q1 - q2 * q2) - mz
            # eq. 39/41: add J_bᵀ f_b
            g0 += -2.0 * bz * q2 * h1 + (-2.0 * bx * q3 + 2.0 * bz * q1) * h2 + 2.0 * bx * q2 * h3
            g1 += 2.0 * bz * q3 * h1 + (2.0 * bx * q2 + 2.0 * bz * q0) * h2 + (
                2.0 * bx * q3 - 4.0 * bz * q1
            ) * h3
            g2 += (-4.0 * bx * q2 - 2.0 * bz * q0) * h1 + (2.0 * bx * q1 + 2.0 * bz * q3) * h2 + (
                2.0 * bx * q0 - 4.0 * bz * q2
            ) * h3
            g3 += (-4.0 * bx * q3 + 2.0 * bz * q1) * h1 + (-2.0 * bx * q0 + 2.0 * bz * q2) * h2 + (
                2.0 * bx * q1
            ) * h3
        ng = math.sqrt(g0 * g0 + g1 * g1 + g2 * g2 + g3 * g3)
        if ng > 0.0:
            # eq. 45/46: q̇_est = q̇_ω − β ∇f/‖∇f‖
            qd = (qd[0] - beta * g0 / ng, qd[1] - beta * g1 / ng, qd[2] - beta * g2 / ng, qd[3] - beta * g3 / ng)

    # eq. 44: integrate and keep unit norm
    K.store_quat(s, quat_normalize((q0 + qd[0] * dt, q1 + qd[1] * dt, q2 + qd[2] * dt, q3 + qd[3] * dt)))


@njit(cache=True)
def madgwick_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        madgwick_step(s, p, rows[i])
        out[i] = s[:4]


class Madgwick(Estimator):
    """Madgwick gradient-descent filter (IMU form, MARG form whenever the magnetometer is usable)."""

    name = "madgwick"
    Params = MadgwickParams
    uses_mag = True
    observes_heading = True
    step = staticmethod(madgwick_step)
    batch = staticmethod(madgwick_batch)
