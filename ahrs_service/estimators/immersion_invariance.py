"""Immersion-and-invariance observer of the gravity direction.

Second source paper, eq. 36–37 (after Estrada-Sánchez, Rodríguez-Cortés and Velasco-Villa,
2008, and Astolfi, Karagiannis and Ortega, 2008). The observed quantity is r₃, the earth "down"
axis seen in the body frame (the third row of R_earth←body, i.e. −f/|f| at rest, eq. 12). With
ν = ∫ a dt the integral of the normalised specific force, the model is (eq. 36)

    ṙ₃ = −Ω × r₃ + ξ,    ν̇ = −r₃ + μ_a,

and the observer (eq. 37) keeps r̂₃, ξ̂, μ̂_a with the manifold functions β_i = γ_i ν,
∂β_i/∂ν = γ_i I. Its estimates are r₃ ≈ r̂₃ − β₁, ξ ≈ ξ̄ tanh(ξ̂ + β₂) and
μ_a ≈ μ̄ tanh(μ̂_a + β₃).

Implementation notes (docs/estimators-paper2.md):

* ν grows without bound, so the observer is run in the equivalent coordinates
  z = r̂₃ − γ₁ ν, η₂ = ξ̂ + γ₂ ν, η₃ = μ̂_a + γ₃ ν, where eq. 37 becomes, with the
  normalised specific force a = f/|f| (= ν̇) and the output error e = z + a − μ̄ tanh η₃,

      ż = −Ω × z + ξ̄ tanh η₂ − γ₁ e,   η̇₂ = γ₂ e,   η̇₃ = γ₃ e;

  z is the estimate of r₃ and nothing is ever integrated open-loop;
* the rotation term is written for our frames: a fixed earth direction seen from a body
  turning at Ω moves as −Ω × r₃ (the paper's S(Ω_b) r₃ has its R in the other direction); it is
  applied as an exact rotation over each dt, the rest by an Euler step;
* the accelerometer gate (not in the paper; ``acc_gate``, ``acc_lowpass`` as the
  complementary filter's, ``K.acc_disturbance``): through a sample whose (low-passed)
  specific-force magnitude is off g by more than ``acc_gate``·g the observer is held, r̂₃
  only turned by the gyro, neither the drift term nor the output error applied (the drift
  term alone, unchecked by the output error, tilts r̂₃). 1e9 (``preset="paper"``): never;
* roll and pitch come from z/|z|; yaw from gyro integration: each sample the gyro-propagated
  quaternion is tilted, by the smallest rotation, onto z (:func:`triad.align_down`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from numba import njit

from ahrs_service.core.layout import Layout, Slot, param_index
from ahrs_service.core.quaternion import quat_from_rotvec, quat_mul, quat_normalize, quat_rotate_inv
from ahrs_service.estimators import _kernel as K
from ahrs_service.estimators.base import Estimator
from ahrs_service.estimators.presets import SearchRange, tunable
from ahrs_service.estimators.triad import align_down, down_direction

STATE = Layout(
    "immersion_invariance state",
    [
        Slot("z", 3, "z: estimate of r₃ (body frame, ≈ unit)"),
        Slot("eta2", 3, "η₂ = ξ̂ + γ₂ ν"),
        Slot("eta3", 3, "η₃ = μ̂_a + γ₃ ν"),
        Slot("acc_lp", 3, "low-passed specific force of the gate, m/s², body frame"),
    ],
    start=K.HEADER,
)
Z, ETA2, ETA3, ACC_LP = STATE.index
STATE_SIZE = STATE.end


@dataclass
class ImmersionInvarianceParams:
    """Tuning of :class:`ImmersionInvariance` (eq. 37; all in units of the normalised gravity
    direction, so |r₃| = 1).

    gamma1: γ₁, gain of the output error on r̂₃, 1/s. Paper: 0.5.
    gamma2: γ₂, gain of the drift estimate ξ̂, 1/s. Paper: 0.7.
    gamma3: γ₃, gain of the accelerometer-deviation estimate μ̂_a, 1/s. Paper: 0.9.
    xi_bar: ξ̄, saturation (and sign) of the drift term, 1/s. Paper: −30 (the sign
        makes the ξ loop a negative feedback). The paper's value lets fast translations tilt
        the estimate; a smaller |ξ̄| (−3) damps this and scores far better on BROAD (figures:
        docs/estimators-paper2.md, "Accuracy on BROAD and speed").
    mu_bar: μ̄_a, saturation of the accelerometer-deviation term. Paper: 10.
    acc_gate: not in the paper: the observer is held through a sample whose specific-force
        magnitude is off g by more than acc_gate·g. 1e9 (the paper): never.
    acc_lowpass: not in the paper: time constant (s) of the gyro-turned low-pass of f the
        gate tests (``K.acc_disturbance``); 0: each sample's own f.
    """

    gamma1: float = tunable(0.17774085168697862, paper=0.5, search=SearchRange(0.01, 10.0, log=True))  # 1/s
    gamma2: float = tunable(0.09876442600408761, paper=0.7, search=SearchRange(0.01, 10.0, log=True))  # 1/s
    gamma3: float = tunable(0.06763761659579741, paper=0.9, search=SearchRange(0.01, 10.0, log=True))  # 1/s
    xi_bar: float = tunable(-0.4618594711617465, paper=-30.0, search=SearchRange(-50.0, -0.1))  # 1/s, negative
    mu_bar: float = tunable(0.08182994420019707, paper=10.0, search=SearchRange(0.0, 30.0))
    acc_gate: float = tunable(0.033465314640989646, paper=1e9, search=SearchRange(0.005, 1.0, log=True))
    acc_lowpass: float = tunable(0.14009055966158587, paper=0.0, search=SearchRange(0.0, 0.2))  # s

    def __post_init__(self) -> None:
        for key in ("gamma1", "gamma2", "gamma3"):
            if not getattr(self, key) > 0:
                raise ValueError(f"{key} must be > 0 (eq. 37: γ_i ∈ ℝ⁺), got {getattr(self, key)}")
        if not self.mu_bar >= 0:
            raise ValueError(f"mu_bar must be >= 0, got {self.mu_bar}")
        if not self.acc_gate > 0:
            raise ValueError(f"acc_gate must be > 0, got {self.acc_gate}")
        if not self.acc_lowpass >= 0:
            raise ValueError(f"acc_lowpass must be >= 0, got {self.acc_lowpass}")


_P = param_index(ImmersionInvarianceParams)  # indices of the packed parameter vector, by field name


@njit(cache=True)
def immersion_invariance_step(s, p, x):
    """One sample row; a gap before it is bridged first (``_kernel``, "sample gaps")."""
    n = K.gap_substeps(s, x)
    if n:
        w0, saved, sub = K.begin_bridge(s)
        for j in range(1, n):
            _immersion_invariance_update(s, p, K.bridge_row(sub, w0, x, j, n))
        x = K.end_bridge(s, saved, x, n)
    _immersion_invariance_update(s, p, x)


@njit(cache=True)
def _immersion_invariance_update(s, p, x):
    g1, g2, g3 = p[_P.gamma1], p[_P.gamma2], p[_P.gamma3]
    # after a gap: the output-error gain raised, the drift and bias estimates held while
    # its error is corrected (_kernel, "sample gaps"); γ₁ dt stays below 1
    g1 = min(g1 * K.recovery_gain(s), 0.5 / max(x[K.DT], 1e-6))
    if K.recovering(s):
        g2 = 0.0
        g3 = 0.0
    xi_bar, mu_bar = p[_P.xi_bar], p[_P.mu_bar]
    realignments = s[K.REALIGNMENTS]
    gyro_ok, acc_ok, _ = K.check_sample(s, x, False)
    if s[K.REALIGNMENTS] != realignments:
        # the tilt was realigned after a gap (_kernel.realign_tilt): the observer's r̂₃ with it
        s[Z], s[Z + 1], s[Z + 2] = quat_rotate_inv(K.load_quat(s), (0.0, 0.0, 1.0))
    phase = K.initialise_from_sample(s, x, acc_ok, False)
    if phase == K.STARTED:
        s[Z], s[Z + 1], s[Z + 2] = down_direction(x)
    if phase or not gyro_ok:
        return
    dt = x[K.DT]
    # −Ω × z over dt, exactly: the body turns by Ω dt, a fixed direction turns back
    turn = quat_from_rotvec(x[0] * dt, x[1] * dt, x[2] * dt)  # exp(Ω dt / 2), also integrates q below
    # the output error compares this sample's acceleration with this prediction p
    px, py, pz = quat_rotate_inv(turn, (s[Z], s[Z + 1], s[Z + 2]))
    zx, zy, zz = px, py, pz
    # the gate (not the paper's): through a specific force far from g the observer is held,
    # r̂₃ only turned with the gyro (no drift term, no output error)
    use_acc = acc_ok and K.acc_disturbance(s, ACC_LP, x, p[_P.acc_lowpass]) <= p[_P.acc_gate]
    if use_acc or not acc_ok:
        # ξ̄ tanh(ξ̂ + β₂): the slowly varying drift of r₃ (eq. 37, first line)
        zx += dt * xi_bar * math.tanh(s[ETA2])
        zy += dt * xi_bar * math.tanh(s[ETA2 + 1])
        zz += dt * xi_bar * math.tanh(s[ETA2 + 2])
    if use_acc:
        na = math.sqrt(x[3] * x[3] + x[4] * x[4] + x[5] * x[5])
        # output error e = z + ν̇ − μ̄ tanh(μ̂ + β₃), i.e. −(−r̂₃ + β₁ + μ̄ tanh(μ̂ + β₃) − ν̇)
        ex = px + x[3] / na - mu_bar * math.tanh(s[ETA3])
        ey = py + x[4] / na - mu_bar * math.tanh(s[ETA3 + 1])
        ez = pz + x[5] / na - mu_bar * math.tanh(s[ETA3 + 2])
        # eq. 37 with ∂β_i/∂ν = γ_i I
        zx -= dt * g1 * ex
        zy -= dt * g1 * ey
        zz -= dt * g1 * ez
        s[ETA2] += dt * g2 * ex
        s[ETA2 + 1] += dt * g2 * ey
        s[ETA2 + 2] += dt * g2 * ez
        s[ETA3] += dt * g3 * ex
        s[ETA3 + 1] += dt * g3 * ey
        s[ETA3 + 2] += dt * g3 * ez
    s[Z], s[Z + 1], s[Z + 2] = zx, zy, zz
    q = quat_normalize(quat_mul(K.load_quat(s), turn))  # quat_integrate, sharing exp(Ω dt / 2)
    nz = math.sqrt(zx * zx + zy * zy + zz * zz)
    if nz > 1e-9 and math.isfinite(nz):
        q = align_down(q, (zx / nz, zy / nz, zz / nz))
    K.store_quat(s, q)


@njit(cache=True)
def immersion_invariance_batch(s, p, rows, out):
    for i in range(rows.shape[0]):
        immersion_invariance_step(s, p, rows[i])
        out[i] = s[:4]


class ImmersionInvariance(Estimator):
    """I&I observer of the gravity direction (eq. 36–37); yaw from gyro integration."""

    name = "immersion_invariance"
    Params = ImmersionInvarianceParams
    uses_mag = False
    observes_heading = False
    state_size = STATE_SIZE
    step = staticmethod(immersion_invariance_step)
    batch = staticmethod(immersion_invariance_batch)
