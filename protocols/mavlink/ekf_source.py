"""MAV_CMD_SET_EKF_SOURCE_SET out: ArduPilot's EKF3 told to leave our heading for its fallback.

With ODOMETRY fused as its yaw source (``EK3_SRC1_YAW = 6``, ExtNav), ArduPilot keeps flying on
the last heading it had when the companion goes quiet: it does not fall back to its compass by
itself. ArduPilot has three EKF *source sets* (``EK3_SRCn_*``, n = 1..3) and switches between
them on an RC switch (``RCx_OPTION = 90``) or on ``MAV_CMD_SET_EKF_SOURCE_SET`` (42007,
ardupilotmega dialect). What its handler does (``GCS_MAVLINK::handle_command_set_ekf_source_set``
in ``libraries/GCS_MAVLink/GCS_Common.cpp``, ``AP_NavEKF_Source::setPosVelYawSourceSet``):

* param1 is the set, 1..3; anything else is answered ``MAV_RESULT_DENIED`` (checked against
  ArduCopter 4.7 SITL: 0 and 4 denied, 1..3 accepted, as COMMAND_LONG or COMMAND_INT);
* an accepted set is active at once: ``COMMAND_ACK`` ACCEPTED, a DataFlash event
  (``EK3_SOURCES_SET_TO_PRIMARY`` / ``_SECONDARY`` / ``_TERTIARY``) and no STATUSTEXT of its
  own; no MAVLink message reports the active set afterwards. When the new set's yaw source
  differs, EKF3 notices on its next update and resets its yaw from the new source (its
  STATUSTEXT then says which: docs/autopilot.md, "Fallback when the companion stops").

:class:`EkfSourceSwitch` asks for the *fallback* set when the service stops cleanly
(:meth:`~EkfSourceSwitch.fall_back_at_stop`) and when the service's own health says its heading
is not to be trusted, and for the *primary* set once the heading has been trustworthy for
``trusted_hold_s`` (hysteresis), never two requests within ``min_interval_s``. Each request's
COMMAND_ACK is read and counted (accepted, refused, unanswered after its tries) and its outcome
handed back once as a notice for the service to report. Time is monotonic ns throughout.
"""

from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Protocol

from ahrs_service.protocols.mavlink.dialect import mavlink

#: ardupilotmega's MAV_CMD_SET_EKF_SOURCE_SET (not in the common dialect the service uses)
MAV_CMD_SET_EKF_SOURCE_SET = 42007
#: the source sets ArduPilot has (EK3_SRC1_* … EK3_SRC3_*)
SOURCE_SETS = (1, 2, 3)
#: the shortest time between two requests, s: a heading that flickers between trusted and not
#: must not make the autopilot reset its yaw again and again
MIN_INTERVAL_S = 3.0
#: how long the heading must stay trustworthy before the primary set is asked for again, s
TRUSTED_HOLD_S = 5.0
#: how long a request waits for its COMMAND_ACK before it is sent again, s (ArduPilot answers
#: within a few ms; a lost datagram or a busy serial link is what this covers)
ACK_TIMEOUT_S = 0.5
#: sends per request (MAVLink's command protocol: the same command, confirmation 0, 1, …)
TRIES = 3
#: at a clean stop: the wait for each try's COMMAND_ACK, s, and the tries; together well
#: inside the service's 2 s stop budget and the 1 s a pilot may allow for the switch
STOP_ACK_TIMEOUT_S = 0.3
STOP_TRIES = 2


class CommandLink(Protocol):
    """What the switch uses of the autopilot link (``AutopilotLink``)."""

    system_id: int
    component_id: int
    autopilot: Any  # AutopilotInfo | None: .kind, .system_id, .component_id

    def command_long(self, command: int, *params: float) -> bool: ...

    def subscribe(self, names: Iterable[str], sink: Callable[[Any, int], None], *,
                  autopilot_only: bool = True) -> None: ...

    def unsubscribe(self, sink: Callable[[Any, int], None]) -> None: ...


@dataclass
class SourceSetStats:
    """Counters of the requests made (``/loop`` ``ekf_source_set``, the final summary).

    requests: requests made (a request is sent up to ``TRIES`` times). accepted / refused /
    unanswered: their outcomes (refused: any COMMAND_ACK result but ACCEPTED and
    IN_PROGRESS; unanswered: no COMMAND_ACK after the last try). send_errors: sends the link
    could not make (no autopilot heard yet, a write that failed). asked: the set last asked
    for (0: none yet). last_result: the last outcome, as reported.
    """

    requests: int = 0
    accepted: int = 0
    refused: int = 0
    unanswered: int = 0
    send_errors: int = 0
    asked: int = 0
    last_result: str = ""


@dataclass
class _Request:
    source_set: int
    why: str
    tries: int
    timeout_ns: int
    sent_ns: int = 0
    sent: int = 0  # tries sent so far


