"""One DroneCAN node's RawIMU stream, told apart from a second sender that uses the same node id.

Nothing on the bus names the sender of a frame but its node id, so two nodes configured with
one id reach the receiver as one node. What still tells them apart is each sender's own
sequence: its transfer ids count up by one per RawIMU transfer (modulo 32), and its
timestamps advance by about one sample period per transfer id. :class:`NodeStreamGuard`
follows the stream the IMU samples come from and holds every transfer that does not continue
it as a *candidate* stream:

- a candidate that continues itself after the followed stream has moved on in between is a
  second sender: a conflict, reported once, and all its transfers are dropped and counted;
- so is a second continuation of the transfer before the newest delivered one (a fork: one
  sender never sends two); of the two, the one nearer to where the stream's period puts it
  is the stream's;
- a candidate that continues itself for three sample periods while the followed stream is
  silent is the node starting over (a reboot without a pause); so is any transfer after the
  followed stream has been silent for ``silence_s``, or after :data:`STARVED_TRANSFERS`
  transfers in a row of which none continued it;
- a transfer repeating a delivered one (a redundant interface) is a duplicate.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

TRANSFER_ID_MODULO = 32  # DroneCAN's 5-bit transfer id on classic CAN
#: the largest forward step of the transfer id taken as lost transfers; a larger one (modulo
#: 32) is a step back
MAX_TRANSFER_ID_STEP = TRANSFER_ID_MODULO // 2
#: a candidate stream becomes the node's stream after this many of its periods in which the
#: followed stream sent nothing
RESTART_PERIODS = 3.0
#: transfers of the node id in a row of which none continued the followed stream: it is over,
#: whatever the reason (the last resort when sequences cannot be measured)
STARVED_TRANSFERS = 16
#: consecutive sample periods that must agree (within half a period) before one is trusted
_PERIOD_CONFIRMATIONS = 2
_PERIOD_SMOOTHING = 1.0 / 16.0  # weight of one new step in the running sample period
_DUPLICATE_MEMORY = 256  # delivered transfers remembered to recognise late duplicates


class Verdict(Enum):
    """What to do with one RawIMU transfer of the pinned node."""

    DELIVER = "deliver"  # continues the node's stream (or starts it again)
    DUPLICATE = "duplicate"  # repeats a delivered transfer: same transfer id, timestamp and payload
    STALE = "stale"  # outside the stream, and not newer than the last delivered sample
    OUT_OF_SEQUENCE = "out_of_sequence"  # outside the stream's transfer-id / time sequence, newer
    CONFLICT = "conflict"  # from a second sender with the same node id


def _mismatch_us(transfer_id: int, usec: int, host_ns: int, last: tuple[int, int, int],
                 period_us: float | None, slack_ns: int) -> float | None:
    """How far (µs) a transfer lies from where a sequence whose newest transfer is ``last``
    (transfer id, µs, host ns) expects it; None: it is not that sequence's next.

    The transfer id must step forward by 1…:data:`MAX_TRANSFER_ID_STEP` (lost transfers
    allowed); the timestamp must advance, by no more than the host clock did (plus
    ``slack_ns``), and, once the period is known, by the id step's periods within half a
    period. A node without time (timestamp 0) is followed by its transfer ids alone.
    """
    last_tid, last_usec, last_host = last
    step = (transfer_id - last_tid) % TRANSFER_ID_MODULO
    if not 1 <= step <= MAX_TRANSFER_ID_STEP:
        return None
    if usec == 0 or last_usec == 0:
        return 0.0
    advance = usec - last_usec
    if advance <= 0 or advance * 1000 > host_ns - last_host + slack_ns:
        return None
    if period_us is None:
        return float(advance)
    mismatch = abs(advance - step * period_us)
    return mismatch if mismatch <= 0.5 * period_us else None


@dataclass(slots=True)
class _Stream:
    """One sender's sequence: its newest transfer, the one before, and its sample period."""

    last: tuple[int, int, int]  # transfer id, timestamp µs, host ns
    estimate_us: float | None = None  # sample period, learned from consecutive transfer ids only
    confirmations: int = 0  # steps that agreed with the estimate
    before: tuple[int, int, int] | None = None
    last_mismatch: float = 0.0  # how far the newest transfer lay from where it was expected (µs)
    #: the followed stream delivered since this candidate began (candidates only)
    interleaved: bool = False
    #: candidate transfers since the followed stream last delivered, and the first one's timestamp
    run: int = 1
    run_start_usec: int = 0
    #: this candidate's transfers counted as stale / out of sequence so far
    held_stale: int = 0
    held_out_of_sequence: int = 0

    @property
    def period_us(self) -> float | None:
        """The sample period (µs) once consecutive steps agreed on it, else None."""
        return self.estimate_us if self.confirmations >= _PERIOD_CONFIRMATIONS else None

    def mismatch_us(self, transfer_id: int, usec: int, host_ns: int, slack_ns: int) -> float | None:
        """:func:`_mismatch_us` against this sequence's newest transfer."""
        return _mismatch_us(transfer_id, usec, host_ns, self.last, self.period_us, slack_ns)

    def advance(self, transfer_id: int, usec: int, host_ns: int, mismatch: float) -> None:
        """Appends a transfer that :meth:`mismatch_us` accepted; learns the sample period."""
        last_tid, last_usec, _ = self.last
        if usec and last_usec and (transfer_id - last_tid) % TRANSFER_ID_MODULO == 1:
            period, estimate = float(usec - last_usec), self.estimate_us
            if estimate is None or abs(period - estimate) > 0.5 * estimate:
                self.estimate_us, self.confirmations = period, 0  # (again) one step to go by
            else:
                self.estimate_us = estimate + _PERIOD_SMOOTHING * (period - estimate)
                self.confirmations += 1
        self.before, self.last = self.last, (transfer_id, usec, host_ns)
        self.last_mismatch = mismatch


