"""TIMESYNC (message 111): the offset and drift between our monotonic clock and an autopilot's.

The protocol (MAVLink "Time Synchronization Protocol v2"): a request carries ``tc1 = 0`` and
``ts1`` = the requester's time (ns); the answer carries ``tc1`` = the answerer's time (ns) and
``ts1`` copied back. The requester then knows the round trip (now − ts1) and, assuming equal
delays both ways, one sample of the offset: ``tc1 − (ts1 + now) / 2``.

What follows PX4's ``src/lib/timesync/Timesync.cpp`` (``Timesync::update``; BSD-3-Clause,
see THIRD_PARTY_NOTICES): samples whose round trip exceeds 10 ms are discarded
(``MAX_RTT_SAMPLE``), and five deviating samples in a row mean the remote clock jumped (a
reboot) and the filter starts again (``MAX_CONSECUTIVE_HIGH_DEVIATION``).

What is physically possible, not PX4's fixed 100 ms, decides what deviates: the answerer
stamps ``tc1`` between our request and its reply, so a sample's offset is within half its
round trip of the true one, and two clocks drift apart by at most ``MAX_DRIFT_PPM`` (±1 000
ppm: crystals are within ±100). A reply whose offset moved from the newest accepted sample's
by more than ``MAX_DRIFT_PPM`` of the time between them plus half of both round trips (and
``JITTER_NS``) is refused (``counters.implausible``). Five refused replies in a row that agree
with one another by the same bound are a clock that jumped (a reboot, a clock set): the filter
starts again (``counters.jumps``). Replies that agree with nothing (a frozen clock:
drift −1 000 000 ppm) are refused one by one and never synced. The fitted drift is clamped to
±``MAX_DRIFT_PPM`` (a young window's noise can fit a steeper line).

The filter itself differs from PX4's double exponential smoothing (which needs 500 exchanges,
``CONVERGENCE_WINDOW``, before it calls itself converged): a least-squares line, offset
against our time, through the last ``WINDOW`` accepted samples, each weighted by how much its
round trip exceeds the shortest (a delay queued on one way only shows as a longer round
trip, and biases that sample's offset by up to half of it; ``RTT_FLOOR_NS``). Its slope is the drift (ppm) and
its value at a time is the offset there, so a synced estimate is usable after ``MIN_SAMPLES``
exchanges (half a second at the 10 Hz request rate) and stays unbiased under a constant drift.

Clocks: "local" is our ``time.monotonic_ns()``; "remote" is whatever clock the autopilot
answers with (PX4: ``hrt_absolute_time`` µs since boot ×1000; ArduPilot: ``micros64`` ×1000).
``offset_ns`` is remote − local at the newest sample, ``drift_ppm`` d(offset)/d(local) × 10⁶.

When we answer a peer's request (PX4 and ArduPilot both ask), ``tc1`` is our *presented*
clock: the local clock until synced, the autopilot's clock (``to_remote``) after — the same
clock every time we send (ODOMETRY.time_usec) is in, so a PX4 that maps our stamps through its
own TIMESYNC estimate (``MavlinkReceiver::handle_message_odometry``: ``sync_stamp(time_usec)``)
and one that takes them as its own time agree. The one switch at sync is a jump PX4 handles as
its code says: five deviating samples, reset, re-converge.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Any

from ahrs_service.protocols.mavlink.dialect import mavlink

#: round trips longer than this are not used (PX4 ``MAX_RTT_SAMPLE``), ns
MAX_RTT_NS = 10_000_000
#: how fast two clocks may drift apart at most, ppm (crystals: ±100; beyond this a clock is broken)
MAX_DRIFT_PPM = 1000.0
#: PX4's fixed bound on an offset's deviation, ns: no longer the test here (the drift bound
#: above is); kept so that code which imported it still runs
MAX_DEVIATION_NS = 100_000_000
#: what the stamps of one exchange may be off besides the round trip (the reply is stamped at
#: its arrival by a reader thread, the request just before it is sent), ns
JITTER_NS = 200_000
#: this many deviating samples in a row: the remote clock jumped, start again (PX4's 5)
MAX_CONSECUTIVE_DEVIATIONS = 5
#: accepted samples before the estimate is called synced
MIN_SAMPLES = 5
#: accepted samples kept (at 10 Hz: the last 25.6 s; a long span for the drift's slope)
WINDOW = 256
#: the fit weighs a sample by 1 / (half its round trip's excess over the window's shortest +
#: this)²: a long round trip is a queue on one way, which biases the offset by up to half of
#: it; this floor stands for the error of the shortest exchanges themselves, ns
RTT_FLOOR_NS = 50_000
#: our requests remembered to match replies (a reply whose ts1 we never sent is another system's)
PENDING = 32
#: how often the owner should call :meth:`TimeSync.request`, Hz (PX4 asks at 10 Hz too)
REQUEST_RATE_HZ = 10.0


@dataclass(frozen=True, slots=True)
class TimesyncFields:
    """One TIMESYNC message's fields: tc1 and ts1, ns (tc1 = 0 marks a request)."""

    tc1: int
    ts1: int

    def encode(self) -> "mavlink.MAVLink_timesync_message":
        return mavlink.MAVLink_timesync_message(int(self.tc1), int(self.ts1))


