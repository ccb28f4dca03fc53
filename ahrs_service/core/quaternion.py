"""Quaternions and rotations shared by every part of the service.

Conventions (docs/design.md): Hamilton quaternions ordered [w, x, y, z], unit norm,
rotating body-frame (FRD) vectors into the earth frame (NED): v_earth = q ⊗ v_body ⊗ q*.
Euler angles are the aerospace ZYX sequence (yaw, pitch, roll) in radians.

Two flavours live here:

* compiled scalar helpers (``quat_mul``, ``quat_rotate`` …) that take and return plain
  tuples of floats. They are numba ``njit`` functions, inlined into the estimator kernels,
  so the hot per-sample path never allocates. They also work when called from Python.
* vectorised NumPy helpers (``*_array``) over (N, 4) arrays, for analysis, logs and tests.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

Quat = tuple[float, float, float, float]
Vec3 = tuple[float, float, float]

_jit = njit(cache=True, inline="always", fastmath=False)


# --------------------------------------------------------------------------- compiled scalars


@_jit
def quat_mul(p, q):
    """Hamilton product p ⊗ q of two [w, x, y, z] tuples."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


@_jit
def quat_conj(q):
    """Conjugate (the inverse of a unit quaternion)."""
    return (q[0], -q[1], -q[2], -q[3])


@_jit
def quat_normalize(q):
    """q / |q|; identity if the norm is zero or not finite."""
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not (n > 1e-300) or not math.isfinite(n):
        return (1.0, 0.0, 0.0, 0.0)
    return (q[0] / n, q[1] / n, q[2] / n, q[3] / n)


@_jit
def quat_rotate(q, v):
    """R(q) v: a body-frame vector expressed in the earth frame."""
    w, x, y, z = q
    vx, vy, vz = v
    # v + 2 w (u × v) + 2 u × (u × v), u = (x, y, z)
    tx = 2.0 * (y * vz - z * vy)
    ty = 2.0 * (z * vx - x * vz)
    tz = 2.0 * (x * vy - y * vx)
    return (
        vx + w * tx + (y * tz - z * ty),
        vy + w * ty + (z * tx - x * tz),
        vz + w * tz + (x * ty - y * tx),
    )


@_jit
def quat_rotate_inv(q, v):
    """R(q)ᵀ v: an earth-frame vector expressed in the body frame."""
    return quat_rotate((q[0], -q[1], -q[2], -q[3]), v)


@_jit
def quat_from_rotvec(rx, ry, rz):
    """exp of a rotation vector (axis · angle, rad) as a unit quaternion."""
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-8:
        # second-order series keeps the result unit to machine precision
        return quat_normalize((1.0 - angle * angle / 8.0, 0.5 * rx, 0.5 * ry, 0.5 * rz))
    s = math.sin(0.5 * angle) / angle
    return (math.cos(0.5 * angle), rx * s, ry * s, rz * s)


@_jit
def quat_integrate(q, wx, wy, wz, dt):
    """q(t+dt) for body angular rate ω (rad/s) held constant over dt: q ⊗ exp(ω dt / 2)."""
    return quat_normalize(quat_mul(q, quat_from_rotvec(wx * dt, wy * dt, wz * dt)))


@_jit
def quat_from_matrix(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Quaternion of a rotation matrix (row-major entries), Shepperd's method, w ≥ 0."""
    tr = r00 + r11 + r22
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(1.0 + r11 - r00 - r22)
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 + r22 - r00 - r11)
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    if q[0] < 0.0:
        q = (-q[0], -q[1], -q[2], -q[3])
    return quat_normalize(q)


@_jit
def quat_from_euler(roll, pitch, yaw):
    """Quaternion of ZYX Euler angles (rad): q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


@_jit
def quat_to_euler(q):
    """ZYX Euler angles (roll, pitch, yaw) in rad of a unit quaternion; yaw in (−π, π].
    A NaN component gives NaN angles (the rounding clamp of the pitch keeps NaN)."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    sp = 2.0 * (w * y - z * x)
    pitch = math.asin(1.0 if sp > 1.0 else -1.0 if sp < -1.0 else sp)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    if yaw == -math.pi:
        yaw = math.pi
    return (roll, pitch, yaw)


#: ``quat_to_euler`` for callers in plain Python (telemetry, log messages): the same code,
#: interpreted, because the compiled call's type check of a tuple argument costs more than
#: the formula.
euler_of = quat_to_euler.py_func


@_jit
def vec_norm(v):
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


@_jit
def vec_cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@_jit
def vec_dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@_jit
def vec_scale(v, s):
    return (v[0] * s, v[1] * s, v[2] * s)


@_jit
def vec_is_usable(x, y, z):
    """True for a finite, non-zero vector: the test every sensor correction passes first."""
    n2 = x * x + y * y + z * z
    return math.isfinite(n2) and n2 > 1e-12


