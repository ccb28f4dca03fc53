"""Mahony's nonlinear complementary filters on SO(3), direct and passive, with gyro bias.

Second source paper, eq. 33–35 (after Mahony, Hamel and Pflimlin, 2008). Both filters drive
the estimate R̂ towards an algebraic attitude sample R_y with the innovation
ϱ = vex(P_a(R̃)), R̃ = R̂ᵀ R_y, and integrate the bias estimate ḃ = −k_i ϱ:

* direct (eq. 33):  Ṙ̂ = S(R_y (Ω_y − b̂) + k_p R̂ ϱ) R̂  ⇔ body rate R̃ (Ω_y − b̂) + k_p ϱ;
* passive (eq. 34): Ṙ̂ = R̂ S(Ω_y − b̂ + k_p ϱ).

For a quaternion q̃ of R̃, P_a(R(q̃)) = 2 w̃ S(ṽ): ϱ = 2 w̃ ṽ = sin θ · axis of the
attitude error, which the vector form below reproduces to first order. The attitude is
advanced by the exact exponential of the body rate over each sample's dt.

R_y (eq. 35) is Wahba's problem with weights λ₁ (gravity) and λ₂ (field). Mahony et al.
(2008, §V) show that to first order vex(P_a(R̂ᵀ R_y)) is then the weighted sum of the
vector errors, ϱ = λ₁ v_a × v̂_a + λ₂ v_m × v̂_m, with v̂ = R̂ᵀ v₀ each reference seen through
the estimate; this "usual vectorial form" is used, so no R_y is formed and each weight acts
on its own sensor. Gravity's reference is NED down; the field's is the measured field turned
into the earth frame by R̂ with its horizontal part laid on north, b = (|h_xy|, 0, h_z),
so no dip has to be configured. For the direct filter R_y is taken, to the same order, as
R̂ exp(S(ϱ)), so the measured rate is turned by the rotation vector ϱ.
Heading-only field correction (the default; ``mag_heading_only = 1``): the field term is
projected onto the estimated vertical, ϱ = λ₁ v_a × v̂_a + λ₂ (v̂_a v̂_aᵀ)(v_m × v̂_m), so the
magnetometer turns the estimate about earth's down axis only and a disturbed field cannot
tilt it. This is the form of the filters' authors' later work: M.-D. Hua, G. Ducard,
T. Hamel, R. Mahony, K. Rudin, "Implementation of a Nonlinear Attitude Estimator for Aerial
Robotic Vehicles", IEEE Trans. Control Systems Technology 22(1), 2014 (eq. 12). The paper's
form, where the field corrects all three axes, is ``mag_heading_only = 0`` (``preset="paper"``).
Magnetic-disturbance gate (not in the paper, the project's addition as the EKF's ``mag_gate``):
a field sample whose magnitude or dip departs from a reference the filter learns from the
accepted samples (``_kernel.mag_gate_accepts``) gives no field term; ``mag_gate = 1e9`` (the
paper) accepts every sample.
Without a usable (or accepted) magnetometer sample only the gravity term acts (IMU form: roll and pitch
corrected, yaw from the gyro); without a usable accelerometer sample ϱ = 0.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, make_dataclass

from numba import njit

from ahrs_service.core.layout import Layout, param_index
from ahrs_service.core.quaternion import quat_from_rotvec, quat_integrate, quat_rotate, quat_rotate_inv, vec_cross
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable
from ahrs_service.estimators.triad import down_direction


@dataclass
class MahonyParams:
    """Tuning of :class:`MahonyDirect` and :class:`MahonyPassive`.

    Defaults: the preset tuned on BROAD and DIDO together (ahrs_service/estimators/tuned/,
    docs/tuning.md); ``preset="paper"`` gives the paper's values (in brackets).

    kp: proportional gain k_p of eq. 33/34, 1/s (paper 25).
    ki: bias gain k_i of eq. 33/34, 1/s² (paper 10).
    w_acc, w_mag: weights λ₁, λ₂ of gravity and field in eq. 35 (1 and 1: Mahony et al. 2008;
        the paper gives none).
    mag_heading_only: 1 (default) projects the field term onto the estimated vertical, as in
        Hua et al. 2014, so the magnetometer corrects heading only; 0 is the paper's term,
        which lets a disturbed field tilt the estimate (paper 0).
    acc_gate: not in the paper: a sample whose specific-force magnitude is off g by more than
        acc_gate·g gives no gravity term (as the complementary filter's gate; paper 1e9, off).
    mag_gate: not in the paper: a field sample gives no field term when |‖m‖/m_ref − 1| +
        |sin δ − sin δ_ref| exceeds it, δ the field's dip below the horizon, the references
        learned from the accepted samples with a 10 s time constant (as the EKF's gate,
        ``_kernel.mag_gate_accepts``; paper 1e9, off).
    The paper's gains suit its 565 Hz robot-arm runs and follow BROAD's accelerations
    (figures: docs/estimators-paper2.md, "Accuracy on BROAD and speed"). The direct filter
    also turns the gyro rate by the noisy R̃, which only small weights λ keep quiet.
    """

    # the passive filter sees λ₁ only through k_p λ₁, but the direct one also turns the measured
    # rate by ϱ (eq. 33), which λ₁ and λ₂ scale alone: both weights are searched
    kp: float = tunable(25.0, paper=25.0, search=SearchRange(0.01, 30.0, log=True))  # 1/s
    ki: float = tunable(10.0, paper=10.0, search=SearchRange(1e-5, 10.0, log=True))  # 1/s²
    w_acc: float = tunable(1.0, paper=1.0, search=SearchRange(0.001, 1.0, log=True))
    w_mag: float = tunable(1.0, paper=1.0, search=SearchRange(0.01, 5.0, log=True))
    mag_heading_only: float = tunable(1.0, paper=0.0)  # 1: Hua et al. 2014 heading-only field term; 0: the paper's
    # not in the paper (as the complementary filter's acc_gate): no gravity term from a sample
    # with |‖f‖ − g| > acc_gate·g; 1e9 (the paper) never gates
    acc_gate: float = tunable(1e9, paper=1e9, search=SearchRange(0.02, 1.0, log=True))
    # not in the paper (as the EKF's mag_gate): no field term from a sample whose magnitude or
    # dip departs from the learned reference by more than mag_gate; 1e9 (the paper) never gates
    mag_gate: float = tunable(1e9, paper=1e9, search=SearchRange(0.02, 1.0, log=True))

    def __post_init__(self) -> None:
        if self.mag_heading_only not in (0.0, 1.0):
            raise ValueError(f"mag_heading_only must be 0 (the paper's field term) or 1 (heading only), got {self.mag_heading_only}")
        if not self.kp >= 0:
            raise ValueError(f"kp must be >= 0, got {self.kp}")
        for key in ("acc_gate", "mag_gate"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be > 0, got {getattr(self, key)}")
        for key in ("ki", "w_acc", "w_mag"):
            if not getattr(self, key) >= 0:
                raise ValueError(f"{key} must be >= 0, got {getattr(self, key)}")


def _with_defaults(cls_name: str, filter_name: str, **defaults: float) -> type:
    """A subclass of :class:`MahonyParams` with each filter's own tuned defaults: same fields,
    same order, same paper values and search ranges (the field metadata), same checks."""
    fields = [
        (f.name, f.type, field(default=defaults.pop(f.name, f.default), metadata=f.metadata))
        for f in dataclasses.fields(MahonyParams)
    ]
    if defaults:
        raise TypeError(f"not fields of MahonyParams: {sorted(defaults)}")
    doc = f":class:`MahonyParams` at the {filter_name} filter's own tuned defaults (same fields, same order)."
    return make_dataclass(cls_name, fields, bases=(MahonyParams,), namespace={"__doc__": doc, "__module__": __name__})


MahonyDirectParams = _with_defaults(
    "MahonyDirectParams", "direct",
    kp=29.0822576272818, ki=0.00010311981327081509, w_acc=0.026525388005353902, w_mag=0.029250720669782092,
    acc_gate=0.02410461722927688, mag_gate=0.17152895578091523,
)  # fmt: skip
MahonyPassiveParams = _with_defaults(
    "MahonyPassiveParams", "passive",
    kp=1.6842788674045666, ki=0.0001970315626693047, w_acc=0.46405149547687025, w_mag=0.676792288634805,
    acc_gate=0.022540307070296264, mag_gate=0.11325325034854324,
)  # fmt: skip


_P = param_index(MahonyParams)  # indices of the packed parameter vector, by field name

# after the common header: the magnetic-disturbance gate's reference
STATE = Layout("mahony state", K.MAG_REFERENCE_SLOTS, start=K.HEADER)
MAG_REF = STATE.index.mag_norm_ref
STATE_SIZE = STATE.end


@njit(cache=True, inline="always")
def _mahony_step(s, p, x, direct):
    kp, ki, w_acc, w_mag = p[_P.kp], p[_P.ki], p[_P.w_acc], p[_P.w_mag]
    acc_gate, mag_gate = p[_P.acc_gate], p[_P.mag_gate]
    # after a gap: k_p raised and the bias integral held while its error is corrected (_kernel)
    kp *= K.recovery_gain(s)
    acc_gate *= K.recovery_gain(s)
    if K.recovering(s):
        ki = 0.0
    heading_only = p[_P.mag_heading_only] != 0.0
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok) or not gyro_ok:
        return
    q = K.load_quat(s)
    dt = x[K.DT]
    ox, oy, oz = x[0] - s[K.BIAS], x[1] - s[K.BIAS + 1], x[2] - s[K.BIAS + 2]
    # the innovation compares the sensors with the gyro prediction for this sample, so that a
    # perfect gyro leaves nothing to correct (evaluating it at the previous R̂ would lag by dt)
    qp = quat_integrate(q, ox, oy, oz, dt)
    rx, ry, rz = 0.0, 0.0, 0.0
    if acc_ok:
        # eq. 35, first order: ϱ = λ₁ v_a × v̂_a (+ λ₂ v_m × v̂_m)
        ca = vec_cross(down_direction(x), quat_rotate_inv(qp, (0.0, 0.0, 1.0)))
        fn = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
        wa = w_acc if abs(fn - K.GRAVITY) <= acc_gate * K.GRAVITY else 0.0  # gate: not the paper's
        rx, ry, rz = wa * ca[0], wa * ca[1], wa * ca[2]
        if mag_ok:
            nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
            vm = (x[6] / nm, x[7] / nm, x[8] / nm)
            h = quat_rotate(qp, vm)
            # the gate (not the paper's): a field whose magnitude or dip left the learned ones is a magnet's
            if K.mag_gate_accepts(s, MAG_REF, nm, h[2], mag_gate, dt):
                cm = vec_cross(vm, quat_rotate_inv(qp, (math.sqrt(h[0] * h[0] + h[1] * h[1]), 0.0, h[2])))
                if heading_only:
                    # Hua et al. 2014, eq. 12: (v̂_a v̂_aᵀ) v_m × v̂_m, only the part about the vertical
                    d = quat_rotate_inv(qp, (0.0, 0.0, 1.0))
                    c = cm[0] * d[0] + cm[1] * d[1] + cm[2] * d[2]
                    cm = (c * d[0], c * d[1], c * d[2])
                rx, ry, rz = rx + w_mag * cm[0], ry + w_mag * cm[1], rz + w_mag * cm[2]
        if direct:
            # eq. 33: the measured rate carried through R_y = R̂ exp(S(ϱ)): R̃ (Ω_y − b̂)
            ox, oy, oz = quat_rotate(quat_from_rotvec(rx, ry, rz), (ox, oy, oz))
            qp = quat_integrate(q, ox, oy, oz, dt)
    # eq. 33/34: R̂ advances with body rate (…) + k_p ϱ; ḃ = −k_i ϱ
    K.store_quat(s, quat_integrate(qp, kp * rx, kp * ry, kp * rz, dt))
    s[K.BIAS] -= ki * rx * dt
    s[K.BIAS + 1] -= ki * ry * dt
    s[K.BIAS + 2] -= ki * rz * dt


@njit(cache=True)
def mahony_direct_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _mahony_step(s, p, K.bridge_row(sub, w0, x, j, n), True)
        x = K.end_bridge(s, saved, x, n)
    _mahony_step(s, p, x, True)


@njit(cache=True)
def mahony_passive_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _mahony_step(s, p, K.bridge_row(sub, w0, x, j, n), False)
        x = K.end_bridge(s, saved, x, n)
    _mahony_step(s, p, x, False)


@njit(cache=True)
def mahony_direct_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        mahony_direct_step(s, p, rows[i])
        out[i] = s[:4]


@njit(cache=True)
def mahony_passive_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        mahony_passive_step(s, p, rows[i])
        out[i] = s[:4]


class MahonyDirect(Estimator):
    """Mahony's direct complementary filter with gyro-bias estimation (eq. 33, R_y by eq. 35)."""

    name = "mahony_direct"
    Params = MahonyDirectParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(mahony_direct_step)
    batch = staticmethod(mahony_direct_batch)


class MahonyPassive(Estimator):
    """Mahony's passive complementary filter with gyro-bias estimation (eq. 34, R_y by eq. 35)."""

    name = "mahony_passive"
    Params = MahonyPassiveParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(mahony_passive_step)
    batch = staticmethod(mahony_passive_batch)
