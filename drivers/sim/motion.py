"""Rigid-body motion for the simulator: attitude, angular rate, specific force and field.

A :class:`Trajectory` gives the true state of the body at any time ``t`` (seconds from the
start of the simulation). Earth frame NED, body frame FRD, quaternions q_earth←body
[w, x, y, z] (see docs/design.md).

The angular rate and the specific force are the *exact* derivatives of the attitude and the
position (analytic, not finite differences), so an estimator fed a perfect simulated IMU
sees a consistent motion:

* ``omega_body`` satisfies q̇ = ½ q ⊗ (0, ω);
* ``specific_force_body`` = Rᵀ (a_earth − g_earth) with g_earth = (0, 0, g): a level body at
  rest reads (0, 0, −g);
* ``mag_body`` = Rᵀ B_earth.

Built-in trajectories: :class:`StaticTrajectory`, :class:`ValidationManoeuvre` (the first
paper's ±90° rotations about x, y and z), :class:`FigureEight` (a flight with banked turns),
:class:`WaypointTrajectory` (attitude/position keyframes) and :class:`FunctionTrajectory` (any
callable). :func:`profile` builds the first three (and waypoints) by name for the config.
"""

from __future__ import annotations

import abc
import bisect
import inspect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ahrs_service.core.quaternion import (
    quat_conj,
    quat_from_euler,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotate_inv,
)

#: standard gravity used by the simulator, m/s²
GRAVITY = 9.81
#: default earth field, NED, µT: 20 north, 0 east, 45 down (as tests/analytic.py)
FIELD_NED = (20.0, 0.0, 45.0)


@dataclass
class MotionState:
    """True state of the body at time ``t``.

    t: s. q: (4,) q_earth←body [w, x, y, z], NED/FRD. omega_body: (3,) rad/s in FRD.
    specific_force_body: (3,) m/s², Rᵀ(a − g), level at rest (0, 0, −g).
    mag_body: (3,) µT, the earth field in FRD. position, velocity, acceleration: (3,) NED,
    m, m/s, m/s² (kinematic acceleration, gravity not included).
    """

    t: float
    q: np.ndarray
    omega_body: np.ndarray
    specific_force_body: np.ndarray
    mag_body: np.ndarray
    position: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))


Kinematics = tuple[tuple[float, float, float, float], Any, Any, Any, Any]


class Trajectory(abc.ABC):
    """A motion of the body over time.

    duration: s, or ``math.inf`` for an endless motion. With ``looping=True`` a finite
    trajectory restarts after ``duration`` (state(t) = state(t mod duration)), so a service
    can run on it forever; without it, what happens after the end is the subclass's choice
    (the keyframe trajectories stay at rest in their last pose).
    field_ned: earth magnetic field, NED, µT. gravity: m/s², pointing down (+z NED).
    """

    duration: float = math.inf

    def __init__(
        self,
        *,
        field_ned: Sequence[float] = FIELD_NED,
        gravity: float = GRAVITY,
        looping: bool = False,
    ) -> None:
        f = np.asarray(field_ned, dtype=float)
        if f.shape != (3,) or not np.isfinite(f).all():
            raise ValueError(f"field_ned must be 3 finite numbers (µT, NED), got {field_ned!r}")
        if not (math.isfinite(gravity) and gravity >= 0.0):
            raise ValueError(f"gravity must be a finite number >= 0 (m/s²), got {gravity!r}")
        self.field_ned = (float(f[0]), float(f[1]), float(f[2]))
        self.gravity = float(gravity)
        self.looping = bool(looping)

    @abc.abstractmethod
    def _kinematics(self, t: float) -> Kinematics:
        """(q tuple, omega_body, position, velocity, acceleration) at local time t."""

    def state(self, t: float) -> MotionState:
        """True state at simulation time ``t`` (s, ≥ 0)."""
        if not t >= 0.0:
            raise ValueError(f"t must be a time >= 0 s, got {t!r}")
        local = t
        if self.looping and math.isfinite(self.duration) and self.duration > 0:
            local = math.fmod(t, self.duration)
        q, omega, pos, vel, acc = self._kinematics(local)
        q = quat_normalize(q)
        f = quat_rotate_inv(q, (float(acc[0]), float(acc[1]), float(acc[2]) - self.gravity))
        m = quat_rotate_inv(q, self.field_ned)
        return MotionState(
            t=float(t),
            q=np.array(q),
            omega_body=np.asarray(omega, dtype=float),
            specific_force_body=np.array(f),
            mag_body=np.array(m),
            position=np.asarray(pos, dtype=float),
            velocity=np.asarray(vel, dtype=float),
            acceleration=np.asarray(acc, dtype=float),
        )


