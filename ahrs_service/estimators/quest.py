"""QUEST: Shuster and Oh's quaternion estimator, the optimal two-vector attitude.

Second source paper, eq. 17–22. Wahba's cost J = ½ Σ ρ_k |v_kb − A v_ki|² (eq. 17) is
minimised by the eigenvector of K (eq. 19–20) for its largest eigenvalue λ_opt (eq. 21).
QUEST finds λ_opt by Newton's method on K's characteristic polynomial, starting from Σ ρ_k
(eq. 18), and the eigenvector through the Rodrigues parameters (eq. 22), written here in
Shuster's adjugate form q ∝ (γ, (αI + βS + S²) Z), which stays finite where the Rodrigues
parameters blow up. Eq. 20's Z is the standard (B₂₃ − B₃₂, B₃₁ − B₁₃, B₁₂ − B₂₁).

Near a 180° rotation γ → 0 and the solution loses precision; Shuster's method of sequential
rotations is used: if |γ| is small, the problem is re-solved with the reference frame turned
180° about x, y or z (whichever gives the largest |γ|), and that turn is undone on the result.

Vectors (earth NED, body FRD): down, −f/|f| in the body, (0, 0, 1) in the earth frame; and the
magnetic field, whose earth direction (cos δ, 0, sin δ) needs the dip δ. The dip is taken from
the first usable sample pair (the angle between down and the field), so heading is against
magnetic north without a configured location. Without a usable magnetometer sample the
gyro-propagated attitude is tilted onto gravity, as in :mod:`triad`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_mul, quat_normalize
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.triad import (
    DISTURBANCE,
    down_direction,
    propagate_then_level,
    record_disturbance,
    snapshot_error_state,
)
from ahrs_service.estimators.uncertainty import AttitudeVariance, SnapshotErrorModel

_inline = njit(cache=True, inline="always")

# state after the header: the earth field direction learned at start-up
STATE = Layout(
    "quest state",
    [Slot("dip", 2, "earth field direction (cos δ, sin δ), δ the dip"), *DISTURBANCE.slots],
    start=K.HEADER,
)
DIP = STATE.index.dip
DIST = STATE.index.lin_acc  # first slot of the error model's record (triad.DISTURBANCE)
STATE_SIZE = STATE.end


@_inline
def _quest_core(b1, r1, b2, r2, w1, w2):
    """Unnormalised optimal quaternion (γ, X) [w, x, y, z] for unit body/earth pairs."""
    # eq. 20: B = Σ ρ b rᵀ, S = B + Bᵀ, σ = tr B, Z
    b00 = w1 * b1[0] * r1[0] + w2 * b2[0] * r2[0]
    b01 = w1 * b1[0] * r1[1] + w2 * b2[0] * r2[1]
    b02 = w1 * b1[0] * r1[2] + w2 * b2[0] * r2[2]
    b10 = w1 * b1[1] * r1[0] + w2 * b2[1] * r2[0]
    b11 = w1 * b1[1] * r1[1] + w2 * b2[1] * r2[1]
    b12 = w1 * b1[1] * r1[2] + w2 * b2[1] * r2[2]
    b20 = w1 * b1[2] * r1[0] + w2 * b2[2] * r2[0]
    b21 = w1 * b1[2] * r1[1] + w2 * b2[2] * r2[1]
    b22 = w1 * b1[2] * r1[2] + w2 * b2[2] * r2[2]
    s00, s11, s22 = 2.0 * b00, 2.0 * b11, 2.0 * b22
    s01, s02, s12 = b01 + b10, b02 + b20, b12 + b21
    sigma = b00 + b11 + b22
    z0, z1, z2 = b12 - b21, b20 - b02, b01 - b10
    # characteristic polynomial of K: λ⁴ − (a + b) λ² − c λ + (a b + c σ − d)
    kappa = (s11 * s22 - s12 * s12) + (s00 * s22 - s02 * s02) + (s00 * s11 - s01 * s01)  # tr adj S
    delta = s00 * (s11 * s22 - s12 * s12) - s01 * (s01 * s22 - s12 * s02) + s02 * (s01 * s12 - s11 * s02)
    sz0 = s00 * z0 + s01 * z1 + s02 * z2
    sz1 = s01 * z0 + s11 * z1 + s12 * z2
    sz2 = s02 * z0 + s12 * z1 + s22 * z2
    zz = z0 * z0 + z1 * z1 + z2 * z2
    zsz = z0 * sz0 + z1 * sz1 + z2 * sz2
    zssz = sz0 * sz0 + sz1 * sz1 + sz2 * sz2
    a = sigma * sigma - kappa
    b = sigma * sigma + zz
    c = delta + zsz
    d = zssz
    # eq. 18: Newton's method from λ₀ = Σ ρ (exact for noise-free, consistent vectors)
    lam = w1 + w2
    for _ in range(20):
        f = ((lam * lam - (a + b)) * lam - c) * lam + (a * b + c * sigma - d)
        fp = (4.0 * lam * lam - 2.0 * (a + b)) * lam - c
        if fp == 0.0:
            break
        step = f / fp
        lam -= step
        if abs(step) < 1e-12 * (w1 + w2):
            break
    # eq. 22 in adjugate form: [(λ + σ) I − S] p = Z  ⇒  q ∝ (γ, (α I + β S + S²) Z)
    alpha = lam * lam - sigma * sigma + kappa
    beta = lam - sigma
    gamma = (lam + sigma) * alpha - delta
    x0 = alpha * z0 + beta * sz0 + (s00 * sz0 + s01 * sz1 + s02 * sz2)
    x1 = alpha * z1 + beta * sz1 + (s01 * sz0 + s11 * sz1 + s12 * sz2)
    x2 = alpha * z2 + beta * sz2 + (s02 * sz0 + s12 * sz1 + s22 * sz2)
    # Shuster's quaternion of the earth→body matrix is the Hamilton q_earth←body (γ, X)
    return (gamma, x0, x1, x2)


@njit(cache=True)
def quest_quat(d, m, rm, w_acc, w_mag):
    """Optimal q_earth←body of Wahba's problem for down and the magnetic field (eq. 17–22).

    d: body unit down (−f/|f|); m: body field (any scale, µT); rm: unit earth field direction
    (NED); w_acc, w_mag: the weights ρ₁, ρ₂. Returns (q, ok); ok is False when the field is
    unusable (zero or parallel to down). q is unit, w ≥ 0 is not guaranteed.
    """
    nm = math.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2])
    if not nm > 0.0:
        return (1.0, 0.0, 0.0, 0.0), False
    bm = (m[0] / nm, m[1] / nm, m[2] / nm)
    cx = d[1] * bm[2] - d[2] * bm[1]
    cy = d[2] * bm[0] - d[0] * bm[2]
    cz = d[0] * bm[1] - d[1] * bm[0]
    if cx * cx + cy * cy + cz * cz < 1e-12:
        return (1.0, 0.0, 0.0, 0.0), False
    q = _quest_core(d, (0.0, 0.0, 1.0), bm, rm, w_acc, w_mag)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    scale = w_acc + w_mag
    if abs(q[0]) >= 0.3 * n and n > 1e-6 * scale * scale * scale:
        return quat_normalize(q), True
    # sequential rotations: reference frame turned 180° about axis i, r' = D_i r; the result
    # q' = e_i ⊗ q is turned back with q = e_i* ⊗ q'. The unnormalised solutions of the four
    # problems share one norm, so the largest |γ| marks the best-conditioned one.
    best = abs(q[0])
    for axis in range(3):
        sx = 1.0 if axis == 0 else -1.0
        sy = 1.0 if axis == 1 else -1.0
        sz = 1.0 if axis == 2 else -1.0
        qr = _quest_core(d, (0.0, 0.0, sz), bm, (sx * rm[0], sy * rm[1], sz * rm[2]), w_acc, w_mag)
        if abs(qr[0]) > best:
            best = abs(qr[0])
            e = (0.0, -1.0 if axis == 0 else 0.0, -1.0 if axis == 1 else 0.0, -1.0 if axis == 2 else 0.0)
            q = quat_mul(e, qr)
    return quat_normalize(q), True


@_inline
def learn_dip(s, x):
    """Stores the earth field direction (cos δ, sin δ) from down · m of a row at s[DIP:DIP+2]."""
    d = down_direction(x)
    nm = math.sqrt(x[6] * x[6] + x[7] * x[7] + x[8] * x[8])
    sd = (d[0] * x[6] + d[1] * x[7] + d[2] * x[8]) / nm
    sd = min(1.0, max(-1.0, sd))
    s[DIP] = math.sqrt(1.0 - sd * sd)
    s[DIP + 1] = sd


@dataclass
class QuestParams:
    """Tuning of :class:`Quest`.

    w_acc: weight ρ₁ of the gravity direction in Wahba's cost (eq. 17). Default 2 (the paper).
    w_mag: weight ρ₂ of the magnetic field direction. Default 2 (the paper). Only the ratio
        matters to the solution; on BROAD equal weights score best (figures:
        docs/estimators-paper2.md, "Accuracy on BROAD and speed").
    """

    w_acc: float = 2.0
    w_mag: float = 2.0

    def __post_init__(self) -> None:
        if not self.w_acc > 0:
            raise ValueError(f"w_acc must be > 0, got {self.w_acc}")
        if not self.w_mag > 0:
            raise ValueError(f"w_mag must be > 0, got {self.w_mag}")


_P = param_index(QuestParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def quest_step(s, p, x):
    w_acc, w_mag = p[_P.w_acc], p[_P.w_mag]
    gyro_ok, acc_ok, mag_ok = K.check_sample(s, x, True)
    record_disturbance(s, DIST, x, acc_ok, mag_ok)
    if s[DIP] == 0.0 and s[DIP + 1] == 0.0 and acc_ok and mag_ok:
        learn_dip(s, x)
    if K.initialise_from_sample(s, x, acc_ok, mag_ok):
        return
    if acc_ok and mag_ok:  # the dip is known: learn_dip ran above
        qq, ok = quest_quat(down_direction(x), (x[6], x[7], x[8]), (s[DIP], 0.0, s[DIP + 1]), w_acc, w_mag)
        if ok:
            K.store_quat(s, qq)
            return
    # without an algebraic fix the gyro carries the attitude, gravity sets its tilt
    propagate_then_level(s, x, gyro_ok, acc_ok)


@njit(cache=True)
def quest_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        quest_step(s, p, rows[i])
        out[i] = s[:4]


class Quest(Estimator):
    """QUEST (eq. 17–22): optimal algebraic attitude from gravity and field every sample.

    Without a usable magnetometer sample: gyro-propagated attitude, tilt set from gravity.
    """

    name = "quest"
    Params = QuestParams
    uses_mag = True
    observes_heading = True
    state_size = STATE_SIZE
    step = staticmethod(quest_step)
    batch = staticmethod(quest_batch)
    #: single-sample error model (``uncertainty.SnapshotErrorModel``); scales: the largest
    #: either data set needs (inclination: BROAD or DIDO; heading: BROAD), docs/autopilot.md
    observed_error_model: ClassVar[SnapshotErrorModel] = SnapshotErrorModel(tilt_scale=0.41, heading_scale=0.64)

    def _model_variance(self) -> AttitudeVariance:
        """Variances from the disturbance the newest samples show (``SnapshotErrorModel``)."""
        if not self.state[K.INITIALISED]:
            return AttitudeVariance.unknown()
        return self.observed_error_model.variance(snapshot_error_state(self.state, DIST))
