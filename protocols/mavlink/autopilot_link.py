"""The link to the flight controller: one pymavlink connection, read on its own thread.

Beside an autopilot the service uses a single connection (``source.mavlink_connection``, any
pymavlink string: ``/dev/ttyAMA0,921600``, ``udpin:0.0.0.0:14540``, ``udpout:…``, ``tcp:…``)
for everything it exchanges with the flight controller: the autopilot's IMU as a source
(``drivers/mavlink_imu.py``), TIMESYNC, ODOMETRY out and the attitude monitor
(``ahrs_service/attitude_monitor.py``). This module owns that connection.

Why a thread: a message's receive time must be taken when it arrives, not when the 200 Hz
loop next polls (PX4 drops TIMESYNC samples whose round trip exceeds 10 ms, and an IMU
sample's arrival is the fallback for mapping the autopilot's clock). The thread waits on the
link's file descriptor (``select``), stamps each read with ``time.monotonic_ns()`` and hands
every parsed message with that stamp to the subscribers of its type. Subscribers run on this
thread and must be quick (append to a deque); everything else happens on the loop's thread.

What it detects and survives:

* **the autopilot**: the first HEARTBEAT whose ``autopilot`` is not ``MAV_AUTOPILOT_INVALID``,
  whose type is not a ground station or companion and whose system (and component) is the
  configured one (``autopilot_system_id``/``autopilot_component_id``; 0: any) names it
  (:class:`AutopilotInfo`: PX4, ArduPilot or other, system and component id); subscribers may
  ask for messages from it only. It is never replaced: another flight controller heard later
  (or before, when it is not the configured one) is counted (``stats.other_autopilots``) and
  reported once, never adopted;
* **a second sender with the autopilot's ids**: on a UDP listening link the autopilot's
  address is pinned when it is adopted; the same ids from another address while the pinned
  one still speaks (within ``HANDOVER_S``) are counted (``stats.identity_conflicts``),
  reported once and not dispatched as the autopilot's (an address silent that long hands
  over: a restarted router or autopilot). Sequence numbers that keep going backwards (two
  senders interleaving behind one address or on a serial line) are reported as a conflict
  too (``stats.sequence_backsteps``);
* **silence** (a UDP peer gone, a cable pulled): no message for ``silence_s`` makes the link
  *lost* (``stats.losses``); the next message makes it *up* again (``stats.recoveries``) and
  starts a new ``session`` — users that configured the autopilot (stream intervals) do it again;
* **where we are**: our own HEARTBEAT (a companion component, ``MAV_TYPE_IMU``) goes out every
  ``HEARTBEAT_S``, so an autopilot or router reached with ``udpout:``/``tcp:`` learns our
  address before it has sent anything;
* **a vanished device** (a USB serial adapter unplugged, the pty closed): a read error or an
  end of file closes the connection and re-opens it every ``reopen_s`` until it opens
  (``stats.read_errors``, ``stats.reopens``, ``stats.open_failures``).
* **messages of another dialect**: a well-framed message whose id the service's dialect
  (``common``) does not define — ArduPilot streams its own (AHRS2, EKF_STATUS_REPORT …) — is
  counted by id (``stats.unknown_messages``, ``stats.unknown``), reported once per id and not
  parsed; it keeps the link alive like any message. Its CRC is checked where ArduPilot's dialect
  knows the id (a damaged one is bad data); an id no dialect here knows is taken as framed.
  Only damage counts as ``stats.bad_data``: a bad CRC, bytes outside any frame, a datagram's
  truncated tail.

Reports (a foreign autopilot, a conflict, TIMESYNC replies refused or its clock jumping) are
kept as notices: logged once (this module's logger, under ``ahrs_service``: the journal) and queued for
the service, which takes them with :meth:`AutopilotLink.take_notices` (STATUSTEXT, ``/log``).

Time is ``time.monotonic_ns()`` throughout. The remote clock (the autopilot's boot time) is
mapped onto ours by :class:`RemoteTimeline`, one per link, so the IMU source and the monitor
use the same mapping and their times stay consistent.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import select
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.endpoints import Endpoint
from ahrs_service.protocols.mavlink.identity import Identity, encode_heartbeat
from ahrs_service.protocols.mavlink.timesync import MAX_DRIFT_PPM, REQUEST_RATE_HZ, TimeSync

#: no message for this long: the link counts as lost (autopilots beat at 1 Hz, stream faster)
SILENCE_S = 2.0
#: a connection that failed or vanished is re-opened this often, s
REOPEN_S = 0.5
#: how long one wait on the file descriptor lasts, s (bounds the reaction to stop() and silence)
POLL_S = 0.05
#: our HEARTBEAT on the link, s: a ``udpout:``/``tcp:`` autopilot (or router) learns where we are
#: from it before we have heard anything, and autopilots route to components they have heard
HEARTBEAT_S = 1.0
#: messages parsed per read at most (a read of 4 kB holds at most ~90 MAVLink frames)
_MAX_PER_READ = 256
#: the autopilot's pinned UDP address silent this long: its ids from a new address take over
#: (a restarted router or autopilot), s. Below any silence of a live autopilot beside us: it
#: streams the IMU and answers TIMESYNC at 10 Hz
HANDOVER_S = 0.5
#: sequence numbers of the autopilot's messages looked at for interleaving, and how many of
#: them stepping backwards (not a loss: a loss only skips forward) make a conflict
SEQUENCE_WINDOW = 64
SEQUENCE_BACKSTEPS = 8
#: notices kept for the service at most (the oldest go first; each was logged already)
NOTICES = 32
#: TIMESYNC clock jumps reported at most this often, s (a peer could jump every 0.5 s)
JUMP_NOTICE_S = 10.0
#: message ids of another dialect reported by name at most (each once); the others are counted only
UNKNOWN_IDS_REPORTED = 16
#: message ids of another dialect counted one by one at most (a peer could send 2^24 of them);
#: the messages of further ids are in the total only
UNKNOWN_IDS_KEPT = 64

_log = logging.getLogger(__name__)

#: how much later than its sample an IMU message may arrive at the least, s: a TIMESYNC estimate
#: that puts the samples further before the arrivals' floor (the smallest arrival − remote time
#: of a few seconds) is wrong (a TIMESYNC clock that jumped while the IMU stamps did not). A
#: queue on the link delays some messages longer; the floor is the least delayed one's
MAX_LATENCY_S = 1.0

#: HEARTBEAT types that are never the flight controller
_NOT_AUTOPILOT_TYPES = frozenset({
    mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL,
    mavlink.MAV_TYPE_ADSB, mavlink.MAV_TYPE_CAMERA, mavlink.MAV_TYPE_IMU,
})

Sink = Callable[[Any, int], None]


def frame_message_id(frame: bytes) -> int:
    """The message id in the header of a MAVLink 1 or 2 frame."""
    if frame[0] == mavlink.PROTOCOL_MARKER_V1:
        return frame[5]
    return frame[7] | frame[8] << 8 | frame[9] << 16


def frame_crc_ok(frame: bytes, crc_extra: int) -> bool:
    """Whether a whole MAVLink 1 or 2 frame's checksum holds with the message's ``crc_extra``."""
    signed = frame[0] == mavlink.PROTOCOL_MARKER_V2 and frame[2] & mavlink.MAVLINK_IFLAG_SIGNED
    end = len(frame) - 2 - (mavlink.MAVLINK_SIGNATURE_BLOCK_LEN if signed else 0)
    if end < 1:
        return False
    crc = mavlink.x25crc(bytearray(frame[1:end]) + bytes([crc_extra]))
    return crc.crc == int.from_bytes(frame[end:end + 2], "little")


def ardupilot_message(msg_id: int) -> Any:
    """The message class of ``msg_id`` in ArduPilot's dialect (``ardupilotmega``, a superset of
    ``common``), None when it has none. Imported on first use: only a link that carries
    messages outside ``common`` pays for it."""
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega.mavlink_map.get(int(msg_id))


@dataclass(frozen=True)
class AutopilotInfo:
    """The flight controller heard on the link.

    kind: ``"px4"``, ``"ardupilot"`` or ``"other"`` (HEARTBEAT.autopilot).
    system_id, component_id: its MAVLink address (the target of our commands).
    mav_type: HEARTBEAT.type (MAV_TYPE_QUADROTOR …).
    """

    kind: str
    system_id: int
    component_id: int
    mav_type: int

    @classmethod
    def from_heartbeat(cls, msg: Any) -> "AutopilotInfo | None":
        """The autopilot a HEARTBEAT announces, or None when it is not a flight controller."""
        autopilot = int(msg.autopilot)
        if autopilot == mavlink.MAV_AUTOPILOT_INVALID or int(msg.type) in _NOT_AUTOPILOT_TYPES:
            return None
        kind = {mavlink.MAV_AUTOPILOT_PX4: "px4", mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot"}.get(autopilot, "other")
        return cls(kind, msg.get_srcSystem(), msg.get_srcComponent(), int(msg.type))


@dataclass
class LinkStats:
    """Counters of the autopilot link (published in the flight log's /loop source section)."""

    messages: int = 0  # parsed messages, all senders
    bad_data: int = 0  # damage only: bad CRC, bytes outside any frame, truncated datagram tails
    unknown_messages: int = 0  # well-framed messages of an id the dialect does not define
    read_errors: int = 0  # reads that failed (device vanished, socket error)
    send_errors: int = 0  # messages that could not be written
    open_failures: int = 0  # attempts to (re-)open the connection that failed
    reopens: int = 0  # connections re-opened after a failure
    losses: int = 0  # up -> lost transitions (silence or a vanished device)
    recoveries: int = 0  # lost -> up transitions
    other_autopilots: int = 0  # HEARTBEATs of a flight controller that is not the one listened to
    other_system_messages: int = 0  # messages of any system but the autopilot's (a GCS behind a router too)
    identity_conflicts: int = 0  # messages with the autopilot's ids from a second address
    sequence_backsteps: int = 0  # the autopilot's sequence numbers going backwards
    address_handovers: int = 0  # the autopilot's ids moved to a new address after its silence
    last_error: str = ""
    received: dict[str, int] = field(default_factory=dict)
    #: unknown_messages by message id (the id as text, the log's JSON keys), UNKNOWN_IDS_KEPT ids at most
    unknown: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, dict) else v) for k, v in self.__dict__.items()}