class NodeStreamGuard:
    """Decides, transfer by transfer, which RawIMU transfers of one node id form its stream.

    silence_s: after this long (host clock) without a transfer of the followed stream, the
        next transfer starts the stream again whatever its sequence (a reboot, a bus outage).
    time_slack_s: how much further a timestamp may advance than the host clock did (a
        backlog read at once, latency).

    Counters (cumulative): ``duplicates``, ``stale``, ``out_of_sequence``, ``conflict_samples``
    (the second sender's transfers, including those held before it was recognised),
    ``conflict_delivered`` (the second sender's transfers delivered because they arrived
    first where both senders' next transfers look alike: at most one per fork),
    ``conflicts`` (second senders recognised) and ``restarts`` (the stream started over).
    """

    def __init__(self, silence_s: float = 1.0, time_slack_s: float = 1.0) -> None:
        self.silence_ns = int(silence_s * 1e9)
        self.slack_ns = int(time_slack_s * 1e9)
        self._stream: _Stream | None = None
        self._candidate: _Stream | None = None
        self._delivered: set[tuple[int, int, int]] = set()
        self._delivered_order: deque[tuple[int, int, int]] = deque()
        self._last_key: tuple[int, int, int] | None = None
        self._undelivered = 0  # transfers in a row that did not continue the followed stream
        #: a second sender is known (reset when the stream starts over)
        self.in_conflict = False
        self.duplicates = 0
        self.stale = 0
        self.out_of_sequence = 0
        self.conflict_samples = 0
        self.conflicts = 0
        self.conflict_delivered = 0
        self.restarts = 0

    @property
    def period_us(self) -> float | None:
        """The followed stream's sample period on the node's clock (µs), None until known."""
        return None if self._stream is None else self._stream.period_us

    def resync(self) -> None:
        """The next transfer starts the stream (e.g. after the bus was reopened: transfers were missed)."""
        self._stream = None
        self._candidate = None

    def admit(self, transfer_id: int, usec: int, payload: bytes, host_ns: int) -> Verdict:
        """The verdict on one RawIMU transfer: transfer id, node timestamp (µs, 0: none),
        payload, host receive time (ns). Only :attr:`Verdict.DELIVER` is to be delivered."""
        verdict = self._judge(transfer_id, usec, payload, host_ns)
        if verdict is Verdict.DELIVER:
            self._undelivered = 0
        elif verdict is not Verdict.DUPLICATE:
            self._undelivered += 1
        return verdict

    def _judge(self, transfer_id: int, usec: int, payload: bytes, host_ns: int) -> Verdict:
        key = (transfer_id, usec, hash(payload))
        # without timestamps an unchanged reading repeats its key every 32 transfers: only
        # the last delivered one can be told to be a duplicate
        if key in self._delivered if usec else key == self._last_key:
            self.duplicates += 1
            return Verdict.DUPLICATE
        stream = self._stream
        starved = self._undelivered >= STARVED_TRANSFERS
        if stream is None or starved or host_ns - stream.last[2] > self.silence_ns:
            if stream is not None and stream.mismatch_us(transfer_id, usec, host_ns, self.slack_ns) is None:
                self._start_over()
            self._stream, self._candidate = _Stream((transfer_id, usec, host_ns)), None
            return self._deliver(key)
        cand = self._candidate
        if cand is not None and host_ns - cand.last[2] > self.silence_ns:
            cand = self._candidate = None  # a one-off long ago is no second sender
        to_stream = stream.mismatch_us(transfer_id, usec, host_ns, self.slack_ns)
        # a second sender may run at another rate: a candidate is measured by its own period
        to_cand = None if cand is None else cand.mismatch_us(transfer_id, usec, host_ns, self.slack_ns)
        # both sequences may take it: the nearer one, where both periods are known to measure by
        measurable = cand is not None and cand.period_us is not None and stream.period_us is not None
        if to_stream is not None and (to_cand is None or not measurable or to_stream <= to_cand):
            stream.advance(transfer_id, usec, host_ns, to_stream)
            if cand is not None:
                cand.interleaved, cand.run = True, 0
            return self._deliver(key)
        not_newer = 0 < usec <= stream.last[1]
        if to_cand is None:
            to_fork = None if stream.before is None else _mismatch_us(
                transfer_id, usec, host_ns, stream.before, stream.period_us, self.slack_ns)
            if to_fork is not None:
                return self._fork(stream, transfer_id, usec, host_ns, key, to_fork)
            cand = self._candidate = _Stream((transfer_id, usec, host_ns), run_start_usec=usec)
            return self._hold(cand, not_newer)
        # the candidate continues itself
        cand.advance(transfer_id, usec, host_ns, to_cand)
        if cand.run == 0:
            cand.run_start_usec = usec
        cand.run += 1
        if cand.interleaved and not self.in_conflict:
            self._recognise_conflict(cand)
        if self.in_conflict:
            self.conflict_samples += 1
            return Verdict.CONFLICT
        if self._restarted(cand, stream):
            self._start_over()
            cand.interleaved, cand.run = False, 1
            self._stream, self._candidate = cand, None
            return self._deliver(key)
        return self._hold(cand, not_newer)

    # ------------------------------------------------------------------------ internals

    def _deliver(self, key: tuple[int, int, int]) -> Verdict:
        self._last_key = key
        self._delivered.add(key)
        self._delivered_order.append(key)
        if len(self._delivered_order) > _DUPLICATE_MEMORY:
            self._delivered.discard(self._delivered_order.popleft())
        return Verdict.DELIVER

    def _hold(self, cand: _Stream, not_newer: bool) -> Verdict:
        if self.in_conflict:
            self.conflict_samples += 1
            return Verdict.CONFLICT
        if not_newer:
            self.stale += 1
            cand.held_stale += 1
            return Verdict.STALE
        self.out_of_sequence += 1
        cand.held_out_of_sequence += 1
        return Verdict.OUT_OF_SEQUENCE

    def _recognise_conflict(self, cand: _Stream) -> None:
        # the candidate's transfers held so far were the second sender's too
        if not self.in_conflict:
            self.conflicts += 1
        self.in_conflict = True
        self.stale -= cand.held_stale
        self.out_of_sequence -= cand.held_out_of_sequence
        self.conflict_samples += cand.held_stale + cand.held_out_of_sequence
        cand.held_stale = cand.held_out_of_sequence = 0

    def _fork(self, stream: _Stream, transfer_id: int, usec: int, host_ns: int, key: tuple[int, int, int],
              mismatch: float) -> Verdict:
        """A second continuation of the transfer before the newest delivered one: one sender
        never sends two, so two senders share the node id. The continuation nearer to where
        the stream's period puts it is the stream's; the other is the second sender's."""
        if stream.period_us is not None and mismatch < stream.last_mismatch:
            # the newest delivered transfer was the second sender's, which arrived first
            self._candidate = _Stream(stream.last, interleaved=True, run=0)
            self._recognise_conflict(self._candidate)
            self.conflict_delivered += 1
            stream.last = stream.before  # type: ignore[assignment]  (a fork needs one)
            stream.advance(transfer_id, usec, host_ns, mismatch)
            return self._deliver(key)
        self._candidate = _Stream((transfer_id, usec, host_ns), interleaved=True, run=0)
        self._recognise_conflict(self._candidate)
        self.conflict_samples += 1
        return Verdict.CONFLICT

    def _restarted(self, cand: _Stream, stream: _Stream) -> bool:
        """Whether the candidate has run long enough alone to be the node starting over."""
        if cand.last[1] == 0 or stream.period_us is None:
            return False  # no period to measure the followed stream's silence by: STARVED_TRANSFERS
        return cand.run >= 2 and cand.last[1] - cand.run_start_usec >= RESTART_PERIODS * stream.period_us

    def _start_over(self) -> None:
        self.restarts += 1
        self.in_conflict = False


__all__ = ["MAX_TRANSFER_ID_STEP", "NodeStreamGuard", "RESTART_PERIODS", "STARVED_TRANSFERS", "Verdict"]
