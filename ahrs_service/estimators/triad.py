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
from typing import ClassVar

from numba import njit

from ahrs_service.core.layout import Layout, Slot
from ahrs_service.core.quaternion import quat_from_down_and_field, quat_integrate, quat_mul, quat_normalize, quat_rotate
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator, sample_age
from ahrs_service.estimators.uncertainty import AttitudeVariance, SnapshotErrorModel, SnapshotErrorState

_inline = njit(cache=True, inline="always")

#: what a single-sample solution's error model needs of the newest sample (``record_disturbance``)
DISTURBANCE = Layout(
    "single-sample disturbance",
    [
        Slot("lin_acc", 1, "linear acceleration the newest accelerometer sample shows, √| |f|² − g² |, m/s²"),
        Slot("field_ref", 2, "slowly learned field norm (µT) and sine of its dip (0, 0: none yet)"),
        Slot("field_dev", 2, "newest field sample's relative norm deviation and dip deviation (rad) from the reference"),
    ],
)
#: time constant with which the reference field follows the samples, s
FIELD_REF_TAU = 10.0


@_inline
def record_disturbance(s, i, x, acc_ok, mag_ok):
    """Writes the newest sample's disturbance into the DISTURBANCE slots starting at ``i``:
    the linear acceleration its specific force shows (|f|² = g² + a² for a horizontal a) and
    how far its field's norm and dip are from a reference learned over FIELD_REF_TAU."""
    if acc_ok:
        n2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5]
        s[i] = math.sqrt(abs(n2 - K.GRAVITY * K.GRAVITY))
    if acc_ok and mag_ok:
        d = down_direction(x)
        nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
        sd = min(1.0, max(-1.0, (d[0] * x[6] + d[1] * x[7] + d[2] * x[8]) / nm))
        if s[i + 1] == 0.0:
            s[i + 1], s[i + 2] = nm, sd
        s[i + 3] = nm / s[i + 1] - 1.0
        s[i + 4] = math.asin(sd) - math.asin(s[i + 2])
        k = min(1.0, x[K.DT] / FIELD_REF_TAU) if x[K.DT] > 0.0 else 0.0
        s[i + 1] += k * (nm - s[i + 1])
        s[i + 2] += k * (sd - s[i + 2])


def snapshot_error_state(s, i: int) -> SnapshotErrorState:
    """The DISTURBANCE slots at ``i`` and the header's field age, for ``SnapshotErrorModel``."""
    return SnapshotErrorState(
        linear_acceleration=float(s[i]),
        field_norm=float(s[i + 1]),
        field_dip=math.asin(max(-1.0, min(1.0, float(s[i + 2])))),
        field_norm_deviation=float(s[i + 3]),
        field_dip_deviation=float(s[i + 4]),
        field_age=sample_age(s[K.MAG_AGE]),
        acc_age=sample_age(s[K.ACC_AGE]),
    )


STATE = Layout("triad state", list(DISTURBANCE.slots), start=K.HEADER)
STATE_SIZE = STATE.end


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
    record_disturbance(s, K.HEADER, x, acc_ok, mag_ok)
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
    state_size = STATE_SIZE
    #: single-sample error model (``uncertainty.SnapshotErrorModel``); scales: the largest
    #: either data set needs (inclination: BROAD or DIDO; heading: BROAD), docs/autopilot.md
    observed_error_model: ClassVar[SnapshotErrorModel] = SnapshotErrorModel(tilt_scale=0.41, heading_scale=0.60)

    def _model_variance(self) -> AttitudeVariance:
        """Variances from the disturbance the newest samples show (``SnapshotErrorModel``)."""
        if not self.state[K.INITIALISED]:
            return AttitudeVariance.unknown()
        return self.observed_error_model.variance(snapshot_error_state(self.state, K.HEADER))