@dataclass(frozen=True, slots=True)
class TimesyncStatus:
    """What the log records after each accepted sample (MCAP ``/timesync``).

    local_ns: our time of the sample (midpoint of the round trip), monotonic ns.
    offset_ns: estimated remote − local at ``local_ns``; observed_offset_ns: this sample's.
    drift_ppm: estimated d(offset)/d(local) × 10⁶. rtt_ns: this sample's round trip.
    synced: the estimate is usable. samples: accepted samples since the last (re)start.
    """

    local_ns: int
    offset_ns: int
    observed_offset_ns: int
    drift_ppm: float
    rtt_ns: int
    synced: bool
    samples: int


@dataclass(slots=True)
class TimesyncCounters:
    """Replies and requests seen, and why replies were not used."""

    requests_sent: int = 0
    requests_answered: int = 0
    replies: int = 0
    accepted: int = 0
    rtt_too_long: int = 0
    deviating: int = 0
    not_ours: int = 0
    resets: int = 0
    implausible: int = 0  # replies whose offset moved more than drift and round trips allow
    jumps: int = 0  # restarts on replies that agreed on a new offset (a reboot, a clock set)


@dataclass(frozen=True, slots=True)
class _Sample:
    local_ns: int  # round-trip midpoint, our clock
    offset_ns: int  # remote − local observed
    rtt_ns: int


def plausible(before: _Sample, after: _Sample) -> bool:
    """Whether two TIMESYNC samples can both be true: their offsets differ by no more than
    ``MAX_DRIFT_PPM`` of the time between them plus half of both round trips and ``JITTER_NS``."""
    drift_ns = MAX_DRIFT_PPM * 1e-6 * abs(after.local_ns - before.local_ns)
    bound = drift_ns + (before.rtt_ns + after.rtt_ns) / 2 + JITTER_NS
    return abs(after.offset_ns - before.offset_ns) <= bound