@dataclass
class _Subscription:
    names: frozenset[str]
    sink: Sink
    autopilot_only: bool


class RemoteTimeline:
    """Maps the autopilot's clock (µs since its boot) onto ours (monotonic ns).

    local_ns = remote_us · 1000 + offset_ns, with one *held* offset: it is taken from the best
    estimate available when the first time is mapped and then kept, so consecutive samples keep
    exactly the spacing the autopilot's clock gave them (the estimator integrates that spacing).
    The estimate is the TIMESYNC one when the attached :class:`TimeSync`
    (protocols/mavlink/timesync.py, used under ``timesync_lock``) is synced, else the smallest
    ``arrival − remote time`` of the last few seconds (the latency floor of the link). When the
    estimate moves more than ``deadband_ns`` away from the held offset (clock drift, a better
    sync), the held offset slews towards it by at most ``slew_ppm`` of the elapsed remote time;
    beyond ``step_ns`` it steps (``steps`` counts those; a rebooted autopilot steps too).
    TIMESYNC's estimate is used only between ``max_latency_s`` before the arrivals' floor and
    ``deadband_ns`` after it (``timesync_refused`` counts the others).
    """

    def __init__(self, *, deadband_ns: int = 10_000_000, slew_ppm: float = 200.0, step_ns: int = 50_000_000,
                 window_s: float = 4.0, max_latency_s: float = MAX_LATENCY_S) -> None:
        self.deadband_ns = int(deadband_ns)
        self.slew = float(slew_ppm) * 1e-6
        self.step_ns = int(step_ns)
        self.timesync: TimeSync | None = None
        self.timesync_lock = threading.Lock()
        self.offset_ns: int | None = None
        self.steps = 0
        #: TIMESYNC estimates not used: more than ``max_latency_ns`` before the arrivals' floor
        #: (or after it), i.e. a sample taken long before it could have been sent
        self.timesync_refused = 0
        self.max_latency_ns = int(max_latency_s * 1e9)
        self.slewed_ns = 0  # total |adjustment| by slewing, ns (0: every spacing is the autopilot's)
        self._bin_ns = int(window_s * 1e9 / 4)
        self._bins: collections.deque[tuple[int, int]] = collections.deque(maxlen=4)  # (bin, min offset)
        self._last_remote_ns: int | None = None
        self._lock = threading.Lock()

    def arrival(self, remote_us: int, rx_ns: int) -> None:
        """A message stamped ``remote_us`` by the autopilot arrived at ``rx_ns`` (reader thread)."""
        off = int(rx_ns) - int(remote_us) * 1000
        b = int(rx_ns) // self._bin_ns
        with self._lock:
            if self._bins and self._bins[-1][0] == b:
                if off < self._bins[-1][1]:
                    self._bins[-1] = (b, off)
            else:
                self._bins.append((b, off))

    def estimate_ns(self, remote_us: int) -> int | None:
        """The best current estimate of local − remote, ns (None before any arrival).

        A sample is never taken after it arrived: an offset above the arrivals' floor by more
        than ``deadband_ns`` is impossible, and TIMESYNC's is not used then. That is the case
        when the autopilot's IMU stamps jump (a clock stepped by 1e9 s) while its TIMESYNC
        replies do not: TIMESYNC's offset put every sample 31 years after its arrival, and
        once the stamps came back, every later sample was dropped as older than those.
        Nor does a message arrive ``max_latency_ns`` after its sample at the least: a TIMESYNC
        offset that far below the floor (its clock jumped ahead while the IMU stamps did not)
        would place every later sample before the ones already handed out."""
        with self._lock:
            floor = min(o for _, o in self._bins) if self._bins else None
        ts = self.timesync
        if ts is not None:
            with self.timesync_lock:
                synced = int(ts.to_local_ns(int(remote_us))) - int(remote_us) * 1000 if ts.synced else None
            if synced is not None:
                if floor is None or floor - self.max_latency_ns <= synced <= floor + self.deadband_ns:
                    return synced
                self.timesync_refused += 1
        return floor

    def to_local_ns(self, remote_us: int) -> int | None:
        """``remote_us`` (autopilot µs) on our monotonic clock, ns; None before anything arrived."""
        remote_ns = int(remote_us) * 1000
        want = self.estimate_ns(remote_us)
        if self.offset_ns is None:
            if want is None:
                return None
            self.offset_ns = want
        elif want is not None:
            error = want - self.offset_ns
            back = self._last_remote_ns is not None and remote_ns < self._last_remote_ns
            if abs(error) > self.step_ns or back:
                self.offset_ns = want
                self.steps += 1
            elif abs(error) > self.deadband_ns and self._last_remote_ns is not None:
                most = int((remote_ns - self._last_remote_ns) * self.slew)
                change = max(-most, min(most, error))
                self.offset_ns += change
                self.slewed_ns += abs(change)
        self._last_remote_ns = remote_ns
        return remote_ns + self.offset_ns

    def peek_local_ns(self, remote_us: int) -> int | None:
        """``remote_us`` on our clock with the held offset as it is (no update; any thread);
        None before the first time was mapped."""
        offset = self.offset_ns
        return None if offset is None else int(remote_us) * 1000 + offset

    def reset(self) -> None:
        """Forgets the held offset and the arrivals (the autopilot rebooted)."""
        with self._lock:
            self._bins.clear()
        self.offset_ns = None
        self._last_remote_ns = None


