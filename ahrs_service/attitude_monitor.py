"""A second opinion on the autopilot's attitude: its ATTITUDE_QUATERNION against our estimate.

When the service runs beside a flight controller (an autopilot link, ``source.type =
"mavlink"``), the autopilot's own attitude arrives as ATTITUDE_QUATERNION (message 31, preferred) or
ATTITUDE (message 30). Each one is compared with the service's estimate **at the autopilot's time**:
the message's ``time_boot_ms`` is mapped onto our clock by the link's
:class:`~ahrs_service.protocols.mavlink.autopilot_link.RemoteTimeline` (the mapping the IMU
samples use, so both sides share one time base) and the estimate is interpolated there
(slerp between the two estimates around it, from a short history).

The disagreement, with both attitudes q_earth←body (NED, FRD; ours with the declination
applied, true north like the autopilot's):

* ``total`` — the angle of the rotation between them, deg;
* ``inclination`` — the angle between the two "down" directions in the body, deg (what tilt
  errors do to a multicopter);
* ``heading`` — autopilot yaw − our yaw, wrapped to [−180, 180), deg.

Published as NAMED_VALUE_FLOAT (names ≤ 10 characters: ``ATT_DIFF``, ``ATT_INCL``,
``ATT_HDG``) at ``[monitor] rate_hz``; logged to MCAP beside both attitudes
(``/autopilot/attitude``, ``/monitor``, and a second frame ``autopilot`` on ``/tf`` so a 3-D
panel shows both bodies). When ``total`` stays above ``[monitor] threshold_deg`` (default 5°)
for ``[monitor] hold_s`` (default 2 s) of autopilot time, a STATUSTEXT warning goes out
(through the component's rate limit, kind ``"attitude monitor"``); when it falls below
again, an info text says so.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ahrs_service.core.quaternion import quat_conj, quat_from_euler, quat_mul, quat_rotate_inv, quat_to_euler
from ahrs_service.core.settings import Section, boolean, number

#: the warning rule's defaults: a disagreement above THRESHOLD_DEG for HOLD_S of autopilot time
THRESHOLD_DEG = 5.0
HOLD_S = 2.0

#: the ``[monitor]`` section of the configuration: the autopilot's attitude against ours when
#: an autopilot link is up (docs/autopilot.md)
MONITOR: Section = {
    "enabled": (True, boolean),
    "threshold_deg": (THRESHOLD_DEG, number(0.1, 180.0)),
    "hold_s": (HOLD_S, number(0.0, 600.0)),
    "rate_hz": (5.0, number(0.1, 50.0)),  # NAMED_VALUE_FLOAT of the disagreement, Hz
}

#: the rate the monitor asks the autopilot's ATTITUDE_QUATERNION at, Hz (60 bytes a frame:
#: 0.6 kB/s), and how long without one before it asks again, s
ATTITUDE_REQUEST_HZ = 10.0
ATTITUDE_REQUEST_RETRY_S = 5.0

#: NAMED_VALUE_FLOAT names (≤ 10 characters), degrees
NAME_TOTAL = "ATT_DIFF"
NAME_INCLINATION = "ATT_INCL"
NAME_HEADING = "ATT_HDG"

#: estimates kept for the interpolation (at 1 kHz: 4 s; the autopilot's attitude arrives
#: within tens of ms of its time)
HISTORY = 4096


@dataclass(frozen=True, slots=True)
class Disagreement:
    """One comparison at the autopilot's time ``t_ns`` (our monotonic clock, ns).

    q_autopilot, q_estimate: q_earth←body [w, x, y, z] (NED, FRD), ours with declination.
    total_deg, inclination_deg, heading_deg: see the module docstring.
    """

    t_ns: int
    q_autopilot: tuple[float, float, float, float]
    q_estimate: tuple[float, float, float, float]
    total_deg: float
    inclination_deg: float
    heading_deg: float

    @classmethod
    def between(cls, t_ns: int, q_ap, q_est) -> "Disagreement":
        q_ap = _unit(q_ap)
        q_est = _unit(q_est)
        err = quat_mul(quat_conj(q_est), q_ap)
        total = 2.0 * math.degrees(math.acos(min(1.0, abs(err[0]))))
        down = (0.0, 0.0, 1.0)
        d_ap, d_est = quat_rotate_inv(q_ap, down), quat_rotate_inv(q_est, down)
        cos_incl = sum(a * b for a, b in zip(d_ap, d_est))
        incl = math.degrees(math.acos(max(-1.0, min(1.0, cos_incl))))
        dyaw = math.degrees(quat_to_euler(q_ap)[2] - quat_to_euler(q_est)[2])
        heading = (dyaw + 180.0) % 360.0 - 180.0  # [−180, 180)
        return cls(int(t_ns), q_ap, q_est, total, incl, heading)


#: how far from 1 the norm of an autopilot's quaternion may be: MAVLink's float32 fields
#: carry a unit quaternion to about 1e-7; a norm off by more is no attitude (a zero or
#: scaled quaternion from a corrupt or hostile message), and 0 would divide by zero
UNIT_TOLERANCE = 0.01


def is_rotation(q) -> bool:
    """``q`` is finite and of unit norm within :data:`UNIT_TOLERANCE`."""
    n2 = sum(float(v) * float(v) for v in q)
    return math.isfinite(n2) and abs(math.sqrt(n2) - 1.0) <= UNIT_TOLERANCE


def _unit(q) -> tuple[float, float, float, float]:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if w < 0:  # one sign of the double cover, so logs and plots do not flip
        n = -n
    return (w / n, x / n, y / n, z / n)


def slerp(q0, q1, f: float) -> tuple[float, float, float, float]:
    """Spherical interpolation from q0 (f = 0) to q1 (f = 1), the shorter way."""
    a = np.asarray(q0, float)
    b = np.asarray(q1, float)
    dot = float(a @ b)
    if dot < 0:
        b, dot = -b, -dot
    if dot > 0.9995:  # nearly equal: linear, then normalised
        q = a + f * (b - a)
    else:
        theta = math.acos(dot)
        q = (math.sin((1 - f) * theta) * a + math.sin(f * theta) * b) / math.sin(theta)
    q = q / np.linalg.norm(q)
    return tuple(q.tolist())  # type: ignore[return-value]


class EstimateHistory:
    """The last ``size`` estimates (t_ns, q) in a ring, for interpolation at a given time."""

    def __init__(self, size: int = HISTORY) -> None:
        self.t = np.zeros(size, np.int64)
        self.q = np.zeros((size, 4))
        self.size = size
        self.n = 0  # estimates added in all
        self.head = 0

    def add(self, t_ns: int, q: Any) -> None:
        self.t[self.head] = t_ns
        self.q[self.head] = q
        self.head = (self.head + 1) % self.size
        self.n += 1

    def add_many(self, t_ns: np.ndarray, q: np.ndarray) -> None:
        """A block of estimates: (n,) int64 times, ns, and (n, 4) quaternions, oldest first."""
        added = n = len(t_ns)
        if n >= self.size:  # only the newest ``size`` can be kept
            t_ns, q, n = t_ns[-self.size:], q[-self.size:], self.size
        idx = (self.head + np.arange(n)) % self.size
        self.t[idx] = t_ns
        self.q[idx] = q
        self.head = (self.head + n) % self.size
        self.n += added

    def at(self, t_ns: int) -> tuple[float, float, float, float] | None:
        """The estimate at ``t_ns`` (interpolated), or None outside the kept span."""
        count = min(self.n, self.size)
        if count < 2:
            return None
        t = self.t
        first = (self.head - count) % self.size  # the oldest
        if t_ns < t[first] or t_ns > t[(self.head - 1) % self.size]:
            return None
        # the ring holds one sorted run, or (once it wrapped) two: t[first:], then t[:head];
        # search the one that holds t_ns in place, without copying the ring into time order
        if first + count <= self.size:
            j = first + int(np.searchsorted(t[first:first + count], t_ns))
        elif t_ns <= t[-1]:
            j = first + int(np.searchsorted(t[first:], t_ns))
        else:
            j = int(np.searchsorted(t[:self.head], t_ns))
        if t[j] == t_ns:
            return tuple(self.q[j].tolist())  # type: ignore[return-value]
        i0, i1 = (j - 1) % self.size, j
        f = (t_ns - t[i0]) / (t[i1] - t[i0])
        return slerp(self.q[i0], self.q[i1], float(f))


@dataclass(frozen=True, slots=True)
class _AutopilotAttitude:
    """One attitude message of the autopilot, as received (link thread)."""

    time_boot_ms: int
    q: tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class MonitorEvent:
    """A text for the operator: STATUSTEXT ``severity`` (4 warning, 6 info) and its text."""

    severity: int
    text: str


class AttitudeMonitor:
    """Compares the autopilot's attitude on ``link`` with the estimates given to :meth:`add_estimate`.

    threshold_deg, hold_s: the warning rule (module docstring). The autopilot's messages are
    taken on the link's thread (a deque); :meth:`update` runs on the loop's thread.
    """

    def __init__(self, link: Any, *, threshold_deg: float = THRESHOLD_DEG, hold_s: float = HOLD_S) -> None:
        self.link = link
        self.threshold_deg = float(threshold_deg)
        self.hold_ns = int(hold_s * 1e9)
        self.history = EstimateHistory()
        self._inbox: collections.deque[_AutopilotAttitude] = collections.deque(maxlen=256)
        self._quaternions_seen = False
        self.latest: Disagreement | None = None
        self.warning = False
        self._above_since_ns: int | None = None
        self.received = 0  # autopilot attitudes taken from the link
        self.compared = 0  # autopilot attitudes compared
        self.unmatched = 0  # autopilot attitudes outside the estimate history (too old, too new, no time map)
        self.rejected = 0  # autopilot attitudes that are no rotation (not finite, norm not 1): never compared
        self.warnings = 0
        self.stream_requests = 0  # SET_MESSAGE_INTERVAL(ATTITUDE_QUATERNION) sent
        self._requested_session: int | None = None
        self._requested_at_ns = 0
        self._last_rx_ns = 0
        link.subscribe(["ATTITUDE_QUATERNION", "ATTITUDE"], self._on_attitude)

    def close(self) -> None:
        """Stops taking the autopilot's attitude (a reload that replaces or disables the monitor)."""
        self.link.unsubscribe(self._on_attitude)

    def _on_attitude(self, msg: Any, rx_ns: int) -> None:
        """Link thread: keep the message's time and quaternion for :meth:`update`."""
        if msg.get_type() == "ATTITUDE_QUATERNION":
            self._quaternions_seen = True
            q = (float(msg.q1), float(msg.q2), float(msg.q3), float(msg.q4))
        elif self._quaternions_seen:
            return  # both streams on: the quaternion is the exact one
        else:
            q = tuple(quat_from_euler(float(msg.roll), float(msg.pitch), float(msg.yaw)))
        if not is_rotation(q):  # a corrupt or hostile message: comparing it would mean nothing
            self.rejected += 1
            return
        self._inbox.append(_AutopilotAttitude(int(msg.time_boot_ms), q))  # type: ignore[arg-type]
        self.received += 1
        self._last_rx_ns = rx_ns

    def request_stream(self, now_ns: int) -> None:
        """Loop thread: asks the autopilot for ATTITUDE_QUATERNION at ``ATTITUDE_REQUEST_HZ``
        when its link has a new session (a first HEARTBEAT, a reboot) or no attitude came for
        ``ATTITUDE_REQUEST_RETRY_S``. ArduPilot streams nothing a link's ``MAVn_*`` rates or a
        request did not ask for; PX4's onboard mode does stream it, and the request then only
        sets the rate."""
        link = self.link
        if link.autopilot is None:
            return
        silent = now_ns - max(self._requested_at_ns, self._last_rx_ns) > ATTITUDE_REQUEST_RETRY_S * 1e9
        if link.session != self._requested_session or silent:
            if link.set_message_interval("ATTITUDE_QUATERNION", ATTITUDE_REQUEST_HZ):
                self.stream_requests += 1
            self._requested_session = link.session
            self._requested_at_ns = now_ns

    def add_estimate(self, t_ns: int, q: Any) -> None:
        """Our estimate q_earth←body (magnetic north, as the estimator keeps it) at ``t_ns``."""
        self.history.add(t_ns, q)

    def add_estimates(self, t_ns: np.ndarray, q: np.ndarray) -> None:
        """A block of our estimates (a sample block's times, ns, and quaternions, oldest first)."""
        self.history.add_many(t_ns, q)

    def receive(self, estimated: Any) -> None:
        """An estimated block from the service's loop (``pipeline.EstimatedBlock``): its
        estimates join the history (the monitor is one of the service's sinks)."""
        self.history.add_many(estimated.t_ns, estimated.q)

    def update(self, declination_deg: float = 0.0) -> tuple[list[Disagreement], list[MonitorEvent]]:
        """Compares every autopilot attitude received since the last call whose time the
        history covers (later ones wait for the next call); returns the comparisons and any
        warning / all-clear. ``declination_deg`` turns our estimate to true north."""
        q_declination = quat_from_euler(0.0, 0.0, math.radians(declination_deg))
        out: list[Disagreement] = []
        events: list[MonitorEvent] = []
        newest = self.history.t[(self.history.head - 1) % self.history.size] if self.history.n else None
        while self._inbox:
            att = self._inbox[0]
            q_ap = att.q
            t_ns = self.link.timeline.peek_local_ns(att.time_boot_ms * 1000)
            if t_ns is None or newest is None or t_ns > newest:
                break  # no time map yet (the IMU source waits for TIMESYNC), or no estimate for that time yet
            self._inbox.popleft()
            q_est = self.history.at(t_ns)
            if q_est is None:
                self.unmatched += 1
                continue
            d = Disagreement.between(t_ns, q_ap, quat_mul(q_declination, q_est))
            self.compared += 1
            out.append(d)
            self.latest = d
            event = self._rule(d)
            if event is not None:
                events.append(event)
        return out, events

    def _rule(self, d: Disagreement) -> MonitorEvent | None:
        if d.total_deg > self.threshold_deg:
            if self._above_since_ns is None:
                self._above_since_ns = d.t_ns
            if not self.warning and d.t_ns - self._above_since_ns >= self.hold_ns:
                self.warning = True
                self.warnings += 1
                return MonitorEvent(4, f"attitude differs from autopilot by {d.total_deg:.1f} deg "
                                       f"(incl {d.inclination_deg:.1f}, hdg {d.heading_deg:.1f})")
            return None
        self._above_since_ns = None
        if self.warning:
            self.warning = False
            return MonitorEvent(6, f"attitude agrees with autopilot again ({d.total_deg:.1f} deg)")
        return None

    def named_values(self) -> list[tuple[str, float]]:
        """(name, degrees) of the latest comparison for NAMED_VALUE_FLOAT; empty before one."""
        d = self.latest
        if d is None:
            return []
        return [(NAME_TOTAL, d.total_deg), (NAME_INCLINATION, d.inclination_deg), (NAME_HEADING, d.heading_deg)]
