"""The autopilot's IMU as a source (``source.type = "mavlink"``): HIGHRES_IMU, SCALED_IMU[2|3], RAW_IMU.

The flight controller already reads an IMU at a high rate; a companion without its own sensor
estimates from the autopilot's readings, sent over the autopilot link
(:class:`~ahrs_service.protocols.mavlink.autopilot_link.AutopilotLink`, the one connection the
service keeps to the flight controller). ``source.mavlink_imu`` picks the message:

======== ============= ==================================================================
key      message       units on the wire → ours
======== ============= ==================================================================
highres  HIGHRES_IMU   m/s², rad/s, gauss (×100 → µT; ArduPilot: see below), °C;
                       ``time_usec`` µs; ``fields_updated`` bits 6–8: new field reading
scaled   SCALED_IMU    mG (×9.80665e-3 → m/s²), mrad/s (×1e-3), mgauss (×0.1 → µT),
scaled2  SCALED_IMU2   cdegC; ``time_boot_ms`` ms (coarse: fine to ~200 Hz)
scaled3  SCALED_IMU3
raw      RAW_IMU       counts × ``source.mavlink_raw_scale`` (acc, gyr, mag per count);
                       ``time_usec`` µs
======== ============= ==================================================================

What the autopilots send (docs/autopilot.md cites the functions): PX4 streams HIGHRES_IMU
(``MavlinkStreamHighresIMU``, from ``vehicle_imu``/``sensor_combined``) and SCALED_IMU*
but not RAW_IMU; ArduPilot sends all of them, RAW_IMU with the same mG/mrad/s/mgauss scale as
SCALED_IMU, which is the default ``mavlink_raw_scale``, and its HIGHRES_IMU field in units of
1e-3 mgauss (:data:`ARDUPILOT_HIGHRES_MAG_TO_UT`, applied when the HEARTBEAT says ArduPilot). Every reading is FRD body axes of the
autopilot, specific force (−g on z at rest), the service's own convention.

Times: each message carries the autopilot's time of the sample. Those times go through the
sample clock (:class:`~ahrs_service.core.sample_clock.SampleClock`, indexed mode: the index is the
autopilot's time in tracked periods, so a gap of m periods counts m − 1 lost samples —
sequence numbers cannot be used, they count all of a sender's messages; the period is
measured over ``WARMUP_SPAN_S`` of the first messages, a burst among them spread out) and are then mapped
onto our monotonic clock by the link's :class:`RemoteTimeline` (TIMESYNC when synchronised:
the first samples wait up to ``SYNC_WAIT_S`` for it, so the offset they keep is TIMESYNC's).
Exactly uniform autopilot times pass the sample clock bit for bit.

The stream is asked for with SET_MESSAGE_INTERVAL at ``source.mavlink_imu_hz`` when the
autopilot is first heard, again each time the link comes back, and again every
``REQUEST_RETRY_S`` while no IMU message arrives (a rebooted autopilot streams nothing until
asked).
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ahrs_service.core.sample_clock import SampleClock
from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
    ImuSample,
    ImuSource,
    LossCounts,
    SampleBlock,
    beyond_range,
)
from ahrs_service.protocols.mavlink.autopilot_link import MAX_LATENCY_S, AutopilotLink
from ahrs_service.protocols.mavlink.dialect import mavlink

G = 9.80665
GAUSS_TO_UT = 100.0
MGAUSS_TO_UT = 0.1

#: config key -> MAVLink message name
IMU_MESSAGES = {
    "highres": "HIGHRES_IMU",
    "scaled": "SCALED_IMU",
    "scaled2": "SCALED_IMU2",
    "scaled3": "SCALED_IMU3",
    "raw": "RAW_IMU",
}

#: ArduPilot's RAW_IMU scale (the SCALED_IMU units): m/s², rad/s, µT per count
ARDUPILOT_RAW_SCALE = {"acc": G * 1e-3, "gyr": 1e-3, "mag": MGAUSS_TO_UT}

#: ArduPilot's HIGHRES_IMU field: GCS_MAVLINK::send_highres_imu (libraries/GCS_MAVLink/
#: GCS_Common.cpp) sends Compass::get_field() (milligauss) × 1000 although the message
#: defines gauss, so one unit is 1e-3 mgauss = 1e-4 µT
ARDUPILOT_HIGHRES_MAG_TO_UT = 1e-4

#: no IMU message this long after a request: ask again, s
REQUEST_RETRY_S = 1.0
#: a jump of the autopilot's time beyond this (or backwards: a reboot) is a new timeline, not
#: lost samples; shorter gaps (a link down for minutes) are counted sample by sample
MAX_GAP_S = 3600.0
#: a jump of the autopilot's time that runs ahead of the messages' arrivals by more than this
#: is its clock stepping (also a new timeline), not samples lost on the way: a link down for a
#: minute delays the arrivals by that minute too; 30 min of autopilot time between two
#: messages 5 ms apart counted 360 000 samples lost before. Above any burst of a queue
#: (a stalled reader's socket buffer holds well under a second of a 1 kHz stream)
MAX_LEAD_S = 5.0
#: a message at most this much older than the newest (or as old), arriving at most this long
#: after the previous one, is a duplicate or was overtaken on the way (UDP, a router with two
#: paths): skipped and counted (``out_of_order``), not a reboot — a reboot restarts the
#: autopilot's time near zero after a silence of its boot time (a second or more), so a stamp
#: that lands just below the old one after such a silence is still a new timeline
REORDER_S = 0.5
#: messages whose spacing sets the sample clock's period before the first sample is handed out …
WARMUP_MESSAGES = 16
#: … and the autopilot time they must span at least, s: a burst of first messages (a queue
#: flushed, stamps 100 µs apart) is then a minority of the spacings, not the stream's period
WARMUP_SPAN_S = 0.25
#: new timelines (a clock jump or a reboot) taken freely within RESET_WINDOW_S; beyond that
#: a message that would start one is skipped while the current timeline still gets messages
#: (within TIMELINE_ALIVE_S): the stamps of two senders with the autopilot's ids interleave,
#: and each switch between their clocks was a new timeline (thousands of them)
RESET_BUDGET = 3
RESET_WINDOW_S = 10.0
TIMELINE_ALIVE_S = 0.5
#: how long the first samples wait for TIMESYNC to converge, s: the offset the samples' times
#: keep (RemoteTimeline) is then TIMESYNC's from the start instead of the arrival times' (late
#: by the link's latency, tens of ms on a busy or slow link); an autopilot that does not answer
#: TIMESYNC costs this once
SYNC_WAIT_S = 2.0
#: samples kept waiting for the loop at most (a loop stalled this long loses the oldest)
QUEUE_SAMPLES = 4096

_HIGHRES_MAG_BITS = 0b111 << 6  # HIGHRES_IMU_UPDATED_XMAG | YMAG | ZMAG


@dataclass(frozen=True, slots=True)
class RawScale:
    """RAW_IMU counts → SI: acc m/s², gyr rad/s, mag µT per count."""

    acc: float
    gyr: float
    mag: float


@dataclass(slots=True)
class _Queued:
    """A stamped sample waiting for the loop, with the samples lost just before it."""

    sample: ImuSample
    lost_before: int


@dataclass(slots=True)
class _Reading:
    """One decoded IMU message, on the autopilot's clock."""

    remote_us: int
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None
    mag_new: bool
    temperature_c: float | None