class LinkClock:
    """The link's clocks as other threads see them (ODOMETRY's ``time_usec``): the part of
    :class:`TimeSync` an :class:`~ahrs_service.protocols.mavlink.odometry.OdometrySender` uses,
    under the link's lock.

    ``presented_ns`` gives a time of ours in the autopilot's clock once TIMESYNC is synced. For a
    time the IMU source mapped (a sample's), the exact inverse of that mapping is used: the
    held offset of the :class:`RemoteTimeline`, so an estimate of a sample is stamped with the
    very time the autopilot gave that sample (TIMESYNC's estimate may since have moved within
    the timeline's deadband).
    """

    def __init__(self, timesync: TimeSync, timeline: RemoteTimeline, lock: threading.Lock) -> None:
        self._ts, self._timeline, self._lock = timesync, timeline, lock

    @property
    def synced(self) -> bool:
        with self._lock:
            return self._ts.synced

    def presented_ns(self, local_ns: int) -> int:
        """``local_ns`` (our monotonic ns) in the autopilot's clock, ns; ours until synced."""
        with self._lock:
            if not self._ts.synced:
                return int(local_ns)
            offset = self._timeline.offset_ns
            if offset is not None:
                return int(local_ns) - offset
            return self._ts.presented_ns(local_ns)


