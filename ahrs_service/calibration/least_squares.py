"""A small Levenberg–Marquardt solver and the sphere model both sensor fits refine.

The magnetometer and accelerometer fits refine at most nine parameters over at most a few
thousand residuals, so a dense solver of the normal equations in NumPy is enough; it keeps
scipy (over 100 MB installed) out of the service's install.

The sphere model: points x_i (rows), a centre c (3,) and a symmetric 3 × 3 matrix T, held as
its six upper-triangle terms in :data:`TRIU` order, give the residuals
``r_i = |T (x_i − c)| − radius``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["LeastSquaresResult", "TRIU", "levenberg_marquardt", "sphere_residuals", "symmetric_from"]

#: the upper-triangle index order of the six terms of a symmetric 3 × 3 matrix
TRIU = np.triu_indices(3)

ResidualsAndJacobian = Callable[[np.ndarray], "tuple[np.ndarray, np.ndarray]"]


@dataclass(frozen=True)
class LeastSquaresResult:
    """Outcome of :func:`levenberg_marquardt`.

    x: (P,) parameters at the end; residuals: (M,) there; jacobian: (M, P) there; cost:
    ½·Σ residuals²; iterations: Jacobian evaluations; converged: a tolerance was met (False:
    the iteration budget ran out or no step reduced the cost); message: which.
    """

    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost: float
    iterations: int
    converged: bool
    message: str


def levenberg_marquardt(
    residuals_and_jacobian: ResidualsAndJacobian,
    x0: np.ndarray,
    *,
    max_iterations: int = 200,
    xtol: float = 1e-12,
    ftol: float = 1e-14,
    gtol: float = 1e-14,
) -> LeastSquaresResult:
    """Minimises ½·Σ r(x)² from ``x0`` by Levenberg–Marquardt.

    residuals_and_jacobian: x (P,) → (r (M,), J (M, P) = ∂r/∂x); M ≥ 1. The damping is
    scaled by the largest diagonal of JᵀJ seen so far (Moré's scaling, as MINPACK's lmder),
    so the solver does not depend on the parameters' units. Stops when a step is shorter
    than ``xtol``·(|x| + xtol), when an accepted step reduces the cost by less than
    ``ftol``·cost, when the residuals are within ``gtol`` (a cosine) of orthogonal to every
    Jacobian column, or after
    ``max_iterations`` evaluations. A trial point whose residuals are not finite counts as a
    rejected step. Raises ValueError when the residuals or Jacobian at ``x0`` are not finite
    or not of matching shapes.
    """
    x = np.array(x0, dtype=float)
    r, J = residuals_and_jacobian(x)
    r, J = np.asarray(r, dtype=float), np.asarray(J, dtype=float)
    if r.ndim != 1 or J.shape != (r.size, x.size):
        raise ValueError(f"residuals (M,) and jacobian (M, {x.size}) expected, got {r.shape} and {J.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(J))):
        raise ValueError("the residuals or the jacobian at the start point are not finite")
    cost = 0.5 * float(r @ r)
    scale = np.maximum(np.einsum("ij,ij->j", J, J), np.finfo(float).tiny)
    damping = 1e-3
    growth = 2.0
    iterations = 1
    message = f"no convergence within {max_iterations} evaluations"
    converged = False
    while iterations < max_iterations:
        gradient = J.T @ r
        normal = J.T @ J
        # MINPACK's gtol: the cosine between the residuals and every Jacobian column
        column_norms = np.sqrt(np.diag(normal))
        residual_norm = float(np.linalg.norm(r))
        if residual_norm == 0.0 or np.all(np.abs(gradient) <= gtol * residual_norm * column_norms):
            converged, message = True, "gradient below gtol"
            break
        scale = np.maximum(scale, np.diag(normal))
        try:
            step = np.linalg.solve(normal + damping * np.diag(scale), -gradient)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(normal + damping * np.diag(scale), -gradient, rcond=None)[0]
        if np.linalg.norm(step) <= xtol * (np.linalg.norm(x) + xtol):
            converged, message = True, "step below xtol"
            break
        trial = x + step
        r_trial, J_trial = residuals_and_jacobian(trial)
        iterations += 1
        r_trial, J_trial = np.asarray(r_trial, dtype=float), np.asarray(J_trial, dtype=float)
        finite = bool(np.all(np.isfinite(r_trial)) and np.all(np.isfinite(J_trial)))
        cost_trial = 0.5 * float(r_trial @ r_trial) if finite else np.inf
        # the reduction the local linear model promises for this step (positive)
        predicted = -float(step @ gradient) - 0.5 * float(step @ normal @ step)
        gain = (cost - cost_trial) / predicted if predicted > 0 else -1.0
        if gain > 0:
            reduction = cost - cost_trial
            x, r, J, cost = trial, r_trial, J_trial, cost_trial
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)  # Nielsen's update
            growth = 2.0
            if reduction <= ftol * cost:
                converged, message = True, "cost reduction below ftol"
                break
        else:
            damping *= growth
            growth *= 2.0
            if not np.isfinite(damping) or damping > 1e16:
                message = "no step reduces the cost"
                break
    return LeastSquaresResult(x, r, J, cost, iterations, converged, message)


def symmetric_from(terms: np.ndarray) -> np.ndarray:
    """The symmetric 3 × 3 matrix of six upper-triangle ``terms`` (:data:`TRIU` order)."""
    T = np.zeros((3, 3))
    T[TRIU] = terms
    return T + np.triu(T, 1).T


def sphere_residuals(points: np.ndarray, radius: float) -> ResidualsAndJacobian:
    """Residuals |T (x_i − c)| − radius and their Jacobian for :func:`levenberg_marquardt`.

    points: (N, 3) rows x_i, in any unit; radius in that unit after T. The parameters are
    [c (3,), the six terms of T in :data:`TRIU` order].
    """
    x = np.asarray(points, dtype=float)
    rows, cols = TRIU

    def evaluate(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = symmetric_from(p[3:])
        y = x - p[:3]
        v = y @ T  # T symmetric: row i is T·y_i
        norm = np.linalg.norm(v, axis=1)
        u = v / np.where(norm > 0, norm, 1.0)[:, None]  # ∂|v|/∂v; 0 where v = 0
        J = np.empty((x.shape[0], 9))
        J[:, :3] = -(u @ T)
        # a diagonal term moves one component of v, an off-diagonal term two
        J[:, 3:] = u[:, rows] * y[:, cols] + np.where(rows != cols, u[:, cols] * y[:, rows], 0.0)
        return norm - radius, J

    return evaluate