# --------------------------------------------------------------------------- static


class StaticTrajectory(Trajectory):
    """At rest in one attitude: ZYX Euler angles roll, pitch, yaw in rad; position NED in m."""

    def __init__(
        self,
        roll: float = 0.0,
        pitch: float = 0.0,
        yaw: float = 0.0,
        *,
        position: Sequence[float] = (0.0, 0.0, 0.0),
        duration: float = math.inf,
        **kw: Any,
    ) -> None:
        super().__init__(**kw)
        self.duration = _positive_duration(duration)
        self._q = quat_from_euler(float(roll), float(pitch), float(yaw))
        self._p = _vec3(position, "position")

    def _kinematics(self, t: float) -> Kinematics:
        return self._q, np.zeros(3), self._p, np.zeros(3), np.zeros(3)


# --------------------------------------------------------------------------- keyframes


def min_jerk(u: float) -> tuple[float, float, float]:
    """Minimum-jerk profile s(u) = 10u³ − 15u⁴ + 6u⁵ on u ∈ [0, 1] and its first two derivatives.

    Starts and ends with zero velocity and acceleration, so motions built from it join at rest
    without jumps in angular rate or specific force.
    """
    u = min(1.0, max(0.0, u))
    u2 = u * u
    return (
        u2 * u * (10.0 - 15.0 * u + 6.0 * u2),
        30.0 * u2 * (1.0 - 2.0 * u + u2),
        60.0 * u * (1.0 - 3.0 * u + 2.0 * u2),
    )


def _rotvec_of(q: tuple[float, float, float, float]) -> np.ndarray:
    """Rotation vector (rad) of a unit quaternion, shortest way (angle ≤ π)."""
    w, x, y, z = q
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-12:
        return np.array([2.0 * x, 2.0 * y, 2.0 * z])
    angle = 2.0 * math.atan2(s, w)
    return np.array([x, y, z]) * (angle / s)


class SegmentTrajectory(Trajectory):
    """A chain of smooth moves from a start pose.

    Each step ``(T, rotvec, dp)`` rotates the body by ``rotvec`` (rad, axis in the body frame
    at the start of the step) and translates it by ``dp`` (m, NED) in ``T`` seconds, both
    along a minimum-jerk profile s(t): q(t) = q_i ⊗ exp(s·rotvec), ω_body = ṡ·rotvec,
    p(t) = p_i + s·dp, a = s̈·dp. A step with zero rotation and translation is a hold. The
    body is at rest at every keyframe; after the last one it stays there.
    """

    def __init__(
        self,
        start_q: Sequence[float],
        start_position: Sequence[float],
        steps: Sequence[tuple[float, Sequence[float], Sequence[float]]],
        **kw: Any,
    ) -> None:
        super().__init__(**kw)
        if not steps:
            raise ValueError("a segment trajectory needs at least one step")
        q = quat_normalize(tuple(float(v) for v in _vec(start_q, 4, "start_q")))
        p = _vec3(start_position, "start_position")
        self._t0: list[float] = []
        self._seg: list[tuple[float, tuple, np.ndarray, np.ndarray, np.ndarray]] = []
        t = 0.0
        for i, (T, rv, dp) in enumerate(steps):
            T = float(T)
            if not (math.isfinite(T) and T > 0.0):
                raise ValueError(f"step {i}: duration must be > 0 s, got {T!r}")
            rv = _vec3(rv, f"step {i} rotvec")
            dp = _vec3(dp, f"step {i} dp")
            self._t0.append(t)
            self._seg.append((T, q, p, rv, dp))
            q = quat_normalize(quat_mul(q, quat_from_rotvec(*rv)))
            p = p + dp
            t += T
        self._end = (q, p)
        self.duration = t
        #: start times of the keyframes (s): the body is at rest at each of them
        self.keyframe_times = [*self._t0, t]

    def _kinematics(self, t: float) -> Kinematics:
        if t >= self.duration:
            return self._end[0], np.zeros(3), self._end[1], np.zeros(3), np.zeros(3)
        i = bisect.bisect_right(self._t0, t) - 1
        T, q0, p0, rv, dp = self._seg[i]
        s, ds, dds = min_jerk((t - self._t0[i]) / T)
        q = quat_mul(q0, quat_from_rotvec(*(rv * s)))
        return q, rv * (ds / T), p0 + dp * s, dp * (ds / T), dp * (dds / (T * T))