class AutopilotLink:
    """One connection to the flight controller, read on a thread (see the module docstring).

    url: pymavlink connection string. system_id, component_id: our own MAVLink address on the
    link (the service's identity). autopilot_system_id, autopilot_component_id: the flight
    controller listened to (0: the first one heard). silence_s, reopen_s: see the module
    constants.
    """

    def __init__(self, url: str, *, system_id: int = 1, component_id: int = mavlink.MAV_COMP_ID_IMU,
                 autopilot_system_id: int = 0, autopilot_component_id: int = 0,
                 silence_s: float = SILENCE_S, reopen_s: float = REOPEN_S) -> None:
        self.url = url
        self.system_id, self.component_id = int(system_id), int(component_id)
        self.autopilot_system_id, self.autopilot_component_id = int(autopilot_system_id), int(autopilot_component_id)
        self.silence_ns = int(silence_s * 1e9)
        self.reopen_ns = int(reopen_s * 1e9)
        self.stats = LinkStats()
        #: TIMESYNC with the autopilot: requested at REQUEST_RATE_HZ by the reader thread once an
        #: autopilot was heard, its replies and requests handled there on arrival. Other threads
        #: (ODOMETRY's time stamps) use it under ``timesync_lock``.
        self.timesync = TimeSync()
        self.timeline = RemoteTimeline()
        self.timeline.timesync = self.timesync
        self.timesync_lock = self.timeline.timesync_lock
        #: what ODOMETRY (another thread) uses to stamp its messages in the autopilot's clock
        self.clock = LinkClock(self.timesync, self.timeline, self.timesync_lock)
        self._next_timesync_ns = 0
        self._next_heartbeat_ns = 0
        # the service's address on this link: a component of the autopilot's vehicle (MAV_TYPE_IMU)
        self._heartbeat = encode_heartbeat(Identity("companion", self.system_id, self.component_id),
                                           mavlink.MAV_STATE_ACTIVE)
        self.autopilot: AutopilotInfo | None = None
        #: increments each time the link comes up (first message, after silence, after a re-open)
        self.session = 0
        self.state = "waiting"  # waiting (nothing heard yet), up, lost
        self.last_rx_ns: int | None = None
        self._ep: Endpoint | None = None
        self._subs: list[_Subscription] = []
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._reopen_at_ns = 0
        self._notices: collections.deque[tuple[int, str]] = collections.deque(maxlen=NOTICES)
        self._notices_lock = threading.Lock()
        self._reported: set[Any] = set()  # what was reported once (a foreign autopilot, an address)
        self._ap_address: Any = None  # the autopilot's UDP address (listening links), pinned
        self._ap_heard_ns = 0  # the newest message from it
        self._ap_seq: int | None = None
        self._backsteps: collections.deque[bool] = collections.deque(maxlen=SEQUENCE_WINDOW)
        self._jump_noted_ns = -(1 << 62)  # the last TIMESYNC jump reported

    # ------------------------------------------------------------------ set-up
    def subscribe(self, names: Iterable[str], sink: Sink, *, autopilot_only: bool = True) -> None:
        """Calls ``sink(msg, rx_ns)`` on the reader thread for every message named in ``names``
        (``autopilot_only``: only those the detected autopilot sent). Any thread, any time."""
        # a new list, not an append: the reader thread iterates the old one meanwhile
        self._subs = [*self._subs, _Subscription(frozenset(names), sink, autopilot_only)]

    def unsubscribe(self, sink: Sink) -> None:
        """Stops calling ``sink`` (any thread; a message being dispatched may still reach it)."""
        self._subs = [sub for sub in self._subs if sub.sink != sink]

    def open(self) -> None:
        """Opens the connection and starts the reader thread. A connection string that cannot be
        opened at all (no such scheme, a port in use) raises OSError naming it; a serial device
        that is missing at the start is waited for like one that vanished."""
        try:
            self._ep = self._connect()
        except OSError as exc:
            if not self._is_serial():
                raise
            self._note_error(f"{exc}")
            self.stats.open_failures += 1
            self._reopen_at_ns = time.monotonic_ns() + self.reopen_ns
        self._thread = threading.Thread(target=self._run, name="autopilot-link", daemon=True)
        self._thread.start()

    def _is_serial(self) -> bool:
        return not any(self.url.startswith(p) for p in ("udp", "tcp", "mcast"))

    def _connect(self) -> Endpoint:
        return Endpoint(self.url, self.system_id, self.component_id)

    # ------------------------------------------------------------------ sending
    def send(self, msg: Any) -> bool:
        """Writes ``msg`` on the link (any thread); False when there is no connection or the
        write failed (counted in ``stats.send_errors``)."""
        with self._send_lock:
            ep = self._ep
            if ep is None:
                self.stats.send_errors += 1
                return False
            if ep.send_many([msg]):
                return True
            self.stats.send_errors += 1
            self.stats.last_error = ep.last_send_error
            return False

    def command_long(self, command: int, *params: float) -> bool:
        """COMMAND_LONG to the detected autopilot (False while none was heard)."""
        ap = self.autopilot
        if ap is None:
            return False
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        return self.send(mavlink.MAVLink_command_long_message(ap.system_id, ap.component_id, command, 0, *p[:7]))

    def set_message_interval(self, name: str, rate_hz: float) -> bool:
        """Asks the autopilot to stream message ``name`` at ``rate_hz`` (MAV_CMD_SET_MESSAGE_INTERVAL,
        param2 = interval µs); False while no autopilot was heard."""
        msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
        return self.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, round(1e6 / rate_hz))

    # ------------------------------------------------------------------ state
    def status(self) -> dict[str, Any]:
        """The link for the flight log (``/loop`` ``autopilot``, once a second): state, the
        autopilot, counters, TIMESYNC's offset (remote − local, ns) and drift (ppm), the
        samples' held offset (local − remote, ns)."""
        ap = self.autopilot
        with self.timesync_lock:
            ts = self.timesync
            timesync = {"synced": ts.synced, "offset_ns": ts.offset_ns, "drift_ppm": ts.drift_ppm,
                        **dataclasses.asdict(ts.counters)}
        tl = self.timeline
        return {
            "state": self.state,
            "session": self.session,
            "autopilot": None if ap is None else dataclasses.asdict(ap),
            "link": self.stats.as_dict(),
            "timesync": timesync,
            "timeline": {"offset_ns": tl.offset_ns, "slewed_ns": tl.slewed_ns, "steps": tl.steps,
                         "timesync_refused": tl.timesync_refused},
        }

    @property
    def up(self) -> bool:
        return self.state == "up"

    def notify(self, text: str, severity: int = 4, once: Any = None) -> None:
        """A report for humans (any thread): logged now, queued for :meth:`take_notices`.
        ``once``: a key; a second notice with the same key is not made. ``severity``:
        MAVLink's (4 warning)."""
        with self._notices_lock:
            if once is not None:
                if once in self._reported:
                    return
                self._reported.add(once)
            self._notices.append((int(severity), text))
        _log.log(logging.WARNING if severity <= 4 else logging.INFO, text)

    def take_notices(self) -> list[tuple[int, str]]:
        """The notices since the last call, oldest first, as (severity, text): for the service
        to report (STATUSTEXT, ``/log``); each was logged when it was made."""
        with self._notices_lock:
            out = list(self._notices)
            self._notices.clear()
        return out

    def _note_error(self, text: str) -> None:
        self.stats.last_error = f"{self.url}: {text}"

    def _went_up(self) -> None:
        if self.state == "lost":
            self.stats.recoveries += 1
        self.state = "up"
        self.session += 1

    def _went_lost(self, why: str) -> None:
        if self.state == "up":
            self.stats.losses += 1
        self.state = "lost"
        self._note_error(why)

    # ------------------------------------------------------------------ the reader thread
    def _run(self) -> None:
        while not self._stop.is_set():
            ep = self._ep
            now = time.monotonic_ns()
            if ep is None:
                if now >= self._reopen_at_ns:
                    self._reopen(now)
                self._stop.wait(POLL_S)
                continue
            if self.state == "up" and self.last_rx_ns is not None and now - self.last_rx_ns > self.silence_ns:
                self._went_lost(f"silent for {(now - self.last_rx_ns) / 1e9:.1f} s")
            if now >= self._next_heartbeat_ns:
                self._next_heartbeat_ns = now + int(HEARTBEAT_S * 1e9)
                self.send(self._heartbeat)
            if self.autopilot is not None and self.state == "up" and now >= self._next_timesync_ns:
                self._next_timesync_ns = now + int(1e9 / REQUEST_RATE_HZ)
                with self.timesync_lock:
                    request = self.timesync.request(time.monotonic_ns())
                self.send(request.encode())
            try:
                fd = ep.conn.port.fileno()
                ready, _, _ = select.select([fd], [], [], POLL_S)
            except (OSError, ValueError, AttributeError) as exc:
                self._drop(f"wait failed: {exc}")
                continue
            if not ready:
                continue
            rx_ns = time.monotonic_ns()  # the arrival, before the bytes are even read
            before = ep.receive_errors
            data = ep.read()
            if ep.receive_errors != before or (not data and not ep.datagram):
                # a readable stream that gives nothing (EOF) or an error: the device is gone
                self.stats.read_errors += 1
                self._drop("read failed: device vanished or closed")
                continue
            if data:
                self._parse(ep, data, rx_ns)

    def _parse(self, ep: Endpoint, data: bytes, rx_ns: int) -> None:
        msg = self._safe_parse(ep, data)
        for _ in range(_MAX_PER_READ):
            if msg is None:
                break
            self._dispatch(msg, rx_ns, getattr(ep, "_from", None))
            msg = self._safe_parse(ep, b"")
        if ep.datagram and ep.end_of_datagram():
            self.stats.bad_data += 1

    def _safe_parse(self, ep: Endpoint, data: bytes) -> Any:
        try:
            return ep.parse(data)
        except Exception as exc:  # pymavlink turns bad input into BAD_DATA; this is the safety net
            self.stats.bad_data += 1
            self._note_error(f"parser: {type(exc).__name__}: {exc}")
            ep.reset_parser()
            return None

    def _dispatch(self, msg: Any, rx_ns: int, address: Any = None) -> None:
        """One parsed message, from ``address`` (the sender's UDP address on a listening link,
        else None)."""
        name = msg.get_type()
        if name == "BAD_DATA":
            self.stats.bad_data += 1
            return
        if name.startswith("UNKNOWN_"):
            self._unknown(msg, rx_ns)
            return
        self.stats.messages += 1
        self.stats.received[name] = self.stats.received.get(name, 0) + 1
        self.last_rx_ns = rx_ns
        if self.state != "up":
            self._went_up()
        if name == "HEARTBEAT":
            heard = AutopilotInfo.from_heartbeat(msg)
            if heard is not None:
                self._heard_autopilot(heard, address, rx_ns)
        ap = self.autopilot
        system = msg.get_srcSystem()
        wanted = ap.system_id if ap is not None else self.autopilot_system_id
        if wanted and system != wanted:
            self.stats.other_system_messages += 1
        from_ap = ap is not None and system == ap.system_id and msg.get_srcComponent() == ap.component_id
        if from_ap:
            from_ap = self._same_sender(msg, address, rx_ns)
        if name == "TIMESYNC" and from_ap:
            with self.timesync_lock:
                counters = self.timesync.counters
                refused, jumps = counters.implausible, counters.jumps
                answer = self.timesync.handle(msg, rx_ns)
                jump_ns = self.timesync.last_jump_ns
            if counters.jumps != jumps and rx_ns - self._jump_noted_ns >= JUMP_NOTICE_S * 1e9:
                self._jump_noted_ns = rx_ns
                self.notify(f"autopilot link: TIMESYNC: the autopilot's clock jumped by {jump_ns / 1e9:+.3f} s; "
                            f"estimate restarted", 4)
            elif counters.implausible != refused and counters.jumps == jumps:
                self.notify("autopilot link: TIMESYNC replies refused: their offset moves faster than "
                            f"±{MAX_DRIFT_PPM:g} ppm and the round trip allow (counted in timesync.implausible)",
                            4, once=("timesync refused", self.timesync.counters.resets))
            if answer is not None:  # the autopilot asked us: answer at once
                self.send(answer.encode())
        for sub in self._subs:
            if name in sub.names and (from_ap or not sub.autopilot_only):
                try:
                    sub.sink(msg, rx_ns)
                except Exception as exc:  # a consumer's bug must not stop the link
                    self._note_error(f"{name} handler: {type(exc).__name__}: {exc}")

    def _unknown(self, msg: Any, rx_ns: int) -> None:
        """A frame whose id the dialect does not define: counted by id when it is intact (it
        shows the link alive), bad data when ArduPilot's dialect knows its CRC and it fails."""
        frame = bytes(msg.get_msgbuf())
        msg_id = frame_message_id(frame)
        known = ardupilot_message(msg_id)
        if known is not None and not frame_crc_ok(frame, known.crc_extra):
            self.stats.bad_data += 1
            return
        stats = self.stats
        stats.unknown_messages += 1
        key = str(msg_id)
        first = key not in stats.unknown
        if not first or len(stats.unknown) < UNKNOWN_IDS_KEPT:
            stats.unknown[key] = stats.unknown.get(key, 0) + 1
        self.last_rx_ns = rx_ns
        if self.state != "up":
            self._went_up()
        if first and len(stats.unknown) <= UNKNOWN_IDS_REPORTED:
            what = f"{known.msgname} of ArduPilot's dialect" if known is not None else "in no dialect known here"
            self.notify(f"autopilot link: message id {msg_id} ({what}) is not in the service's dialect: "
                        "counted in link.unknown, not used", 6)

    def _heard_autopilot(self, heard: AutopilotInfo, address: Any, rx_ns: int) -> None:
        """A flight controller's HEARTBEAT: adopted when it is the first one the configuration
        allows; any other one is counted and reported once, never adopted."""
        ap = self.autopilot
        if ap is None and (not self.autopilot_system_id or heard.system_id == self.autopilot_system_id) \
                and (not self.autopilot_component_id or heard.component_id == self.autopilot_component_id):
            self.autopilot = heard
            self._ap_address, self._ap_heard_ns = address, rx_ns
            return
        if ap is not None and (heard.system_id, heard.component_id) == (ap.system_id, ap.component_id):
            return
        self.stats.other_autopilots += 1
        if ap is not None:
            listening = f"listening to {ap.kind} system {ap.system_id} component {ap.component_id}"
        else:
            listening = f"listening to system {self.autopilot_system_id}" + (
                f" component {self.autopilot_component_id}" if self.autopilot_component_id else "")
        self.notify(f"autopilot link: ignoring {heard.kind} system {heard.system_id} component "
                    f"{heard.component_id}: {listening}", 4, once=("autopilot", heard.system_id, heard.component_id))

    def _same_sender(self, msg: Any, address: Any, rx_ns: int) -> bool:
        """Whether a message with the autopilot's ids comes from the sender adopted: its pinned
        UDP address (handed over after ``HANDOVER_S`` of its silence); its sequence numbers
        are watched for a second sender behind the same address."""
        pinned = self._ap_address
        if address is not None and pinned is not None and address != pinned:
            if rx_ns - self._ap_heard_ns < HANDOVER_S * 1e9:
                self.stats.identity_conflicts += 1
                ap = self.autopilot
                self.notify(f"autopilot link: a second sender at {address[0]}:{address[1]} uses the autopilot's ids "
                            f"(system {ap.system_id} component {ap.component_id}, at {pinned[0]}:{pinned[1]}): "
                            f"its messages are ignored", 4, once=("address", address))
                return False
            self.stats.address_handovers += 1
            self.notify(f"autopilot link: the autopilot's messages now come from {address[0]}:{address[1]} "
                        f"(silent at {pinned[0]}:{pinned[1]} for {(rx_ns - self._ap_heard_ns) / 1e9:.1f} s)", 5,
                        once=("handover", address))
            self._ap_address, self._ap_seq = address, None
        elif pinned is None and address is not None:
            self._ap_address = address
        self._ap_heard_ns = rx_ns
        seq = msg.get_seq()
        if self._ap_seq is not None:
            # a loss only skips forward; a step back of more than half the range is a second
            # sender's count (or a reboot: once, not SEQUENCE_BACKSTEPS times in a window)
            back = (seq - self._ap_seq) % 256 > 128
            self._backsteps.append(back)
            if back:
                self.stats.sequence_backsteps += 1
                if sum(self._backsteps) >= SEQUENCE_BACKSTEPS:
                    ap = self.autopilot
                    self.notify(f"autopilot link: the sequence numbers of system {ap.system_id} component "
                                f"{ap.component_id} keep going back: a second sender seems to use its ids",
                                4, once="sequence")
        self._ap_seq = seq
        return True

    def _drop(self, why: str) -> None:
        """The connection failed: close it, and re-open it after ``reopen_s``."""
        with self._send_lock:
            ep, self._ep = self._ep, None
        if ep is not None:
            ep.close()
        self._went_lost(why)
        self._reopen_at_ns = time.monotonic_ns() + self.reopen_ns

    def _reopen(self, now: int) -> None:
        try:
            ep = self._connect()
        except OSError as exc:
            self.stats.open_failures += 1
            self._note_error(f"{exc}")
            self._reopen_at_ns = now + self.reopen_ns
            return
        with self._send_lock:
            self._ep = ep
        self.stats.reopens += 1

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Stops the reader thread and closes the connection."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self._send_lock:
            ep, self._ep = self._ep, None
        if ep is not None:
            ep.close()
