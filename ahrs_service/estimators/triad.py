"""TRIAD: the attitude built algebraically from one accelerometer and one magnetometer sample.

Second source paper (Rosario-Gabriel, Rodríguez-Cortés, Velasco-Villa), eq. 15–16, after
Kim et al. (1964). Two orthonormal triads, one from the body-frame measurements and one from
the same directions in the earth frame, give R = [t1b t2b t3b][t1i t2i t3i]ᵀ (eq. 16).

Frames here: earth NED, body FRD. The first vector is "down": −f/|f| in the body (specific
force, eq. 12) and (0, 0, 1) in the earth frame. The second is the magnetic field; since only
the plane spanned by down and the field matters to t2 (eq. 15), the earth reference is
magnetic north, whatever the dip. Heading is thus against magnetic north, as in BROAD.

Without a usable magnetometer sample TRIAD has no heading. This implementation then keeps the
gyro-propagated attitude and tilts it, by the smallest rotation, until its down axis matches
the accelerometer: inclination stays algebraic, yaw comes from gyro integration. The same
"gravity-only" correction (``align_down``) serves QUEST and the observers of this paper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.quaternion import quat_from_down_and_field, quat_integrate, quat_mul, quat_normalize, quat_rotate

_inline = njit(cache=True, inline="always")


@_inline
def down_direction(x):
    """Body-frame unit "down" vector −f/|f| of a row's specific force (eq. 12)."""
    n = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
    return (-x[3] / n, -x[4] / n, -x[5] / n)


@_inline
def align_down(q, d):
    """q turned by the smallest earth-frame rotation that maps body "down" ``d`` onto NED z.

    The rotation axis is horizontal, so the heading of q is kept (gravity-only correction).
    """
    u = quat_rotate(q, d)  # measured down, seen in the earth frame through q
    # shortest arc u → e_z: quaternion (1 + u·e_z, u × e_z), normalised
    c = 1.0 + u[2]
    if c < 1e-9:
        # u points up (q is upside down against the measurement): any horizontal axis works
        return quat_normalize(quat_mul((0.0, 1.0, 0.0, 0.0), q))
    return quat_normalize(quat_mul((c, u[1], -u[0], 0.0), q))


@_inline
def propagate_then_level(s, x, gyro_ok, acc_ok):
    """Fallback of the algebraic estimators (TRIAD, QUEST) for a sample without a fix: the
    gyro carries the attitude (heading included), then gravity sets its tilt."""
    q = K.load_quat(s)
    if gyro_ok:
        q = quat_integrate(q, x[0], x[1], x[2], x[K.DT])
    if acc_ok:
        q = align_down(q, down_direction(x))
    K.store_quat(s, q)


@_inline
def triad_quat(d, mx, my, mz):
    """q_earth←body from body down ``d`` and field (mx, my, mz), eq. 15–16.

    Returns (q, ok); ok is False when the field is (nearly) parallel to down.
    """
    # eq. 15's body triad is t1 = down, t2 = down × m / |down × m| (east), t3 = t1 × t2 = −north;
    # with the earth triad (e_z, e_y, −e_x), eq. 16's product is R_body←earth, whose columns
    # north, east, down are the rows of R_earth←body that quat_from_down_and_field builds
    return quat_from_down_and_field(d, (mx, my, mz))


@dataclass
class TriadParams:
    """TRIAD has no tuning parameter (eq. 15–16 are purely algebraic)."""


@njit(cache=True)
def triad_step(s, p, x):
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok):
        return
    if acc_ok and mag_ok:
        qt, ok = triad_quat(down_direction(x), x[6], x[7], x[8])
        if ok:
            K.store_quat(s, qt)
            return
    # between algebraic fixes the gyro carries the attitude (yaw without mag), gravity its tilt
    propagate_then_level(s, x, gyro_ok, acc_ok)


@njit(cache=True)
def triad_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        triad_step(s, p, rows[i])
        out[i] = s[:4]


class Triad(Estimator):
    """TRIAD (eq. 15–16): algebraic attitude from accelerometer and magnetometer every sample.

    Without a usable magnetometer sample: gyro-propagated attitude, tilt set from gravity.
    """

    name = "triad"
    Params = TriadParams
    uses_mag = True
    observes_heading = True
    step = staticmethod(triad_step)
    batch = staticmethod(triad_batch)