class TimeSync:
    """Estimates an autopilot's clock from TIMESYNC exchanges; answers its requests.

    Drive: every ``1 / REQUEST_RATE_HZ`` s send ``request(now_ns).encode()``; hand every
    received TIMESYNC to ``handle(msg, rx_ns)`` with ``rx_ns`` taken when it arrived (a reader
    thread, not a poll: the round trip is the error bound), and send what it returns.
    Not thread-safe: call from one thread, or under the caller's lock.
    """

    def __init__(self) -> None:
        self.counters = TimesyncCounters()
        self.last_status: TimesyncStatus | None = None
        self._pending: deque[int] = deque(maxlen=PENDING)
        self._samples: deque[_Sample] = deque(maxlen=WINDOW)
        self._deviations = 0
        self._deviating: list[_Sample] = []  # refused samples that agree with one another
        #: the size of the newest jump the filter restarted on, ns (remote − local, new − old)
        self.last_jump_ns = 0
        # the fitted line: offset(t) = _a + _b * (t - _t0), ns and ns/ns
        self._t0 = 0
        self._a = 0.0
        self._b = 0.0

    # ------------------------------------------------------------------ state
    @property
    def synced(self) -> bool:
        """The offset estimate rests on at least ``MIN_SAMPLES`` accepted exchanges."""
        return len(self._samples) >= MIN_SAMPLES

    @property
    def offset_ns(self) -> int:
        """Remote − local at the newest accepted sample, ns (0 before any)."""
        if not self._samples:
            return 0
        return int(round(self._offset_at(self._samples[-1].local_ns)))

    @property
    def drift_ppm(self) -> float:
        """How fast the remote clock runs against ours: d(offset)/d(local) × 10⁶ (0 until two samples)."""
        return self._b * 1e6

    def _offset_at(self, local_ns: int) -> float:
        return self._a + self._b * (local_ns - self._t0)

    def reset(self) -> None:
        """Forgets every sample (the remote clock jumped, or the link to it is new)."""
        self._samples.clear()
        self._pending.clear()
        self._deviations = 0
        self._deviating = []
        self._a = self._b = 0.0
        self.counters.resets += 1

    # ------------------------------------------------------------------ conversions
    def to_remote_ns(self, local_ns: int) -> int:
        """Our monotonic ns as the autopilot's clock, ns. ValueError until synced."""
        if not self.synced:
            raise ValueError("timesync: not synced with the autopilot yet")
        return int(local_ns + round(self._offset_at(local_ns)))

    def to_remote_us(self, local_ns: int) -> int:
        """Our monotonic ns as the autopilot's clock, µs (ODOMETRY.time_usec). ValueError until synced."""
        return self.to_remote_ns(local_ns) // 1000

    def to_local_ns(self, remote_us: int) -> int:
        """An autopilot time stamp (µs) as our monotonic ns. ValueError until synced."""
        if not self.synced:
            raise ValueError("timesync: not synced with the autopilot yet")
        # remote = local + a + b (local − t0)  ⇒  local = (remote − a + b t0) / (1 + b)
        remote_ns = int(remote_us) * 1000
        return int(round(self._t0 + (remote_ns - self._t0 - self._a) / (1.0 + self._b)))

    def presented_ns(self, local_ns: int) -> int:
        """The clock we present to the autopilot (TIMESYNC answers, ODOMETRY time): its own
        once synced, ours before."""
        return self.to_remote_ns(local_ns) if self.synced else int(local_ns)

    # ------------------------------------------------------------------ protocol
    def request(self, now_ns: int) -> TimesyncFields:
        """A TIMESYNC request stamped ``now_ns`` (our monotonic ns), remembered for its reply."""
        self._pending.append(int(now_ns))
        self.counters.requests_sent += 1
        return TimesyncFields(tc1=0, ts1=int(now_ns))

    def handle(self, msg: Any, rx_ns: int) -> TimesyncFields | None:
        """Takes one received TIMESYNC (anything with ``tc1``, ``ts1``) that arrived at
        ``rx_ns`` (our monotonic ns). A request returns the answer to send; a reply to one of
        our requests updates the estimate and returns None."""
        tc1, ts1 = int(msg.tc1), int(msg.ts1)
        if tc1 == 0:
            self.counters.requests_answered += 1
            return TimesyncFields(tc1=self.presented_ns(rx_ns), ts1=ts1)
        self.counters.replies += 1
        if ts1 not in self._pending:
            self.counters.not_ours += 1  # another system's exchange, or a reply we gave up on
            return None
        self._pending.remove(ts1)
        rtt = int(rx_ns) - ts1
        if rtt < 0 or rtt > MAX_RTT_NS:
            self.counters.rtt_too_long += 1
            return None
        mid = ts1 + rtt // 2
        observed = tc1 - mid
        sample = _Sample(mid, observed, rtt)
        if self._samples and not plausible(self._samples[-1], sample):
            self.counters.deviating += 1
            self.counters.implausible += 1
            self._deviations += 1
            if self._deviating and not plausible(self._deviating[-1], sample):
                self._deviating = []  # agrees with nothing before it either (a frozen clock)
            self._deviating.append(sample)
            if len(self._deviating) >= MAX_CONSECUTIVE_DEVIATIONS:
                # the remote clock jumped (PX4: "time jump detected"): the replies agree on
                # where it is now; start again (as PX4 does, from the next replies)
                self.last_jump_ns = self._deviating[-1].offset_ns - self._samples[-1].offset_ns
                self.reset()
                self.counters.jumps += 1
            return None
        self._deviations = 0
        self._deviating = []
        self._samples.append(sample)
        self.counters.accepted += 1
        self._fit()
        self.last_status = TimesyncStatus(
            local_ns=mid,
            offset_ns=int(round(self._offset_at(mid))),
            observed_offset_ns=observed,
            drift_ppm=self.drift_ppm,
            rtt_ns=rtt,
            synced=self.synced,
            samples=len(self._samples),
        )
        return None

    def _fit(self) -> None:
        # weighted least squares offset = a + b (t − t0), t0 the newest sample's time (the
        # line's value where it is used, now, is its intercept). A sample's offset can be off by
        # up to half of what its round trip exceeds the shortest one (a queue on one way), so
        # its weight is 1 / (that excess / 2 + RTT_FLOOR_NS)²
        samples = self._samples
        t0 = samples[-1].local_ns
        rtt_min = min(s.rtt_ns for s in samples)
        sw = st = sy = 0.0
        rows = []
        for s in samples:
            w = 1.0 / (0.5 * (s.rtt_ns - rtt_min) + RTT_FLOOR_NS) ** 2
            t, y = float(s.local_ns - t0), float(s.offset_ns)
            rows.append((w, t, y))
            sw += w
            st += w * t
            sy += w * y
        mt, my = st / sw, sy / sw
        stt = sum(w * (t - mt) ** 2 for w, t, _ in rows)
        sty = sum(w * (t - mt) * (y - my) for w, t, y in rows)
        b = 0.0 if len(rows) < 2 or stt <= 0.0 else sty / stt
        # no clock drifts faster: a young window's round-trip noise fits a steeper line
        b = max(-MAX_DRIFT_PPM * 1e-6, min(MAX_DRIFT_PPM * 1e-6, b))
        self._t0, self._b, self._a = t0, b, my - b * mt