def decode_highres(msg: Any, mag_to_ut: float = GAUSS_TO_UT) -> _Reading:
    """HIGHRES_IMU (message 105): m/s², rad/s, field × ``mag_to_ut`` (gauss by the message's
    definition: ×100; see :data:`ARDUPILOT_HIGHRES_MAG_TO_UT`), °C; the magnetometer counts as
    new only when ``fields_updated`` says so."""
    mag = np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float) * mag_to_ut
    return _Reading(int(msg.time_usec), np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float),
                    np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float), mag,
                    bool(int(msg.fields_updated) & _HIGHRES_MAG_BITS), float(msg.temperature))


def decode_scaled(msg: Any) -> _Reading:
    """SCALED_IMU / SCALED_IMU2 / SCALED_IMU3 (messages 26, 116, 129): mG, mrad/s, mgauss, cdegC
    (0 = not sent); every message carries the latest field reading."""
    temp = getattr(msg, "temperature", 0)
    return _Reading(int(msg.time_boot_ms) * 1000,
                    np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float) * 1e-3,
                    np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float) * (G * 1e-3),
                    np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float) * MGAUSS_TO_UT, True,
                    temp / 100.0 if temp else None)


def decode_raw(msg: Any, scale: RawScale) -> _Reading:
    """RAW_IMU (message 27): counts, scaled by the autopilot's factors (``source.mavlink_raw_scale``)."""
    return _Reading(int(msg.time_usec), np.array([msg.xgyro, msg.ygyro, msg.zgyro], dtype=float) * scale.gyr,
                    np.array([msg.xacc, msg.yacc, msg.zacc], dtype=float) * scale.acc,
                    np.array([msg.xmag, msg.ymag, msg.zmag], dtype=float) * scale.mag, True, None)


