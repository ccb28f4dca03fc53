"""The service's MAVLink component: publishes attitude at configured rates and answers the
parameter and command protocols, over one or more links at once.

Threading: a component is used from **one thread** (the service's loop). ``publish`` and
``poll`` never block; neither raises on network trouble — errors are counted in ``stats``.

Typical drive (one loop iteration of the service)::

    def calibrate_gyro(action: int) -> tuple[int, str]:   # a commands.CalibrationCallback
        accepted, text = link.calibrate_gyro()             # mavlink_bridge.ServiceLink.calibrate_gyro
        return (MAV_RESULT_ACCEPTED if accepted else MAV_RESULT_TEMPORARILY_REJECTED), text

    comp = MavlinkComponent(["udpout:127.0.0.1:14550"], Identity(), params=table,
                            gyro_calibration=calibrate_gyro)
    while running:
        ...                                     # read IMU, step the estimator
        comp.publish(time.monotonic_ns(), telemetry)   # sends what is due
        comp.poll()                             # handles pending requests and commands
    comp.close()

Signing (MAVLink 2, 32-byte key): every outgoing message is signed; incoming writes
(``signing.SIGNED_ONLY``: PARAM_SET, COMMAND_LONG, …) need a valid signature, and unsigned or
wrongly signed ones are dropped and counted in ``stats.unsigned_rejected``.

Writes, signed or not, follow the rules of docs/mavlink.md, "Security" (PX4's and
ArduPilot's): HEARTBEAT cannot be switched off or slowed below ``HEARTBEAT_MIN_HZ``; a
calibration starts only when ``calibration_guard`` finds nothing against it (at rest, no
armed autopilot). Every accepted write that changed something is handed to ``on_write`` with
its sender (an :class:`AcceptedWrite`), a write of the value already in force is answered and
not handed on, and every refused write is counted in ``stats.writes_refused``.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping

from ahrs_service.protocols.mavlink.attitude import (
    attitude_frame,
    attitude_quaternion_frame,
    encode_attitude,
    encode_attitude_quaternion,
)
from ahrs_service.protocols.mavlink.commands import (
    WRITE_COMMANDS,
    CalibrationCallback,
    CalibrationGuard,
    Command,
    CommandResult,
    CommandTable,
    Sender,
    calibrated_sensor,
    encode_command_ack,
    preflight_calibration_handler,
)
from ahrs_service.protocols.mavlink.dialect import mavlink, message_id
from ahrs_service.protocols.mavlink.endpoints import Endpoint
from ahrs_service.protocols.mavlink.health import encode_statustext, encode_sys_status, system_state
from ahrs_service.protocols.mavlink.identity import Identity, encode_heartbeat
from ahrs_service.protocols.mavlink.imu import encode_highres_imu
from ahrs_service.protocols.mavlink.params import BYTEWISE, ParameterTable
from ahrs_service.protocols.mavlink.signing import SIGNED_ONLY, check_key
from ahrs_service.protocols.mavlink.statustext_limit import StatusTextLimiter
from ahrs_service.protocols.mavlink.telemetry import ATTITUDE_STREAMS, Telemetry
from ahrs_service.protocols.mavlink.vibration import encode_vibration

_log = logging.getLogger("ahrs_service.mavlink")

#: default publishing rates, Hz (0 = off)
DEFAULT_RATES: dict[str, float] = {
    "HEARTBEAT": 1.0,
    "ATTITUDE": 50.0,
    "ATTITUDE_QUATERNION": 50.0,
    "HIGHRES_IMU": 0.0,
    "SYS_STATUS": 1.0,
    "VIBRATION": 2.0,
}

_ENCODERS: dict[str, Callable[[Telemetry], Any]] = {
    "ATTITUDE": encode_attitude,
    "ATTITUDE_QUATERNION": encode_attitude_quaternion,
    "HIGHRES_IMU": encode_highres_imu,
    "SYS_STATUS": encode_sys_status,
    "VIBRATION": encode_vibration,
}
# unsigned links send the attitude streams as pre-packed frames: the same bytes at 2.5x less cost
_UNSIGNED_ENCODERS: dict[str, Callable[[Telemetry], Any]] = {
    **_ENCODERS,
    "ATTITUDE": attitude_frame,
    "ATTITUDE_QUATERNION": attitude_quaternion_frame,
}
STREAMABLE = ("HEARTBEAT", *_ENCODERS)


@dataclass
class MavlinkStats:
    """Counters of one component. Every dict is keyed by message name or endpoint string."""

    sent: dict[str, int] = field(default_factory=dict)
    received: dict[str, int] = field(default_factory=dict)
    received_total: int = 0
    malformed: int = 0  # bad CRC, bad prefix or length, truncated datagram tails
    bad_crc: int = 0  # the CRC failures among ``malformed``
    unknown_ids: int = 0  # well-framed messages of ids outside the common dialect
    unsigned_rejected: int = 0  # writes without a valid signature while signing is on
    writes_accepted: int = 0  # PARAM_SETs and write commands that changed something
    writes_refused: int = 0  # writes refused, for any reason (unsigned_rejected among them)
    not_for_us: int = 0  # requests addressed to another system/component
    handler_errors: int = 0  # exceptions raised by service callbacks (answered FAILED)
    statustext_suppressed: int = 0  # STATUSTEXTs over their kind's rate limit (statustext_limit)
    rates_refused: int = 0  # SET_MESSAGE_INTERVAL requests answered DENIED
    stale_withheld: int = 0  # stream messages not sent: no fresh estimate (Telemetry.attitude_fresh)
    send_errors: dict[str, int] = field(default_factory=dict)
    receive_errors: dict[str, int] = field(default_factory=dict)
    # messages not sent to a destination whose name did not resolve yet (endpoints.HostResolver)
    unresolved: dict[str, int] = field(default_factory=dict)
    last_error: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}


#: slowest HEARTBEAT a peer may ask for, Hz: MAVLink's nominal rate. Ground stations call a
#: vehicle lost after a few seconds without one; off or slower is refused (PX4 refuses off).
HEARTBEAT_MIN_HZ = 1.0

#: slowest stream rate, Hz: an interval of 100 s. GET_MESSAGE_INTERVAL answers in
#: MESSAGE_INTERVAL.interval_us, an int32 (at most 2³¹-1 µs ≈ 35.8 min); a slower rate could not
#: be reported, and a stream that slow is off in all but name.
MIN_RATE_HZ = 0.01

#: streams that carry the estimate or the IMU readings: withheld while the estimate is stale
_NEEDS_FRESH_ESTIMATE = frozenset({"ATTITUDE", "ATTITUDE_QUATERNION", "HIGHRES_IMU", "VIBRATION"})


@dataclass(frozen=True)
class AcceptedWrite:
    """A write a peer made that changed something: ``name`` (a parameter's, ``"<MESSAGE> rate
    Hz"`` for a message interval, ``"calibration"`` for a calibration started), the value
    before and after (None for a calibration's before; its after names the sensor), and who
    sent it."""

    name: str
    old: Any
    new: Any
    sender: Sender


@dataclass
class _Stream:
    name: str
    msg_id: int
    hz: float
    anchor_ns: int | None = None  # the schedule is anchor + k / hz: no drift accumulates
    k: int = 0
    next_ns: int = 0  # due_ns(k), kept: publish compares it on every call

    def due_ns(self, k: int) -> int:
        return self.anchor_ns + int(round(k * 1e9 / self.hz))  # type: ignore[operator]


class MavlinkComponent:
    """A MAVLink component on one or more links (see the module docstring for how to drive it).

    endpoints: pymavlink connection strings, e.g. ``["udpout:127.0.0.1:14550",
        "/dev/ttyAMA0,921600"]``. Every message goes out on every endpoint.
    identity: system/component id and heartbeat type (``Identity()`` = standalone, sys 1 comp 1).
    rates: message name → Hz over ``DEFAULT_RATES`` (HEARTBEAT, ATTITUDE, ATTITUDE_QUATERNION,
        HIGHRES_IMU, SYS_STATUS, VIBRATION); 0 switches a message off. These are also the "default rates"
        MAV_CMD_SET_MESSAGE_INTERVAL with interval 0 returns to.
    signing_key: 32-byte MAVLink 2 signing key, or None for no signing.
    params: the parameter table the ground station sees (empty if None).
    gyro_calibration, mag_calibration, accel_calibration: MAV_CMD_PREFLIGHT_CALIBRATION
        callbacks ``(action: int) -> (MAV_RESULT, text)``; None answers UNSUPPORTED.
    max_rate_hz: fastest rate a ground station may request for a stream.
    current_telemetry: builds a full :class:`Telemetry` of now (None before the first
        estimate) for messages sent on request (MAV_CMD_REQUEST_MESSAGE, ``send_now``); without
        it they use the last full one ``publish`` was given.
    calibration_guard: ``(sensor) -> reason`` run before a calibration callback; a reason
        answers TEMPORARILY_REJECTED (commands.preflight_calibration_handler).
    on_write: told every accepted write that changed something (:class:`AcceptedWrite`), after
        its answer went out; an exception it raises is counted in ``stats.handler_errors``.
    require_signed_writes: refuse to start without ``signing_key`` (ValueError): with a key,
        writes need a valid signature anyway; this makes a missing key an error instead of an
        open link.
    """

    def __init__(self, endpoints: Iterable[str], identity: Identity | None = None, *,
                 rates: Mapping[str, float] | None = None, signing_key: bytes | None = None,
                 params: ParameterTable | None = None,
                 gyro_calibration: CalibrationCallback | None = None,
                 mag_calibration: CalibrationCallback | None = None,
                 accel_calibration: CalibrationCallback | None = None,
                 max_rate_hz: float = 250.0,
                 current_telemetry: Callable[[], Telemetry | None] | None = None,
                 calibration_guard: CalibrationGuard | None = None,
                 on_write: Callable[[AcceptedWrite], None] | None = None,
                 require_signed_writes: bool = False) -> None:
        if require_signed_writes and signing_key is None:
            raise ValueError("require_signed_writes needs a signing key")
        self.identity = identity or Identity()
        self.on_write = on_write
        #: the sender of the write being handled (a setter may ask), None between writes
        self.sender: Sender | None = None
        self._current_telemetry = current_telemetry
        self.params = params if params is not None else ParameterTable()
        self.max_rate_hz = float(max_rate_hz)
        self.stats = MavlinkStats()
        self._default_rates = dict(DEFAULT_RATES)
        for name, hz in (rates or {}).items():
            self._default_rates[self._check_rate(name, hz)[0]] = float(hz)
        self._streams = {n: _Stream(n, int(message_id(n)), hz)  # type: ignore[arg-type]
                         for n, hz in self._default_rates.items()}
        self._last: Telemetry | None = None
        self._next_due_ns: int | None = None  # earliest stream deadline; None: not known yet
        self._statustext_id = 0
        self._status_limit = StatusTextLimiter()
        self._rejected = False
        self._reply_after_ack: Any = None  # a message a command handler wants sent after its ACK
        self._write_done: AcceptedWrite | None = None  # what a write command changes, if it is accepted
        if signing_key is not None:
            signing_key = check_key(signing_key)
        self.signing = signing_key is not None
        self._encoders = _ENCODERS if self.signing else _UNSIGNED_ENCODERS

        self.commands = CommandTable()
        self.commands.register(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, self._cmd_set_message_interval)
        self.commands.register(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, self._cmd_get_message_interval)
        self.commands.register(mavlink.MAV_CMD_REQUEST_MESSAGE, self._cmd_request_message)
        self._calibrate = preflight_calibration_handler(gyro_calibration, mag_calibration, accel_calibration,
                                                        guard=calibration_guard)
        self.commands.register(mavlink.MAV_CMD_PREFLIGHT_CALIBRATION, self._cmd_preflight_calibration)

        endpoints = list(endpoints)
        if len(set(endpoints)) != len(endpoints):
            raise ValueError(f"MAVLink endpoints listed twice: {endpoints}")
        self._endpoints: list[Endpoint] = []
        try:
            for link_id, url in enumerate(endpoints):
                ep = Endpoint(url, self.identity.system_id, self.identity.component_id)  # type: ignore[arg-type]
                if signing_key is not None:
                    ep.conn.setup_signing(signing_key, sign_outgoing=True,
                                          allow_unsigned_callback=self._allow_unsigned, link_id=link_id % 256)
                self._endpoints.append(ep)
                self.stats.send_errors[url] = 0
                self.stats.receive_errors[url] = 0
        except Exception:
            self.close()
            raise
        if not self._endpoints:
            raise ValueError("MavlinkComponent needs at least one endpoint")
        self._resolving = [ep for ep in self._endpoints if ep.resolver is not None]

    # ================================================================== rates
    @staticmethod
    def _check_rate(name: str, hz: float) -> tuple[str, float]:
        if name not in STREAMABLE:
            raise ValueError(f"cannot stream {name!r}; streamable messages: {', '.join(STREAMABLE)}")
        hz = float(hz)
        if not math.isfinite(hz) or hz < 0 or 0 < hz < MIN_RATE_HZ:
            raise ValueError(f"rate of {name} must be 0 (off) or {MIN_RATE_HZ:g} Hz or more, got {hz:g}")
        return name, hz

    @property
    def rates(self) -> dict[str, float]:
        """Current publishing rate of each streamable message, Hz (0 = off)."""
        return {n: s.hz for n, s in self._streams.items()}

    def set_rate(self, name: str, hz: float) -> None:
        """Sets the publishing rate of message ``name`` in Hz (0 = off); the new schedule
        starts at the next ``publish``."""
        name, hz = self._check_rate(name, hz)
        s = self._streams[name]
        s.hz = hz
        s.anchor_ns = None
        self._next_due_ns = None

    # ================================================================== sending
    def _send_all(self, msg: Any, only: Endpoint | None = None) -> None:
        self._send_batch([msg], only)

    def _send_batch(self, msgs: list[Any], only: Endpoint | None = None) -> None:
        """Sends ``msgs`` on every endpoint (or ``only``) in one write each: on UDP one
        datagram carrying them back to back, as autopilots send their streams."""
        sent = self.stats.sent
        for ep in (only,) if only is not None else self._endpoints:
            if ep.send_many(msgs):
                for msg in msgs:
                    name = msg.get_type()
                    sent[name] = sent.get(name, 0) + 1
            else:
                self.stats.send_errors[ep.url] = ep.send_errors
                self.stats.last_error = f"{ep.url}: {ep.last_send_error}"

    def _encode(self, name: str, telemetry: Telemetry | None) -> Any:
        if name == "HEARTBEAT":
            return encode_heartbeat(self.identity, system_state(telemetry))
        if telemetry is None:
            return None
        if not telemetry.attitude_fresh and name in _NEEDS_FRESH_ESTIMATE:
            self.stats.stale_withheld += 1  # no fresh-looking copy of an old attitude
            return None
        return self._encoders[name](telemetry)

    def due(self, now_ns: int) -> bool:
        """Whether ``publish(now_ns, …)`` would send anything: lets the caller skip building
        the telemetry snapshot on the calls where no stream is due."""
        return self._next_due_ns is None or now_ns >= self._next_due_ns

    def _due_streams(self, now_ns: int) -> list[_Stream]:
        """The streams ``publish(now_ns, …)`` sends: on, and at or past their next slot (or
        not anchored yet, or anchored after ``now_ns``: they start again now)."""
        return [s for s in self._streams.values()
                if s.hz > 0.0 and (s.anchor_ns is None or now_ns < s.anchor_ns or now_ns >= s.next_ns)]

    def only_attitude_due(self, now_ns: int) -> bool:
        """Whether every stream ``publish(now_ns, …)`` would send is one of
        :data:`~ahrs_service.protocols.mavlink.telemetry.ATTITUDE_STREAMS`: an
        ``attitude_only`` telemetry then serves them."""
        return all(s.name in ATTITUDE_STREAMS for s in self._due_streams(now_ns))

    def publish(self, now_ns: int, telemetry: Telemetry | None) -> int:
        """Sends every stream that is due at ``now_ns`` (monotonic clock, ns); returns how
        many messages were built.

        Each stream follows an absolute schedule (anchor + k/rate), so late calls do not push
        later messages back; a stream is sent at most once per call (a loop slower than the
        stream's rate caps it). ``telemetry`` None (no estimate yet) sends only HEARTBEAT
        (state BOOT). An ``attitude_only`` telemetry serves only :meth:`only_attitude_due`
        calls (ValueError otherwise, before anything is sent).
        """
        return self.publish_built(now_ns, lambda attitude_only: telemetry)

    def publish_built(self, now_ns: int, build: Callable[[bool], Telemetry | None]) -> int:
        """:meth:`publish` of the telemetry ``build(attitude_only)`` returns, once the due
        streams are known: ``attitude_only`` True when every one of them is one of the
        ``ATTITUDE_STREAMS`` (an ``attitude_only`` telemetry serves them; the caller builds
        the full snapshot only when it is False)."""
        streams = self._due_streams(now_ns)
        attitude_only = all(s.name in ATTITUDE_STREAMS for s in streams)
        telemetry = build(attitude_only)
        if telemetry is not None:
            if telemetry.attitude_only:
                if not attitude_only:
                    raise ValueError("an attitude-only telemetry given while other streams are due")
            else:
                self._last = telemetry
        due = []
        for s in streams:
            if s.anchor_ns is None or now_ns < s.anchor_ns:
                s.anchor_ns, s.k, s.next_ns = now_ns, 0, now_ns
            msg = self._encode(s.name, telemetry)
            if msg is not None:
                due.append(msg)
            # next slot strictly after now; slots missed while the loop was late are skipped
            k = max(s.k + 1, int((now_ns - s.anchor_ns) * s.hz / 1e9))
            while s.due_ns(k) <= now_ns:
                k += 1
            s.k, s.next_ns = k, s.due_ns(k)
        if due:
            self._send_batch(due)
        self._next_due_ns = min(
            (s.next_ns for s in self._streams.values() if s.hz > 0.0 and s.anchor_ns is not None),
            default=now_ns + 1_000_000_000,
        )
        return len(due)

    def send_now(self, name: str, telemetry: Telemetry | None = None) -> bool:
        """Sends message ``name`` once now on every endpoint (``telemetry`` None: a full one
        of now from ``current_telemetry``, else the last full one published); False if it
        cannot be built (unknown name or no telemetry yet)."""
        msg = self._build_once(name, telemetry if telemetry is not None else self._telemetry_now())
        if msg is None:
            return False
        self._send_all(msg)
        return True

    def _telemetry_now(self) -> Telemetry | None:
        """A full telemetry for a message sent on request: the caller's of now, else the last
        full one published."""
        if self._current_telemetry is not None:
            telemetry = self._current_telemetry()
            if telemetry is not None:
                return telemetry
        return self._last

    def _build_once(self, name: str, telemetry: Telemetry | None) -> Any:
        if name in STREAMABLE:
            return self._encode(name, telemetry)
        if name == "AUTOPILOT_VERSION":
            return self._autopilot_version()
        return None

    def _autopilot_version(self) -> Any:
        caps = mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        caps |= (mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE if self.params.encoding == BYTEWISE
                 else mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST)
        zeros8 = [0] * 8
        return mavlink.MAVLink_autopilot_version_message(caps, 0, 0, 0, 0, zeros8, zeros8, zeros8, 0, 0, 0, [0] * 18)

    def send(self, msg: Any) -> None:
        """Sends one message built elsewhere (NAMED_VALUE_FLOAT of the attitude monitor, ODOMETRY …) on
        every link now; errors are counted like the streams'."""
        self._send_all(msg)

    def statustext(self, severity: int, text: str, kind: str | None = None) -> None:
        """Sends ``text`` on every link as STATUSTEXT at MAV_SEVERITY ``severity`` (0..7),
        chunked when longer than 50 bytes. ``kind`` (a short key) puts the text under the rate
        limit of that kind (see ``statustext_limit``): texts a peer can trigger pass one, the
        service's own reports (kind None) are never dropped."""
        if kind is not None:
            admitted = self._status_limit.admit(kind, text, time.monotonic_ns())
            self.stats.statustext_suppressed = self._status_limit.suppressed_total
            if admitted is None:
                return
            text = admitted
        self._statustext_id = self._statustext_id % 0xFFFF + 1  # 1..65535; 0 means "single chunk"
        for msg in encode_statustext(severity, text, self._statustext_id):
            self._send_all(msg)

    # ================================================================== receiving
    def _allow_unsigned(self, mav: Any, msg_id: int) -> bool:
        # pymavlink asks this for every message without a valid signature
        if msg_id in SIGNED_ONLY:
            self.stats.unsigned_rejected += 1
            self.stats.writes_refused += 1
            self._rejected = True
            return False
        return True

    def _next_message(self, ep: Endpoint) -> Any:
        """The next parsed message (or BAD_DATA) of ``ep``; None when nothing is pending."""
        for _ in range(64):  # bounded: at most this many reads per call
            self._rejected = False
            msg = self._parse(ep, b"")
            if msg is not None:
                return msg
            if ep.datagram and ep.end_of_datagram():
                self.stats.malformed += 1
            before = ep.receive_errors
            data = ep.read()
            if ep.receive_errors != before:
                self.stats.receive_errors[ep.url] = ep.receive_errors
            if not data:
                return None
            self._rejected = False
            msg = self._parse(ep, data)
            if msg is not None:
                return msg
            if not ep.datagram:
                return None  # a stream link waits for the rest of the message
        return None

    def _parse(self, ep: Endpoint, data: bytes) -> Any:
        try:
            return ep.parse(data)
        except Exception as exc:  # pymavlink turns bad input into BAD_DATA; this is the safety net
            self.stats.malformed += 1
            self.stats.last_error = f"{ep.url}: parser: {type(exc).__name__}: {exc}"
            ep.reset_parser()
            return None

    def poll(self, max_messages: int = 100) -> int:
        """Handles up to ``max_messages`` pending incoming messages (all endpoints, round
        robin) without blocking; returns how many were handled, malformed ones included."""
        if self._resolving:
            self._report_resolution()
        handled = 0
        idle: set[int] = set()
        while handled < max_messages and len(idle) < len(self._endpoints):
            for i, ep in enumerate(self._endpoints):
                if i in idle or handled >= max_messages:
                    continue
                msg = self._next_message(ep)
                if msg is None:
                    idle.add(i)
                    continue
                handled += 1
                self._handle(ep, msg)
        return handled

    def _report_resolution(self) -> None:
        """A destination name that does not resolve (or resolves at last): one journal line and
        one STATUSTEXT (on the links that work) per change; its unsent messages counted."""
        for ep in self._resolving:
            self.stats.unresolved[ep.url] = ep.unresolved
            news = ep.resolution_news()
            if news is None:
                continue
            resolved = ep.resolver is not None and ep.resolver.address is not None
            _log.log(logging.INFO if resolved else logging.WARNING, news)
            self.statustext(mavlink.MAV_SEVERITY_INFO if resolved else mavlink.MAV_SEVERITY_WARNING, news)
        # resolved (and its news given): nothing more to report of it
        self._resolving = [ep for ep in self._resolving if ep.resolver is None or ep.resolver.address is None]

    def _handle(self, ep: Endpoint, msg: Any) -> None:
        name = msg.get_type()
        if name == "BAD_DATA":
            if self._rejected:  # a write without valid signature: already counted as rejected
                return
            self.stats.malformed += 1
            if "CRC" in str(getattr(msg, "reason", "")):
                self.stats.bad_crc += 1
            return
        if name.startswith("UNKNOWN_"):
            self.stats.unknown_ids += 1
            return
        self.stats.received_total += 1
        self.stats.received[name] = self.stats.received.get(name, 0) + 1
        handler = self._HANDLERS.get(name)
        if handler is None:
            return
        try:
            handler(self, ep, msg)
        except Exception as exc:  # a service callback failed: count it, keep serving
            self.stats.handler_errors += 1
            self.stats.last_error = f"{name}: {type(exc).__name__}: {exc}"

    def _for_us(self, msg: Any, broadcast_system: bool = True) -> bool:
        ts, tc = int(msg.target_system), int(msg.target_component)
        ok = (ts == self.identity.system_id or (broadcast_system and ts == 0)) and \
             tc in (self.identity.component_id, mavlink.MAV_COMP_ID_ALL)
        if not ok:
            self.stats.not_for_us += 1
        return ok

    # ------------------------------------------------------------------ parameter protocol
    def _on_param_request_list(self, ep: Endpoint, msg: Any) -> None:
        if self._for_us(msg):
            for answer in self.params.handle_request_list():
                self._send_all(answer, ep)

    def _on_param_request_read(self, ep: Endpoint, msg: Any) -> None:
        if self._for_us(msg):
            for answer in self.params.handle_request_read(msg):
                self._send_all(answer, ep)

    def _on_param_set(self, ep: Endpoint, msg: Any) -> None:
        # a set must name our system: a broadcast write to every system is not honoured
        if not self._for_us(msg, broadcast_system=False):
            return
        self.sender = sender = Sender.of(msg)
        try:
            answers, reason, result = self.params.handle_set(msg)
        finally:
            self.sender = None
        for answer in answers:
            self._send_all(answer)  # every link, so every ground station sees the new value
        if reason:
            self.stats.writes_refused += 1
            # anyone on a link can send these: rate-limited, unknown names and rejections apart
            self.statustext(mavlink.MAV_SEVERITY_WARNING, reason,
                            kind="param unknown" if not answers else "param rejected")
        elif result is not None and result.changed:
            self._accepted(AcceptedWrite(answers[0].param_id, result.old, result.value, sender))

    def _accepted(self, write: AcceptedWrite) -> None:
        """Counts an accepted write and tells ``on_write``; its failure is counted, not raised:
        the write is in force and answered already."""
        self.stats.writes_accepted += 1
        if self.on_write is None:
            return
        try:
            self.on_write(write)
        except Exception as exc:
            self.stats.handler_errors += 1
            self.stats.last_error = f"recording {write.name}: {type(exc).__name__}: {exc}"

    # ------------------------------------------------------------------ command protocol
    def _on_command_long(self, ep: Endpoint, msg: Any) -> None:
        if not self._for_us(msg):
            return
        cmd = Command.from_command_long(msg)
        self._reply_after_ack = None
        self._write_done = None
        try:
            result = self.commands.dispatch(cmd)
        except Exception as exc:
            self.stats.handler_errors += 1
            self.stats.last_error = f"command {cmd.command}: {type(exc).__name__}: {exc}"
            result = CommandResult(mavlink.MAV_RESULT_FAILED, f"command {cmd.command} failed: {exc}")
        ok = result.result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_IN_PROGRESS)
        if cmd.command in WRITE_COMMANDS and not ok:
            self.stats.writes_refused += 1
        self._send_all(encode_command_ack(cmd, result), ep)
        if result.text:
            self.statustext(mavlink.MAV_SEVERITY_INFO if ok else mavlink.MAV_SEVERITY_WARNING, result.text,
                            kind=f"command {cmd.command}")
        if self._reply_after_ack is not None:
            reply, self._reply_after_ack = self._reply_after_ack, None
            self._send_all(reply, ep)
        if self._write_done is not None and ok:
            write, self._write_done = self._write_done, None
            self._accepted(write)

    def _on_command_int(self, ep: Endpoint, msg: Any) -> None:
        # none of the supported commands has a position, so MAVLink wants them as COMMAND_LONG
        if not self._for_us(msg):
            return
        cmd = Command(int(msg.command), (0.0,) * 7, msg.get_srcSystem(), msg.get_srcComponent())
        self._send_all(encode_command_ack(cmd, CommandResult(mavlink.MAV_RESULT_COMMAND_LONG_ONLY)), ep)

    _HANDLERS: dict[str, Callable[["MavlinkComponent", Endpoint, Any], None]] = {
        "PARAM_REQUEST_LIST": _on_param_request_list,
        "PARAM_REQUEST_READ": _on_param_request_read,
        "PARAM_SET": _on_param_set,
        "COMMAND_LONG": _on_command_long,
        "COMMAND_INT": _on_command_int,
    }

    def _stream_of(self, param: float) -> _Stream | None:
        if not math.isfinite(param):
            return None
        mid = int(param)
        return next((s for s in self._streams.values() if s.msg_id == mid), None)

    def _cmd_set_message_interval(self, cmd: Command) -> CommandResult:
        s = self._stream_of(cmd.params[0])
        interval_us = cmd.params[1]
        if s is None:
            return CommandResult(mavlink.MAV_RESULT_DENIED)  # the command is known, that message is not ours
        if not math.isfinite(interval_us) or (interval_us < 0 and interval_us != -1):
            return CommandResult(mavlink.MAV_RESULT_DENIED)
        if interval_us == -1:
            hz = 0.0
        elif interval_us == 0:
            hz = self._default_rates[s.name]
        else:
            hz = 1e6 / interval_us
            if hz > self.max_rate_hz or hz < MIN_RATE_HZ:
                self.stats.rates_refused += 1
                return CommandResult(mavlink.MAV_RESULT_DENIED,
                                     f"{s.name}: {MIN_RATE_HZ:g}..{self.max_rate_hz:g} Hz")
        # interval 0 returns to the configured rate, whatever it is: the operator's choice
        if s.name == "HEARTBEAT" and interval_us != 0 and hz < HEARTBEAT_MIN_HZ:
            self.stats.rates_refused += 1
            return CommandResult(mavlink.MAV_RESULT_DENIED,
                                 f"HEARTBEAT stays on: {HEARTBEAT_MIN_HZ:g}..{self.max_rate_hz:g} Hz")
        old = s.hz
        if hz != old:
            self.set_rate(s.name, hz)
            self._write_done = AcceptedWrite(f"{s.name} rate Hz", old, hz, cmd.sender)
        return CommandResult(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_preflight_calibration(self, cmd: Command) -> CommandResult:
        result = self._calibrate(cmd)
        sensor = calibrated_sensor(cmd)
        if sensor:  # recorded when the command is accepted (the ACK says so)
            self._write_done = AcceptedWrite("calibration", None, sensor, cmd.sender)
        return result

    def _cmd_get_message_interval(self, cmd: Command) -> CommandResult:
        s = self._stream_of(cmd.params[0])
        if s is None:
            return CommandResult(mavlink.MAV_RESULT_DENIED)
        interval = -1 if s.hz <= 0 else int(round(1e6 / s.hz))
        self._reply_after_ack = mavlink.MAVLink_message_interval_message(s.msg_id, interval)
        return CommandResult(mavlink.MAV_RESULT_ACCEPTED)

    def _cmd_request_message(self, cmd: Command) -> CommandResult:
        p1 = cmd.params[0]
        mid = int(p1) if math.isfinite(p1) else -1
        name = next((n for n in (*STREAMABLE, "AUTOPILOT_VERSION") if message_id(n) == mid), None)
        if name is None:
            return CommandResult(mavlink.MAV_RESULT_DENIED)
        msg = self._build_once(name, self._telemetry_now())
        if msg is None:  # supported, but nothing to report before the first estimate
            return CommandResult(mavlink.MAV_RESULT_TEMPORARILY_REJECTED)
        self._reply_after_ack = msg  # MAVLink: ACK first, then the message
        return CommandResult(mavlink.MAV_RESULT_ACCEPTED)

    # ================================================================== lifetime
    @property
    def endpoints(self) -> list[str]:
        return [ep.url for ep in self._endpoints]

    def close(self) -> None:
        """Closes every link. The component cannot be used afterwards."""
        for ep in self._endpoints:
            ep.close()
        self._endpoints = []

    def __enter__(self) -> "MavlinkComponent":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
