"""ODOMETRY (message 331) out: the attitude (and its variances) in the form an autopilot fuses.

Neither PX4 nor ArduPilot fuses ATTITUDE / ATTITUDE_QUATERNION from a companion; both take
ODOMETRY as external vision. What each handler reads (docs/autopilot.md, "ODOMETRY"):

* **PX4** — ``src/modules/mavlink/mavlink_receiver.cpp``, ``MavlinkReceiver::
  handle_message_odometry``: ``timestamp_sample = _mavlink_timesync.sync_stamp(time_usec)``;
  position only if x, y, z are all finite (then variances from pose_covariance[0, 6, 11]);
  q (body → local) if finite, its variances from pose_covariance[15, 18, 20] unless
  estimator_type is NAIVE; velocity only if finite; rollspeed/pitchspeed/yawspeed if finite;
  reset_counter and quality copied; estimator_type VISION or VIO (or UNKNOWN/NAIVE) go to
  ``vehicle_visual_odometry``, which EKF2 fuses the yaw of when ``EKF2_EV_CTRL`` has the yaw
  bit. frame_id LOCAL_NED makes the pose north-referenced, LOCAL_FRD an arbitrary heading frame.
* **ArduPilot** — ``libraries/GCS_MAVLink/GCS_Common.cpp``, ``GCS_MAVLINK::handle_odometry``:
  anything but frame_id LOCAL_FRD with child_frame_id BODY_FRD is dropped without a word;
  posErr and angErr are taken from pose_covariance only when pose_covariance[0] is not NaN
  (angErr = ∛(σ²_roll² + σ²_pitch² + σ²_yaw²) of entries 15, 18, 20); the position and the
  velocity rotated by q always go on to ``AP_VisualOdom`` (``handle_pose_estimate``,
  ``handle_vision_speed_estimate``), so they must be finite: zero, with a huge variance, and
  ArduPilot told to take only yaw from it (EK3_SRC1_YAW = 6, POSXY/VELXY/POSZ/VELZ not 6).

The quaternion is q_earth←body [w, x, y, z] — MAVLink's "body → local" rotation, the
project's own convention (docs/design.md), so it is the ATTITUDE_QUATERNION's q unchanged.

``pose_covariance`` is the upper triangle of the 6 × 6 covariance of (x, y, z, roll, pitch,
yaw), row by row (21 entries): diagonal entries at 0, 6, 11, 15, 18, 20. Position variances
are ``POSITION_VARIANCE_UNKNOWN`` (finite, so ArduPilot reads the attitude variances; huge, so
no filter would trust a position of zero); cross terms 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

from ahrs_service.core.quaternion import euler_of
from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.timesync import TimeSync

#: where each variance sits in pose_covariance (upper triangle of 6 × 6, row-major)
COV_X, COV_Y, COV_Z, COV_ROLL, COV_PITCH, COV_YAW = 0, 6, 11, 15, 18, 20
#: position (and velocity) variance when position is unknown, m² ((1 km)²)
POSITION_VARIANCE_UNKNOWN = 1e6
#: a yaw variance that says "no information" where NaN cannot be sent (ArduPilot), rad²
YAW_VARIANCE_UNINFORMATIVE = 1e4
#: a heading change between two messages that the gyro does not explain, rad: a jump
HEADING_JUMP_RAD = math.radians(10.0)
#: every attitude variance of a diverged estimate is at least this, rad² (σ = 100 rad: no
#: information, finite so that both autopilots read it; its quality is −1 as well)
DIVERGED_VARIANCE = 1e4
#: the σ that maps to quality 100 (rad); quality falls as 1/σ above it, floor 1
QUALITY_REF_SIGMA = math.radians(2.0)
#: rates accepted for [mavlink.odometry] rate_hz, Hz (PX4 asks for 30–50 Hz external vision)
MIN_RATE_HZ, MAX_RATE_HZ = 1.0, 200.0


@dataclass(frozen=True, slots=True)
class OdometryRules:
    """How one autopilot's ODOMETRY handler wants the fields (see the module docstring).

    name: "px4" or "ardupilot". frame_heading / frame_no_heading: frame_id when the heading
    is (is not) observed. child_frame_id: frame of the velocity (BODY_FRD for both).
    unknown_as_nan: unknown position/velocity/yaw variance sent as NaN (PX4 reads finiteness)
    rather than zero with a huge variance (ArduPilot passes everything on).
    body_rates: rollspeed/pitchspeed/yawspeed filled (PX4 uses them; ArduPilot ignores them,
    and a finite triple is what some of its forks take for a body-velocity message).
    """

    name: str
    frame_heading: int
    frame_no_heading: int
    child_frame_id: int
    unknown_as_nan: bool
    body_rates: bool
    estimator_type: int = mavlink.MAV_ESTIMATOR_TYPE_VISION


PX4 = OdometryRules(
    "px4",
    frame_heading=mavlink.MAV_FRAME_LOCAL_NED,
    frame_no_heading=mavlink.MAV_FRAME_LOCAL_FRD,
    child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
    unknown_as_nan=True,
    body_rates=True,
)
ARDUPILOT = OdometryRules(
    "ardupilot",
    frame_heading=mavlink.MAV_FRAME_LOCAL_FRD,
    frame_no_heading=mavlink.MAV_FRAME_LOCAL_FRD,
    child_frame_id=mavlink.MAV_FRAME_BODY_FRD,
    unknown_as_nan=False,
    body_rates=False,
)
RULES = {r.name: r for r in (PX4, ARDUPILOT)}


@dataclass(frozen=True, slots=True)
class AttitudeEstimate:
    """What one ODOMETRY carries, from the service.

    t_ns: the estimate's sample time, our monotonic clock, ns.
    q: q_earth←body [w, x, y, z] (NED/FRD), as published in ATTITUDE_QUATERNION.
    body_rate: (p, q, r) rad/s about FRD x, y, z, bias removed.
    roll_var, pitch_var, yaw_var: variances of the ZYX angles, rad² (NaN unknown).
    healthy: the estimator is initialised and its estimate fresh; False sends quality −1.
    epoch: bumped by the caller when the estimator restarted (reset, re-initialisation,
        a reference change such as the declination): the ODOMETRY reset_counter goes up.
    diverged: the service's divergence monitor flags the attitude as not trustworthy: quality
        −1 and every attitude variance raised to at least ``DIVERGED_VARIANCE``.
    """

    t_ns: int
    q: Sequence[float]
    body_rate: Sequence[float]
    roll_var: float
    pitch_var: float
    yaw_var: float
    healthy: bool = True
    epoch: int = 0
    diverged: bool = False


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _euler_yaw_rate(q: Sequence[float], rate: Sequence[float]) -> float:
    # ZYX: ψ̇ = (q sin φ + r cos φ) / cos θ
    roll, pitch, _ = euler_of(q)
    cp = max(math.cos(pitch), 1e-3)
    return (rate[1] * math.sin(roll) + rate[2] * math.cos(roll)) / cp


def quality_of(estimate: AttitudeEstimate) -> int:
    """ODOMETRY.quality: −1 failed (not healthy, or flagged diverged), else 1..100 from the
    worst σ that matters (yaw when known, else roll/pitch): 100 at ≤ QUALITY_REF_SIGMA,
    falling as 1/σ."""
    if not estimate.healthy or estimate.diverged:
        return -1
    var = estimate.yaw_var if math.isfinite(estimate.yaw_var) else max(estimate.roll_var, estimate.pitch_var)
    if not math.isfinite(var) or var < 0:
        return 0  # unknown
    sigma = math.sqrt(var)
    return int(max(1, min(100, round(100.0 * QUALITY_REF_SIGMA / max(sigma, 1e-12)))))


@dataclass
class OdometryStats:
    sent: int = 0
    resets: int = 0
    send_errors: int = 0
    not_synced: int = 0  # messages stamped in our clock because TIMESYNC had not converged


@dataclass
class OdometrySender:
    """Builds ODOMETRY at ``rate_hz`` under ``rules`` and hands each to ``send``.

    send: callable taking a pymavlink message (the bridge's endpoints, or the autopilot
        link); its exceptions are counted, never raised.
    timesync: a ``TimeSync`` or anything with its ``synced`` and ``presented_ns`` (beside an
        autopilot: ``AutopilotLink.clock``, which locks for itself); when synced, time_usec is
        in the autopilot's clock, otherwise our monotonic µs.
    Drive with :meth:`tick` from one thread; the schedule is absolute (anchor + k / rate).
    """

    send: Callable[[Any], Any]
    rate_hz: float = 30.0
    rules: OdometryRules = PX4
    timesync: TimeSync | None = None
    stats: OdometryStats = field(default_factory=OdometryStats)
    reset_counter: int = 0
    # the schedule (anchor + k / rate) and the previous message, for the heading-jump test
    _anchor_ns: int | None = field(default=None, init=False, repr=False)
    _k: int = field(default=0, init=False, repr=False)
    _last: AttitudeEstimate | None = field(default=None, init=False, repr=False)
    _last_frame: int | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not (MIN_RATE_HZ <= float(self.rate_hz) <= MAX_RATE_HZ):
            raise ValueError(f"mavlink.odometry.rate_hz must be {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz, got {self.rate_hz!r}")

    def due(self, now_ns: int) -> bool:
        return self._anchor_ns is None or now_ns >= self._next_ns()

    def _next_ns(self) -> int:
        return self._anchor_ns + int(round(self._k * 1e9 / self.rate_hz))  # type: ignore[operator]

    def tick(self, now_ns: int, estimate: AttitudeEstimate | None) -> bool:
        """Sends one ODOMETRY if one is due at ``now_ns`` (monotonic ns); True if sent."""
        if estimate is None or not self.due(now_ns):
            return False
        if self._anchor_ns is None:
            self._anchor_ns, self._k = now_ns, 0
        while self._next_ns() <= now_ns:
            self._k += 1  # slots missed while the loop was late are skipped
        msg = self.encode(estimate)
        try:
            self.send(msg)
        except Exception:  # a link that cannot take it: counted, the loop goes on
            self.stats.send_errors += 1
            return False
        self.stats.sent += 1
        return True

    def _heading_jumped(self, est: AttitudeEstimate, frame: int) -> bool:
        prev = self._last
        if prev is None:
            return False
        if est.epoch != prev.epoch or frame != self._last_frame:
            return True
        dt = (est.t_ns - prev.t_ns) * 1e-9
        if dt <= 0:
            return False
        # the heading change the gyro explains, trapezoid over the two messages' rates
        turned = 0.5 * dt * (_euler_yaw_rate(prev.q, prev.body_rate) + _euler_yaw_rate(est.q, est.body_rate))
        return abs(_wrap(euler_of(est.q)[2] - euler_of(prev.q)[2] - turned)) > HEADING_JUMP_RAD

    def encode(self, est: AttitudeEstimate) -> "mavlink.MAVLink_odometry_message":
        """The ODOMETRY for ``est`` under the rules (updates reset_counter)."""
        r = self.rules
        heading = math.isfinite(est.yaw_var)
        frame = r.frame_heading if heading else r.frame_no_heading
        if self._heading_jumped(est, frame):
            self.reset_counter = (self.reset_counter + 1) % 256
            self.stats.resets += 1
        self._last, self._last_frame = est, frame

        nan = float("nan")
        if r.unknown_as_nan:
            pos = vel = (nan, nan, nan)
            yaw_var = est.yaw_var
            vel_cov = [nan] + [0.0] * 20
        else:
            pos = vel = (0.0, 0.0, 0.0)
            yaw_var = est.yaw_var if heading else YAW_VARIANCE_UNINFORMATIVE
            vel_cov = [0.0] * 21
            vel_cov[0] = vel_cov[6] = vel_cov[11] = POSITION_VARIANCE_UNKNOWN
        pose_cov = [0.0] * 21
        pose_cov[COV_X] = pose_cov[COV_Y] = pose_cov[COV_Z] = POSITION_VARIANCE_UNKNOWN
        pose_cov[COV_ROLL], pose_cov[COV_PITCH], pose_cov[COV_YAW] = est.roll_var, est.pitch_var, yaw_var
        if est.diverged:  # no information: nothing an autopilot would lean on (NaN, too, becomes huge)
            for i in (COV_ROLL, COV_PITCH, COV_YAW):
                pose_cov[i] = DIVERGED_VARIANCE if not pose_cov[i] >= DIVERGED_VARIANCE else pose_cov[i]
        rates = tuple(float(v) for v in est.body_rate) if r.body_rates else (nan, nan, nan)

        ts = self.timesync
        if ts is not None and ts.synced:
            time_usec = ts.presented_ns(est.t_ns) // 1000
        else:
            time_usec = int(est.t_ns) // 1000
            if ts is not None:
                self.stats.not_synced += 1
        w, x, y, z = (float(v) for v in est.q)
        return mavlink.MAVLink_odometry_message(
            max(0, int(time_usec)), frame, r.child_frame_id,
            *pos, [w, x, y, z], *vel, *rates,
            pose_cov, vel_cov, self.reset_counter, r.estimator_type, quality_of(est),
        )