class WaypointTrajectory(SegmentTrajectory):
    """Smooth motion through attitude and position keyframes.

    times: (N,) strictly increasing keyframe times in s, the first one 0.
    attitudes: (N, 3) ZYX Euler angles [roll, pitch, yaw] in rad, or (N, 4) quaternions
        q_earth←body [w, x, y, z]. Between keyframes the attitude turns the shortest way
        about a fixed axis, along a minimum-jerk profile, so the body is at rest at each
        keyframe (exact derivatives throughout).
    positions: (N, 3) NED in m, or None to stay at the origin.
    """

    def __init__(
        self,
        times: Sequence[float],
        attitudes: Sequence[Sequence[float]],
        positions: Sequence[Sequence[float]] | None = None,
        **kw: Any,
    ) -> None:
        t = np.asarray(times, dtype=float)
        att = np.asarray(attitudes, dtype=float)
        if t.ndim != 1 or len(t) < 2:
            raise ValueError("times must list at least two keyframe times (s)")
        if t[0] != 0.0 or not (np.diff(t) > 0).all() or not np.isfinite(t).all():
            raise ValueError(f"times must start at 0 and increase strictly, got {t.tolist()}")
        if att.ndim != 2 or att.shape[0] != len(t) or att.shape[1] not in (3, 4):
            raise ValueError(f"attitudes must be (N, 3) Euler rad or (N, 4) quaternions, N={len(t)}")
        if positions is None:
            pos = np.zeros((len(t), 3))
        else:
            pos = np.asarray(positions, dtype=float)
            if pos.shape != (len(t), 3):
                raise ValueError(f"positions must be (N, 3) in m, N={len(t)}; got {pos.shape}")
        if att.shape[1] == 3:
            quats = [quat_from_euler(*map(float, a)) for a in att]
        else:
            quats = [quat_normalize(tuple(map(float, a))) for a in att]
        steps = []
        for i in range(len(t) - 1):
            rel = quat_mul(quat_conj(quats[i]), quats[i + 1])
            steps.append((t[i + 1] - t[i], _rotvec_of(rel), pos[i + 1] - pos[i]))
        super().__init__(quats[0], pos[0], steps, **kw)

    @classmethod
    def from_keyframes(cls, keyframes: Sequence[dict[str, Any]], **kw: Any) -> "WaypointTrajectory":
        """From config-style keyframes: [{"t": s, "rpy_deg": [r, p, y], "position": [n, e, d]}, …]."""
        allowed = {"t", "rpy_deg", "position"}
        times, att, pos = [], [], []
        for i, k in enumerate(keyframes):
            unknown = set(k) - allowed
            if unknown:
                raise ValueError(f"keyframe {i}: unknown key(s) {sorted(unknown)}; allowed {sorted(allowed)}")
            for key in ("t", "rpy_deg"):
                if key not in k:
                    raise ValueError(f"keyframe {i}: missing key {key!r}")
            times.append(k["t"])
            att.append(np.radians(_vec3(k["rpy_deg"], f"keyframe {i} rpy_deg")))
            pos.append(_vec3(k.get("position", (0.0, 0.0, 0.0)), f"keyframe {i} position"))
        return cls(times, att, pos, **kw)