def spread_bursts(stamps_ns: list[int], period_ns: float) -> list[int]:
    """The warm-up messages' times for the sample clock, ns: a run of messages stamped less than
    half a period apart (a queue flushed at once, stamped when sent) is one sample a period,
    ending a period before the message after the run (from the message before it when the
    run ends the list; evenly between the two when a period each does not fit). Fed as
    stamped, a young line takes such a burst for the stream's pace, and the indices counted
    from it lock the clock onto a wrong period for good (3.4 ms for 5 ms, a phantom loss
    every other sample)."""
    out = list(stamps_ns)
    if period_ns <= 0:
        return out
    n, i = len(out), 0
    while i < n - 1:
        if stamps_ns[i + 1] - stamps_ns[i] >= 0.5 * period_ns:
            i += 1
            continue
        j = i
        while i < n - 1 and stamps_ns[i + 1] - stamps_ns[i] < 0.5 * period_ns:
            i += 1
        run = range(j, i + 1)  # messages j … i came in one burst
        before = stamps_ns[j - 1] if j > 0 else None
        after = stamps_ns[i + 1] if i + 1 < n else None
        if after is not None and (before is None or after - (i + 2 - j) * period_ns > before):
            for k in run:
                out[k] = int(round(after - (i + 1 - k) * period_ns))
        elif after is not None:
            step = (after - before) / (i + 2 - j)
            for k in run:
                out[k] = int(round(before + (k - j + 1) * step))
        elif before is not None:
            for k in run:
                out[k] = int(round(before + (k - j + 1) * period_ns))
        i += 1
    return out