@_jit
def quat_from_down_and_field(d, m):
    """q_earth←body from the body's unit "down" ``d`` and magnetic field ``m`` (any scale).

    East = d × m, north = east × d: the rows of R_earth←body, heading against magnetic north.
    Returns (q, ok); ok is False when the field is (nearly) parallel to down.
    """
    e = vec_cross(d, m)
    ne = vec_norm(e)
    if not ne > 1e-6 * vec_norm(m):
        return (1.0, 0.0, 0.0, 0.0), False
    e = vec_scale(e, 1.0 / ne)
    nn = vec_cross(e, d)
    return quat_from_matrix(nn[0], nn[1], nn[2], e[0], e[1], e[2], d[0], d[1], d[2]), True


@_jit
def quat_from_gravity_and_field(ax, ay, az, mx, my, mz, use_field):
    """Attitude from one accelerometer (specific force) and optionally one magnetometer sample.

    Down in the body frame is −f/|f|; with a field, east = down × m and north = east × down
    (heading against magnetic north). Without it, yaw is zero. The rows of R_earth←body are
    north, east and down expressed in the body frame.
    """
    n = math.sqrt(ax * ax + ay * ay + az * az)
    if use_field:
        q, ok = quat_from_down_and_field((-ax / n, -ay / n, -az / n), (mx, my, mz))
        if ok:
            return q
    roll = math.atan2(-ay, -az)
    pitch = math.atan2(ax, math.sqrt(ay * ay + az * az))
    return quat_from_euler(roll, pitch, 0.0)


# --------------------------------------------------------------------------- NumPy, (N, 4) arrays

#: q_enu←ned: maps NED components (x_N, y_N, z_N) to ENU (y_N, x_N, −z_N) — 180° about (1, 1, 0)/√2.
Q_NED_TO_ENU = np.array([0.0, math.sqrt(0.5), math.sqrt(0.5), 0.0])


def quat_mul_array(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Row-wise Hamilton product of (N, 4) or (4,) arrays, broadcast."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def vecs_are_usable(v: np.ndarray) -> np.ndarray:
    """(N,) :func:`vec_is_usable` of each row of ``v`` (N, 3)."""
    v = np.asarray(v, dtype=np.float64)
    n2 = np.sum(v * v, axis=1)
    return np.isfinite(n2) & (n2 > 1e-12)


def quat_conj_array(q: np.ndarray) -> np.ndarray:
    """Conjugate of (N, 4) quaternions."""
    return np.asarray(q, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])


def quat_rotate_array(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """R(q) v row-wise: body vectors (N, 3) into the earth frame."""
    q = np.asarray(q, dtype=float)
    v = np.asarray(v, dtype=float)
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + q[..., :1] * t + np.cross(u, t)


def euler_from_quat_array(q: np.ndarray) -> np.ndarray:
    """(N, 3) ZYX Euler angles [roll, pitch, yaw] in rad of (N, 4) quaternions."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    roll = np.arctan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2.0 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    yaw = np.where(yaw == -np.pi, np.pi, yaw)
    return np.stack([roll, pitch, yaw], axis=-1)


def quat_from_euler_array(euler: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions of (N, 3) ZYX Euler angles [roll, pitch, yaw] in rad."""
    roll, pitch, yaw = np.moveaxis(np.asarray(euler, dtype=float), -1, 0)
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def quat_to_matrix_array(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices R_earth←body of (N, 4) quaternions."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=float), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def quat_from_rotvec_array(r: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions of (N, 3) rotation vectors (rad)."""
    r = np.asarray(r, dtype=float)
    angle = np.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * angle
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 0, angle, 1.0), 0.5)
    return np.concatenate([np.cos(half), r * s], axis=-1)


def quat_to_rotvec_array(q: np.ndarray) -> np.ndarray:
    """(…, 3) rotation vectors (rad, the shortest way: angle ≤ π) of (…, 4) unit quaternions;
    the inverse of :func:`quat_from_rotvec_array`. NaN quaternions give NaN vectors."""
    q = np.asarray(q, dtype=float)
    q = np.where(q[..., :1] < 0.0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        # 2·atan2(|v|, w)·v/|v|, with its limit 2·v/w for a vanishing angle (NaN w stays NaN)
        scale = np.where(s > 1e-12, 2.0 * np.arctan2(s, q[..., :1]) / np.where(s > 1e-12, s, 1.0), 2.0 / q[..., :1])
    return v * scale


def quat_angle_array(q: np.ndarray) -> np.ndarray:
    """Rotation angle (rad, in [0, π]) of each (N, 4) unit quaternion."""
    w = np.abs(np.asarray(q, dtype=float)[..., 0])
    return 2.0 * np.arccos(np.clip(w, 0.0, 1.0))


def ned_to_enu_array(q_ned: np.ndarray) -> np.ndarray:
    """q_earth←body in NED turned into the same attitude against ENU: q_enu = q_ned→enu ⊗ q_ned."""
    return quat_mul_array(Q_NED_TO_ENU, q_ned)