class ValidationManoeuvre(SegmentTrajectory):
    """The first paper's validation motion (§6.1): from rest, rotate to +90° and then to −90°
    about the body x axis, back to 0, then the same about y, then about z.

    hold: s at rest before the first move and after every move. move: s for a 90° turn (the
    +90° → −90° swing takes twice as long). amplitude_deg: the turn angle (90). axes: the
    order of the axes. start: ZYX Euler angles (rad) of the rest attitude. Each turn follows
    a minimum-jerk profile; ``phases`` names the time span of each hold.
    """

    def __init__(
        self,
        *,
        hold: float = 2.0,
        move: float = 2.0,
        amplitude_deg: float = 90.0,
        axes: str = "xyz",
        start: Sequence[float] = (0.0, 0.0, 0.0),
        **kw: Any,
    ) -> None:
        if not axes or set(axes) - set("xyz"):
            raise ValueError(f"axes must be letters from 'xyz', got {axes!r}")
        if not (math.isfinite(amplitude_deg) and 0.0 < amplitude_deg <= 180.0):
            raise ValueError(f"amplitude_deg must be in (0, 180], got {amplitude_deg!r}")
        a = math.radians(amplitude_deg)
        zero = (0.0, 0.0, 0.0)
        steps: list[tuple[float, Sequence[float], Sequence[float]]] = [(hold, zero, zero)]
        self.phases: list[tuple[str, float, float]] = []
        t = hold
        for ax in axes:
            e = np.eye(3)["xyz".index(ax)]
            for name, angle, T in (("+", a, move), ("-", -2.0 * a, 2.0 * move), ("0", a, move)):
                steps += [(T, e * angle, zero), (hold, zero, zero)]
                t += T
                label = f"{ax}{'0' if name == '0' else name + f'{amplitude_deg:g}'}"
                self.phases.append((label, t, t + hold))
                t += hold
        super().__init__(quat_from_euler(*map(float, start)), zero, steps, **kw)


# --------------------------------------------------------------------------- figure eight


class FigureEight(Trajectory):
    """A flight along a figure eight (lemniscate of Gerono) with banked, coordinated turns.

    Position, NED, m: n = L sin ωt, e = W sin 2ωt, d = −altitude − C sin ωt, ω = 2π/period.
    The speed changes along the path (linear accelerations of a few m/s²); the body points
    along the horizontal velocity (yaw), pitches with the flight-path angle, and banks by
    atan(a_lateral / (g − a_down)) as in a coordinated turn. Angular rates come from the
    analytic Euler-angle rates (jerk of the path), so they are exact.

    length, width: half-extents north and east, m. period: s per lap. altitude: m above the
    origin. climb: vertical amplitude C, m. laps: number of laps (duration = laps · period),
    None for endless. The path is periodic, so it simply continues past ``duration``.
    """

    def __init__(
        self,
        *,
        length: float = 30.0,
        width: float = 15.0,
        period: float = 20.0,
        altitude: float = 10.0,
        climb: float = 2.0,
        laps: float | None = None,
        **kw: Any,
    ) -> None:
        super().__init__(**kw)
        for name, v in (("length", length), ("width", width), ("period", period)):
            if not (math.isfinite(v) and v > 0.0):
                raise ValueError(f"{name} must be > 0, got {v!r}")
        self.length, self.width, self.period = float(length), float(width), float(period)
        self.altitude, self.climb = float(altitude), float(climb)
        self.duration = math.inf if laps is None else _positive_duration(laps * self.period)

    def _path(self, t: float) -> tuple[tuple[float, float, float], ...]:
        """Position and its first three derivatives (NED) at time t, as Python floats: the
        scalar algebra of :meth:`_kinematics` costs a third of what it does on numpy's
        float64 scalars (the same IEEE operations, the same bits)."""
        w = 2.0 * math.pi / self.period
        L, W, C = self.length, self.width, self.climb
        s1, c1 = math.sin(w * t), math.cos(w * t)
        s2, c2 = math.sin(2 * w * t), math.cos(2 * w * t)
        p = (L * s1, W * s2, -self.altitude - C * s1)
        v = (L * w * c1, 2 * W * w * c2, -C * w * c1)
        a = (-L * w * w * s1, -4 * W * w * w * s2, C * w * w * s1)
        j = (-L * w**3 * c1, -8 * W * w**3 * c2, C * w**3 * c1)
        return p, v, a, j

    def _kinematics(self, t: float) -> Kinematics:
        p, v, a, j = self._path(t)
        g = self.gravity
        vh2 = v[0] * v[0] + v[1] * v[1]
        vh = math.sqrt(vh2)
        vh_dot = (v[0] * a[0] + v[1] * a[1]) / vh
        # heading of the horizontal velocity and its rate
        yaw = math.atan2(v[1], v[0])
        turn = v[0] * a[1] - v[1] * a[0]
        yaw_dot = turn / vh2
        # bank: lateral (rightward) acceleration against the effective vertical
        a_lat = turn / vh
        a_lat_dot = ((v[0] * j[1] - v[1] * j[0]) * vh - turn * vh_dot) / vh2
        den, den_dot = g - a[2], -j[2]
        roll = math.atan2(a_lat, den)
        roll_dot = (a_lat_dot * den - a_lat * den_dot) / (a_lat * a_lat + den * den)
        # pitch: flight-path angle (nose up when climbing, i.e. v_down < 0)
        pitch = math.atan2(-v[2], vh)
        pitch_dot = (-a[2] * vh + v[2] * vh_dot) / (v[2] * v[2] + vh2)
        sr, cr = math.sin(roll), math.cos(roll)
        sp, cp = math.sin(pitch), math.cos(pitch)
        # ZYX Euler-angle rates to body rates
        omega = np.array(
            [
                roll_dot - yaw_dot * sp,
                pitch_dot * cr + yaw_dot * sr * cp,
                -pitch_dot * sr + yaw_dot * cr * cp,
            ]
        )
        return quat_from_euler(roll, pitch, yaw), omega, p, v, a