class MavlinkImuSource(ImuSource):
    """IMU samples from the autopilot over ``link`` (see the module docstring).

    link: the autopilot link (opened and closed by this source when it created it).
    message: a key of :data:`IMU_MESSAGES`. rate_hz: the stream rate asked for, Hz (also the
    sample clock's nominal rate). raw_scale: RAW_IMU factors (default ArduPilot's).
    """

    may_have_backlog = True
    #: the samples' times are the autopilot's own (recovered here, mapped onto our clock): the
    #: service must not recover them again as host arrival times (the service's block loop
    #: reads this attribute of ImuSource)
    times_on_sensor_clock = True

    def __init__(self, link: AutopilotLink, *, message: str = "highres", rate_hz: float = 200.0,
                 raw_scale: RawScale | None = None, own_link: bool = True) -> None:
        super().__init__()
        if message not in IMU_MESSAGES:
            raise ValueError(f"source.mavlink_imu: {message!r} is not one of {', '.join(IMU_MESSAGES)}")
        self.link = link
        self.message = message
        self.msg_name = IMU_MESSAGES[message]
        self.rate_hz = float(rate_hz)
        self.raw_scale = raw_scale or RawScale(**ARDUPILOT_RAW_SCALE)
        self.own_link = own_link
        self.has_mag = True
        self._queue: collections.deque[_Queued] = collections.deque(maxlen=QUEUE_SAMPLES)
        self._clock: SampleClock | None = None
        self._index = 0
        self._warmup: list[_Reading] = []
        self._last_remote_ns: int | None = None  # the newest message's time
        self._stamped_ns = 0  # the newest sample's recovered time (autopilot clock, ns)
        self._requested_session = -1
        self._requested_at_ns = 0
        self._last_imu_rx_ns = 0  # arrival of the newest IMU message (reader thread)
        self.requests = 0  # SET_MESSAGE_INTERVAL commands sent
        self.timeline_resets = 0  # the autopilot's time jumped back or far ahead (reboot)
        #: messages skipped: duplicates, overtaken ones, or a sample whose time on our clock
        #: would not come after the previous sample's (across a new timeline)
        self.out_of_order = 0
        self._last_t_ns: int | None = None  # the newest sample's time on our clock, ns
        self._lost_carry = 0  # samples lost before a skipped sample, counted with the next
        self.queue_overflows = 0
        #: messages that would have started a new timeline while the current one still got
        #: messages, beyond RESET_BUDGET resets in RESET_WINDOW_S (two clocks interleaving)
        self.timeline_conflicts = 0
        self._reset_times_ns: collections.deque[int] = collections.deque(maxlen=RESET_BUDGET)
        self._timeline_rx_ns = 0  # arrival of the newest message on the current timeline
        self._timesync_refused_seen = 0
        self.refusals = 0  # SET_MESSAGE_INTERVAL answered with anything but ACCEPTED
        self.refusal = ""  # the last refusal, for humans
        link.subscribe([self.msg_name], self._on_message)
        link.subscribe(["COMMAND_ACK"], self._on_ack)

    @property
    def autopilot_link(self) -> AutopilotLink:
        """The link the attitude monitor and ODOMETRY share with this source."""
        return self.link

    def open(self) -> None:
        if self.own_link:
            self.link.open()

    # ------------------------------------------------------------------ reader thread
    def _decode(self, msg: Any) -> _Reading:
        if self.message == "highres":
            ap = self.link.autopilot
            kind = ap.kind if ap is not None else ""
            return decode_highres(msg, ARDUPILOT_HIGHRES_MAG_TO_UT if kind == "ardupilot" else GAUSS_TO_UT)
        if self.message == "raw":
            return decode_raw(msg, self.raw_scale)
        return decode_scaled(msg)

    def _on_message(self, msg: Any, rx_ns: int) -> None:
        """An IMU message arrived (reader thread): decode, stamp, queue."""
        r = self._decode(msg)
        prev_rx_ns, self._last_imu_rx_ns = self._last_imu_rx_ns, rx_ns
        last = self._last_remote_ns
        remote_ns = r.remote_us * 1000
        if last is not None:
            if last - REORDER_S * 1e9 <= remote_ns <= last and rx_ns - prev_rx_ns <= REORDER_S * 1e9:
                # a duplicate (a router with two paths) or a message overtaken on the way: its
                # sample is not used (the later one counted it lost), the timeline stays
                self.out_of_order += 1
                return
            ahead_ns = (remote_ns - last) - (rx_ns - prev_rx_ns)
            if remote_ns < last or remote_ns - last > MAX_GAP_S * 1e9 or ahead_ns > MAX_LEAD_S * 1e9:
                # the autopilot rebooted (its time went back) or its clock jumped: a new timeline
                # (TIMESYNC notices the same jump in its replies and starts again by itself)
                if not self._may_reset(rx_ns):
                    self.timeline_conflicts += 1
                    return
                self.timeline_resets += 1
                if self._clock is None and self._warmup:
                    # the old timeline ended while its first samples waited for TIMESYNC: they
                    # are stamped now, on the old timeline's arrivals, not dropped uncounted
                    self._start_clock()
                self.link.timeline.reset()
                self._clock, self._warmup = None, []
        self.link.timeline.arrival(r.remote_us, rx_ns)
        self._last_remote_ns = remote_ns
        self._timeline_rx_ns = rx_ns
        refused = self.link.timeline.timesync_refused
        if refused != self._timesync_refused_seen:  # once a timeline
            self._timesync_refused_seen = refused
            self.link.notify("autopilot IMU: TIMESYNC's offset disagrees with the IMU messages' arrivals "
                             f"(beyond {MAX_LATENCY_S:g} s of latency): their times are mapped by the arrivals",
                             4, once=("timesync vs arrivals", self.timeline_resets))
        if self._clock is None:
            # the stream's real rate, from its first spacings: an autopilot may not give the
            # rate asked for, and the sample clock's periods must be the stream's own
            self._warmup.append(r)
            span_us = r.remote_us - self._warmup[0].remote_us
            spanned = span_us >= WARMUP_SPAN_S * 1e6 or len(self._warmup) >= QUEUE_SAMPLES
            if len(self._warmup) >= WARMUP_MESSAGES and spanned and self._may_start():
                self._start_clock()
            return
        self._stamp(r)

    def _may_reset(self, rx_ns: int) -> bool:
        """Whether a message whose time jumped may start a new timeline: freely RESET_BUDGET
        times in RESET_WINDOW_S, beyond that only once the current timeline has been silent
        for TIMELINE_ALIVE_S (a reboot, a clock that stepped); reported once when refused."""
        times = self._reset_times_ns
        if len(times) < RESET_BUDGET or rx_ns - times[0] > RESET_WINDOW_S * 1e9 \
                or rx_ns - self._timeline_rx_ns > TIMELINE_ALIVE_S * 1e9:
            times.append(rx_ns)
            return True
        self.link.notify(f"autopilot IMU: its times switch back and forth between clocks ({RESET_BUDGET} new "
                         f"timelines in {RESET_WINDOW_S:g} s): a second sender seems to use the autopilot's ids; "
                         "staying on the current timeline", 4, once="timeline conflict")
        return False

    def _start_clock(self) -> None:
        """Starts the sample clock at the stream's rate measured over the warm-up messages (the
        rate asked for when they are too few to measure) and stamps them. The median spacing,
        unless most spacings are far below the mean (the stamps came in bursts): the mean; a
        burst among them is spread a period a message (:func:`spread_bursts`)."""
        pending, self._warmup = self._warmup, []
        spacing = 0.0
        if len(pending) > 1:
            times = np.array([w.remote_us for w in pending], dtype=np.float64) * 1000
            spacing = float(np.median(np.diff(times)))
            mean = (times[-1] - times[0]) / (len(times) - 1)
            if spacing < 0.5 * mean:
                spacing = mean
        self._clock = SampleClock(1e9 / spacing if spacing > 0 else self.rate_hz)
        self._index = 0
        stamps = spread_bursts([w.remote_us * 1000 for w in pending], spacing)
        self._stamp(pending[0], first=True, remote_ns=stamps[0])
        for w, remote_ns in zip(pending[1:], stamps[1:]):
            self._stamp(w, remote_ns=remote_ns)

    def _on_ack(self, msg: Any, rx_ns: int) -> None:
        """The autopilot's answer to our stream request (reader thread): a refusal is counted
        and named (an autopilot without that message, or a parameter limiting its rate)."""
        if int(msg.command) != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL or int(msg.result) == mavlink.MAV_RESULT_ACCEPTED:
            return
        self.refusals += 1
        result = mavlink.enums["MAV_RESULT"].get(int(msg.result))
        self.refusal = f"autopilot refused {self.msg_name} at {self.rate_hz:g} Hz: {result.name if result else msg.result}"

    def _may_start(self) -> bool:
        """Whether the first samples may be stamped: TIMESYNC is synced, or waited for long
        enough (``SYNC_WAIT_S`` of autopilot time), or the wait would overflow the queue."""
        with self.link.timesync_lock:
            if self.link.timesync.synced:
                return True
        waited_us = self._warmup[-1].remote_us - self._warmup[0].remote_us
        return waited_us >= SYNC_WAIT_S * 1e6 or len(self._warmup) >= QUEUE_SAMPLES

    def _stamp(self, r: _Reading, first: bool = False, remote_ns: int | None = None) -> None:
        """Stamps and queues ``r``; ``remote_ns``: its time on the autopilot's clock when not
        its own stamp (a warm-up burst's message), ns."""
        if remote_ns is None:
            remote_ns = r.remote_us * 1000
        lost = 0
        if not first:
            # the autopilot's time in tracked periods since the previous sample's place on the
            # steady line (not its stamp: a send-time stamp is late by up to its scheduler's
            # delay, and two such delays would add up): m periods on = m − 1 samples lost
            period_ns = 1e9 / self._clock.rate_hz  # type: ignore[union-attr]
            dk = max(1, int(round((remote_ns - self._stamped_ns) / period_ns)))
            lost = dk - 1
            self._index += dk
        steady_ns = int(self._clock.stamp_indexed(remote_ns, self._index))  # type: ignore[union-attr]
        self._stamped_ns = steady_ns
        t_ns = self.link.timeline.to_local_ns(steady_ns // 1000) + steady_ns % 1000  # type: ignore[operator]
        if self._last_t_ns is not None and t_ns <= self._last_t_ns:
            # a new timeline mapped at or before what was already handed out: the estimator's
            # times must increase (a dt <= 0 of -1800 s went into the estimate before)
            self.out_of_order += 1
            self._lost_carry += lost  # the losses before it stay counted, with the next sample
            return
        self._last_t_ns = t_ns
        lost, self._lost_carry = lost + self._lost_carry, 0
        flags = GYR_VALID | ACC_VALID
        mag = r.mag
        if mag is not None and np.all(np.isfinite(mag)) and mag.any():  # all zeros: no compass
            if beyond_range(mag, "mag"):
                mag = None
                self.diagnostics.saturated += 1
                flags |= MAG_SATURATED
            else:
                flags |= MAG_VALID | (MAG_NEW if r.mag_new else 0)
        else:
            mag = None
        for part, bit, sat in (("gyr", GYR_VALID, GYR_SATURATED), ("acc", ACC_VALID, ACC_SATURATED)):
            values = getattr(r, part)
            if not np.all(np.isfinite(values)):
                flags &= ~bit
                self.diagnostics.non_finite += 1
            elif beyond_range(values, part):
                # beyond any part's range: a corrupt or hostile message, not a motion; the
                # estimator skips it as it skips a saturated reading of our own parts
                flags = (flags & ~bit) | sat
                self.diagnostics.saturated += 1
        if len(self._queue) == self._queue.maxlen:
            self.queue_overflows += 1
            self.diagnostics.lost.host_stall += 1
        self._queue.append(_Queued(ImuSample(t_ns, r.gyr, r.acc, mag, flags, temperature_c=r.temperature_c), lost))

    # ------------------------------------------------------------------ loop thread
    def _request_stream(self) -> None:
        link = self.link
        now = time.monotonic_ns()
        if link.autopilot is None:
            return
        fresh_session = link.session != self._requested_session
        # no IMU message for a while, since the request or since the stream stopped (an
        # autopilot that rebooted streams nothing until asked again)
        last_heard = max(self._requested_at_ns, self._last_imu_rx_ns)
        silent = now - last_heard > REQUEST_RETRY_S * 1e9
        if fresh_session or silent:
            if link.set_message_interval(self.msg_name, self.rate_hz):
                self.requests += 1
            self._requested_session = link.session
            self._requested_at_ns = now

    def _update_diagnostics(self) -> None:
        d, s = self.diagnostics, self.link.stats
        # lost, or a device that has not opened since the start
        d.device_lost = self.link.state == "lost" or (self.link.state == "waiting" and s.open_failures > 0)
        d.bus_errors = s.read_errors + s.send_errors
        d.reinitialisations = s.reopens
        # damaged frames only: a well-framed message of another dialect is no dropped frame
        d.dropped_frames = s.bad_data
        d.last_error = self.refusal or s.last_error
        d.extra.update(link_losses=s.losses, link_recoveries=s.recoveries, stream_requests=self.requests,
                       timeline_resets=self.timeline_resets, out_of_order=self.out_of_order,
                       clock_steps=self.link.timeline.steps,
                       stream_refusals=self.refusals, timeline_conflicts=self.timeline_conflicts,
                       timesync_refused=self.link.timeline.timesync_refused,
                       identity_conflicts=s.identity_conflicts, other_autopilots=s.other_autopilots,
                       unknown_messages=s.unknown_messages)

    def _pop(self) -> _Queued | None:
        try:
            item = self._queue.popleft()
        except IndexError:
            return None
        self.diagnostics.samples += 1
        self.diagnostics.lost.gap += item.lost_before
        return item

    def read(self) -> ImuSample | None:
        self._request_stream()
        self._update_diagnostics()
        item = self._pop()
        return None if item is None else item.sample

    def read_block(self, max_samples: int = 64) -> SampleBlock:
        """The queued samples, oldest first, ending before a loss (the loss opens the next block)."""
        self._request_stream()
        self._update_diagnostics()
        samples: list[ImuSample] = []
        lost_before = LossCounts()
        while len(samples) < max_samples and self._queue:
            if samples and self._queue[0].lost_before:
                break  # a gap: the next block starts with it
            item = self._pop()
            if item is None:
                break
            if not samples:
                lost_before.gap = item.lost_before
            samples.append(item.sample)
        return SampleBlock.from_samples(samples, lost_before)

    def close(self) -> None:
        if self.own_link:
            self.link.close()


def parse_raw_scale(table: dict[str, Any]) -> RawScale:
    """``source.mavlink_raw_scale`` ({acc, gyr, mag} per count, missing keys ArduPilot's)."""
    values = dict(ARDUPILOT_RAW_SCALE)
    for key, value in table.items():
        if key not in values:
            raise ValueError(f"source.mavlink_raw_scale.{key}: unknown; accepted: acc, gyr, mag")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"source.mavlink_raw_scale.{key}: {value!r} is not a positive number")
        values[key] = float(value)
    return RawScale(**values)