class EkfSourceSwitch:
    """Asks an ArduPilot autopilot for its primary or fallback EKF source set.

    link: the autopilot link (COMMAND_LONG out, COMMAND_ACK in on its reader thread).
    primary_set: the set with our heading (1..3), asked for again once the heading is
    trustworthy; 0 never asks for it. fallback_set: the set without it (1..3), asked for at
    a clean stop and when the heading is not trustworthy. min_interval_s, trusted_hold_s,
    ack_timeout_s, tries: see the module constants. stats: counters to continue (a reload).
    Drive :meth:`update` and :meth:`fall_back_at_stop` from one thread.
    """

    def __init__(self, link: CommandLink, *, primary_set: int, fallback_set: int,
                 min_interval_s: float = MIN_INTERVAL_S, trusted_hold_s: float = TRUSTED_HOLD_S,
                 ack_timeout_s: float = ACK_TIMEOUT_S, tries: int = TRIES,
                 stats: SourceSetStats | None = None) -> None:
        if fallback_set not in SOURCE_SETS or primary_set not in (0, *SOURCE_SETS) or primary_set == fallback_set:
            raise ValueError(f"EKF source sets: primary {primary_set!r} and fallback {fallback_set!r} must be "
                             f"distinct sets 1..3 (primary 0: never asked for)")
        self.link = link
        self.primary_set, self.fallback_set = int(primary_set), int(fallback_set)
        self.min_interval_ns = int(min_interval_s * 1e9)
        self.trusted_hold_ns = int(trusted_hold_s * 1e9)
        self.ack_timeout_ns = int(ack_timeout_s * 1e9)
        self.tries = max(1, int(tries))
        self.stats = stats if stats is not None else SourceSetStats()
        self._acks: collections.deque[int] = collections.deque(maxlen=16)  # results, from the reader thread
        self._ack_arrived = threading.Event()
        self._pending: _Request | None = None
        self._last_request_ns: int | None = None
        self._trusted_since_ns: int | None = None
        self._ever_trusted = False
        self._notices: list[tuple[int, str]] = []
        self._not_ardupilot_noted = False
        self._accepted_set = 0  # the set the autopilot last accepted (0: none)
        self.stopped = False  # closed: no more COMMAND_ACKs read
        self.last_ack_ns: int | None = None  # when the newest COMMAND_ACK for the command arrived, monotonic ns
        link.subscribe(["COMMAND_ACK"], self._on_ack)

    # ------------------------------------------------------------------ the reader thread
    def _on_ack(self, msg: Any, rx_ns: int) -> None:
        if msg.command != MAV_CMD_SET_EKF_SOURCE_SET:
            return
        # MAVLink 1 acks carry no target (0); a MAVLink 2 ack for another component is not ours
        target = (getattr(msg, "target_system", 0), getattr(msg, "target_component", 0))
        if target != (0, 0) and target != (self.link.system_id, self.link.component_id):
            return
        self.last_ack_ns = rx_ns
        self._acks.append(int(msg.result))
        self._ack_arrived.set()

    # ------------------------------------------------------------------ the loop
    def update(self, now_ns: int, trusted: bool, why: str = "") -> list[tuple[int, str]]:
        """One look at the heading's health (``trusted``; ``why``: what is wrong when it is
        not): resolves a request under way (its COMMAND_ACK, a resend, or no answer) and makes
        a new one when the set wanted changed. Returns the notices (severity, text) to report,
        each outcome once."""
        self._resolve(now_ns)
        if trusted:
            if self._trusted_since_ns is None:
                self._trusted_since_ns = now_ns
            self._ever_trusted = True
        else:
            self._trusted_since_ns = None
        if self._pending is None:
            wanted, reason = self._wanted(now_ns, trusted, why)
            if wanted and (self._last_request_ns is None or now_ns - self._last_request_ns >= self.min_interval_ns):
                self._request(now_ns, wanted, reason, self.tries, self.ack_timeout_ns)
        return self._take_notices()

    def _wanted(self, now_ns: int, trusted: bool, why: str) -> tuple[int, str]:
        asked = self.stats.asked
        if trusted:
            held = self._trusted_since_ns is not None and now_ns - self._trusted_since_ns >= self.trusted_hold_ns
            if self.primary_set and asked != self.primary_set and held:
                return self.primary_set, "our heading is trustworthy"
            return 0, ""
        # a start-up is not a fault: the estimator initialising has never been trusted yet
        if self._ever_trusted and asked != self.fallback_set:
            return self.fallback_set, f"our heading is not trustworthy: {why or 'unknown'}"
        return 0, ""

    def fall_back_at_stop(self, now_ns: int | None = None, *, ack_timeout_s: float = STOP_ACK_TIMEOUT_S,
                          tries: int = STOP_TRIES) -> list[tuple[int, str]]:
        """The service stops cleanly: asks for the fallback set at once (whatever the interval
        since the last request) unless it was asked for and accepted already, and waits for
        the COMMAND_ACK, at most ``ack_timeout_s`` × ``tries``. Returns the notices to report."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        self._resolve(now_ns)
        pending = self._pending
        done = self._accepted_set == self.fallback_set
        if pending is not None and pending.source_set != self.fallback_set:
            self._give_up(pending)  # superseded: counted (its answer, late, could not be told from the fallback's)
            pending = None
        if pending is None and not done:
            self._request(now_ns, self.fallback_set, "the service is stopping", tries, int(ack_timeout_s * 1e9))
        end_ns = now_ns + int(ack_timeout_s * 1e9) * max(1, tries) + 50_000_000
        # bounded: each turn waits for an ack or a try's timeout, at most tries + 2 turns
        for _ in range(max(1, tries) + 2):
            if self._pending is None:
                break
            self._ack_arrived.wait(max(0.0, min(ack_timeout_s, (end_ns - time.monotonic_ns()) / 1e9)))
            self._resolve(time.monotonic_ns())
            if time.monotonic_ns() >= end_ns and self._pending is not None:
                self._give_up(self._pending)
        return self._take_notices()

    def close(self) -> None:
        """Stops reading COMMAND_ACKs (a request under way is left as it is)."""
        self.link.unsubscribe(self._on_ack)
        self.stopped = True

    # ------------------------------------------------------------------ requests
    def _request(self, now_ns: int, source_set: int, why: str, tries: int, timeout_ns: int) -> None:
        ap = self.link.autopilot
        if ap is not None and ap.kind != "ardupilot":
            if not self._not_ardupilot_noted:  # PX4 has no source sets: said once, never asked
                self._not_ardupilot_noted = True
                self._notices.append((4, f"EKF source set {source_set} not asked: the autopilot is {ap.kind}, "
                                         f"MAV_CMD_SET_EKF_SOURCE_SET is ArduPilot's"))
            return
        self._acks.clear()
        self._ack_arrived.clear()
        self.stats.requests += 1
        self.stats.asked = source_set
        self._last_request_ns = now_ns
        self._pending = _Request(source_set, why, max(1, tries), timeout_ns)
        self._send(self._pending, now_ns)

    def _send(self, req: _Request, now_ns: int) -> None:
        # param2..7 unused; MAVLink's confirmation (a resend's count) is not exposed by the
        # link's command_long, and ArduPilot does not read it for this command
        req.sent += 1
        req.sent_ns = now_ns
        if not self.link.command_long(MAV_CMD_SET_EKF_SOURCE_SET, float(req.source_set)):
            self.stats.send_errors += 1

    def _resolve(self, now_ns: int) -> None:
        req = self._pending
        if req is None:
            self._acks.clear()
            return
        self._ack_arrived.clear()  # before the deque is read: an ack arriving meanwhile sets it again
        while self._acks:
            result = self._acks.popleft()
            if result == mavlink.MAV_RESULT_IN_PROGRESS:
                continue
            self._pending = None
            entry = mavlink.enums["MAV_RESULT"].get(result)  # the dialect's names, as imu_source's refusals
            name = entry.name[len("MAV_RESULT_"):] if entry is not None else str(result)
            if result == mavlink.MAV_RESULT_ACCEPTED:
                self.stats.accepted += 1
                self._accepted_set = req.source_set
                self._outcome(req, "accepted", 5)
            else:
                self.stats.refused += 1
                self._outcome(req, f"refused ({name})", 3)
            return
        if now_ns - req.sent_ns >= req.timeout_ns:
            if req.sent < req.tries:
                self._send(req, now_ns)
            else:
                self._give_up(req)

    def _give_up(self, req: _Request) -> None:
        self._pending = None
        self.stats.unanswered += 1
        self._outcome(req, f"no answer after {req.sent} tr{'y' if req.sent == 1 else 'ies'}", 3)

    def _outcome(self, req: _Request, result: str, severity: int) -> None:
        role = "primary" if req.source_set == self.primary_set else "fallback"
        self.stats.last_result = f"set {req.source_set} {result}"
        self._notices.append((severity, f"autopilot EKF source set {req.source_set} ({role}; {req.why}): {result}"))

    def _take_notices(self) -> list[tuple[int, str]]:
        out, self._notices = self._notices, []
        return out

    def summary(self) -> str:
        """The final summary's part: what was asked and how the autopilot answered."""
        st = self.stats
        return (f"EKF source set: {st.requests} request{'s' if st.requests != 1 else ''} (accepted {st.accepted}, "
                f"refused {st.refused}, no answer {st.unanswered})")