# --------------------------------------------------------------------------- user callable


class FunctionTrajectory(Trajectory):
    """A user-defined motion from callables of time t (s).

    attitude(t) -> q_earth←body [w, x, y, z]; position(t) -> NED m (None: at the origin).
    angular_rate(t) -> body rad/s and acceleration(t) -> NED m/s² (kinematic) should be the
    exact derivatives when you have them; when omitted they are computed by fourth-order
    central differences with step ``h`` (s) — accurate to ~1e-8 for smooth motions, but no
    longer exact, and the callables are then also evaluated at t ± 2h (slightly negative t
    near the start).
    """

    def __init__(
        self,
        attitude: Callable[[float], Sequence[float]],
        position: Callable[[float], Sequence[float]] | None = None,
        *,
        duration: float = math.inf,
        angular_rate: Callable[[float], Sequence[float]] | None = None,
        acceleration: Callable[[float], Sequence[float]] | None = None,
        h: float = 1e-3,
        **kw: Any,
    ) -> None:
        super().__init__(**kw)
        self.duration = _positive_duration(duration)
        self._att, self._pos = attitude, position
        self._rate, self._acc = angular_rate, acceleration
        self._h = float(h)

    def _q(self, t: float) -> tuple[float, float, float, float]:
        return quat_normalize(tuple(float(v) for v in _vec(self._att(t), 4, "attitude(t)")))

    def _p(self, t: float) -> np.ndarray:
        return np.zeros(3) if self._pos is None else _vec3(self._pos(t), "position(t)")

    def _kinematics(self, t: float) -> Kinematics:
        h = self._h
        q = self._q(t)
        if self._rate is not None:
            omega = _vec3(self._rate(t), "angular_rate(t)")
        else:
            qa = np.array(q)
            # neighbours on the same hemisphere as q(t): q and −q are the same attitude
            nb = [np.array(self._q(t + k * h)) for k in (-2, -1, 1, 2)]
            nb = [x if x @ qa >= 0 else -x for x in nb]
            qd = (nb[0] - 8 * nb[1] + 8 * nb[2] - nb[3]) / (12 * h)
            # q̇ = ½ q ⊗ (0, ω)  ⇒  (0, ω) = 2 q* ⊗ q̇
            omega = 2.0 * np.array(quat_mul(quat_conj(q), tuple(qd)))[1:]
        p = self._p(t)
        if self._pos is None:
            v = a = np.zeros(3)
        else:
            pm2, pm1, pp1, pp2 = (self._p(t + k * h) for k in (-2, -1, 1, 2))
            v = (pm2 - 8 * pm1 + 8 * pp1 - pp2) / (12 * h)
            a = (-pm2 + 16 * pm1 - 30 * p + 16 * pp1 - pp2) / (12 * h * h)
        if self._acc is not None:
            a = _vec3(self._acc(t), "acceleration(t)")
        return q, omega, p, v, a


# --------------------------------------------------------------------------- by name

_PROFILES: dict[str, type[Trajectory]] = {
    "static": StaticTrajectory,
    "validation": ValidationManoeuvre,
    "figure8": FigureEight,
}


class Vibrating(Trajectory):
    """``base`` with a sinusoidal linear vibration added along the body axes: the specific
    force on body axis i gains ``amplitude_mss[i]``·sin(2π·``frequency_hz``·t) (m/s²), as a
    motor's vibration shakes the airframe (the gyroscope does not see it; the displacement,
    amplitude / (2π f)², below a millimetre at the rates that matter, is left out of the
    position). The kinematic acceleration (NED) carries the same vibration rotated to NED. It
    loops when ``base`` does (``base.state`` folds the time; the vibration runs on)."""

    def __init__(self, base: Trajectory, amplitude_mss: Sequence[float], frequency_hz: float) -> None:
        super().__init__(field_ned=base.field_ned, gravity=base.gravity, looping=base.looping)
        self.base = base
        self.duration = base.duration
        self.amplitude = _vec3(amplitude_mss, "amplitude_mss")
        if not (math.isfinite(frequency_hz) and frequency_hz >= 0.0):
            raise ValueError(f"frequency_hz must be a finite number >= 0, got {frequency_hz!r}")
        self.frequency_hz = float(frequency_hz)

    def _kinematics(self, t: float) -> Kinematics:  # pragma: no cover - state() is overridden
        raise NotImplementedError

    def state(self, t: float) -> MotionState:
        s = self.base.state(t)
        shake = self.amplitude * math.sin(2.0 * math.pi * self.frequency_hz * t)
        s.specific_force_body = s.specific_force_body + shake
        s.acceleration = s.acceleration + np.asarray(quat_rotate(tuple(s.q), tuple(shake)))
        return s


def profile_names() -> list[str]:
    """Names accepted by :func:`profile`."""
    return [*_PROFILES, "waypoints"]


def profile(name: str, **kw: Any) -> Trajectory:
    """A built-in trajectory by name: "static", "validation", "figure8" or "waypoints".

    ``kw`` are the class's keyword arguments (e.g. ``profile("static", roll=0.3)``,
    ``profile("figure8", period=30, looping=True)``; "waypoints" takes ``keyframes`` as in
    :meth:`WaypointTrajectory.from_keyframes`). Unknown names or keywords raise ValueError.
    """
    if name == "waypoints":
        if "keyframes" not in kw:
            raise ValueError("profile 'waypoints' needs the key 'keyframes'")
        kf = kw.pop("keyframes")
        _check_kwargs(WaypointTrajectory, kw, name, extra=("keyframes",))
        return WaypointTrajectory.from_keyframes(kf, **kw)
    try:
        cls = _PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown trajectory profile {name!r}; available: {', '.join(profile_names())}") from None
    _check_kwargs(cls, kw, name)
    return cls(**kw)


def _check_kwargs(cls: type, kw: dict[str, Any], name: str, extra: Sequence[str] = ()) -> None:
    # the class's own keywords plus the Trajectory ones it hands on through **kw
    sig = inspect.signature(cls.__init__)
    allowed = {"field_ned", "gravity", "looping", *extra} | {
        p.name
        for p in sig.parameters.values()
        if p.name != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)
    }
    if cls is WaypointTrajectory:
        allowed -= {"times", "attitudes", "positions"}
    unknown = sorted(set(kw) - allowed)
    if unknown:
        raise ValueError(f"profile {name!r}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


# --------------------------------------------------------------------------- helpers


def _vec(v: Any, n: int, what: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != (n,) or not np.isfinite(a).all():
        raise ValueError(f"{what} must be {n} finite numbers, got {v!r}")
    return a


def _vec3(v: Any, what: str) -> np.ndarray:
    return _vec(v, 3, what)


def _positive_duration(d: float) -> float:
    d = float(d)
    if not d > 0.0:
        raise ValueError(f"duration must be > 0 s (or math.inf), got {d!r}")
    return d
