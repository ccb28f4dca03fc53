"""Flight-log recording to MCAP: a cheap, never-raising writer for the service loop.

:class:`FlightLogWriter` is what the service uses. Its ``write_*`` methods only copy their
arguments into plain Python values and append one named record per call to a bounded queue
(about a microsecond each); a background thread hands each record to its handler, which
encodes the messages to JSON and writes them to a :class:`~ahrs_service.logs.mcap_file.McapLogFile`
(the MCAP file layer, ``logs/mcap_file.py``, through the ``mcap`` library's public API). The
thread closes the current chunk and ``fsync``\\ s the file at least every
``flush_interval_s`` seconds, so a crash (power loss, SIGKILL) loses at most about that much
data; :func:`ahrs_service.logs.recover.recover` turns such a file back into a valid one.

Errors (unwritable directory, disk full, any ``OSError``) never reach the caller: they set
``status``/``last_error`` (the path and the system's error text), the messages that could not
be written are counted (``dropped``, ``samples_not_logged``, ``outage_s``), and the writer
tries again with back-off: ``retry_first_s`` (0.5 s) after the failure, then each delay
``retry_factor`` (2) times the previous, at most ``retry_max_s`` (30 s). A file the disk
refused stays open with its unwritten bytes staged (``logs/mcap_file.py``): when the disk takes
them again the same file goes on — one file per recording, no empty or torn leftovers.

Public API (all keyword arguments after the sample's time, row and flags are named)::

    log = FlightLogWriter("flight-logs", metadata={"vehicle": "rov-1"})
    log.write_config(t_ns, {"estimator": {"name": "madgwick", "params": est.get_params()}})
    ...
    q = est.update_row(row)                       # row: the (10,) sample row fed to it
    log.write_raw(t_ns, row, sample.flags, raw=sample.raw, temperature=sample.temperature_c)
    log.write_attitude(t_ns, q, est.name, bias=est.gyro_bias, diagnostics=est.diagnostics, state=est.state)
    # or both in one call (and one queue entry), as the service does at its rate:
    log.write_sample(t_ns, row, sample.flags, q=q, estimator=est.name, bias=est.gyro_bias, state=est.state)
    ...
    log.write_param_change(t_ns, None, "beta", old, new, "mavlink")  # after est.set_params
    ...
    log.close()

Adding a message kind: a record class below (``_Record`` subclass), a ``write_*`` method that
queues it, and a handler registered in ``FlightLogWriter._HANDLERS``. A record that carries
samples (or several messages) says how many in ``_CARRIES``, and its handler checks for a file
with ``_ensure_item(item)``, so the queue and the disk count the same "not logged".
"""

from __future__ import annotations

import atexit
import collections
import datetime as _dt
import enum
import errno as errno_mod
import json
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol

import numpy as np

from ahrs_service.logs.mcap_file import LogFileDeleted, McapLogFile
from ahrs_service.logs.schemas import (
    attitude_block_message,
    attitude_message,
    autopilot_attitude_messages,
    encode,
    jsonable,
    log_message,
    num_or_null,
    raw_block_message,
    raw_message,
    tf_message,
    truth_block_message,
    truth_message,
)

# --------------------------------------------------------------------------- threaded writer

# Queue entries: one record class per kind, each handled by one FlightLogWriter method. They
# hold plain Python values (lists, not arrays): the caller may reuse its arrays at once.
@dataclass(slots=True)
class _Raw:
    t_ns: int
    row: list  # the sample row [gx, gy, gz, ax, ay, az, mx, my, mz, dt]
    flags: int
    raw: Any
    temperature: float | None
    index: int  # the sample's number since the writer started


@dataclass(slots=True)
class _Attitude:
    t_ns: int
    q: list  # q_earth←body [w, x, y, z]
    estimator: str
    bias: list | None  # rad/s, body frame
    diagnostics: dict | None


@dataclass(slots=True)
class _Sample:
    """/imu/raw + /attitude (+ /attitude/truth) of one sample: the service's per-sample entry."""

    t_ns: int
    row: list
    flags: int
    raw: Any
    temperature: float | None
    index: int
    q: list
    estimator: str
    bias: list | None
    truth_q: list | None
    diagnostics: dict | None  # the estimator's, at the service's diagnostics rate; else None


@dataclass(slots=True)
class _Block:
    """The samples of one block and their estimates: the service's one entry per burst.
    Written as /imu/raw + /attitude (+ /attitude/truth) per row, or, when ``one_message``,
    as one /imu/raw_block + /attitude_block (+ /attitude/truth_block). The arrays are the
    caller's, copied (the caller may reuse its own at once)."""

    t_ns: np.ndarray  # (n,) int64 recovered sample times, ns
    t_source_ns: np.ndarray | None  # (n,) the source's own stamps, ns
    rows: np.ndarray  # (n, 10) float64 sample rows as fed to the estimator
    flags: np.ndarray  # (n,)
    raw: dict | None  # {name: (n, …) array} driver counts
    temperature: np.ndarray | None  # (n,) °C, NaN where unknown (encode writes null)
    first_index: int
    q: np.ndarray  # (n, 4)
    estimator: str
    bias: list | None  # after the last row, rad/s body FRD: written with the last row only
    truth_q: np.ndarray | None  # (n, 4)
    diagnostics: dict | None  # the estimator's after the last row, at the diagnostics rate
    one_message: bool  # the samples come faster than block_messages_above_hz: block channels


@dataclass(slots=True)
class _Truth:
    t_ns: int
    q: list
    movement: bool | None
    source: str


@dataclass(slots=True)
class _Loop:
    t_ns: int
    stats: dict


@dataclass(slots=True)
class _Config:
    t_ns: int
    config: dict
    reason: str


@dataclass(slots=True)
class _ParamChange:
    t_ns: int
    sample_index: int
    name: str
    old: Any
    new: Any
    source: str


@dataclass(slots=True)
class _Mavlink:
    t_ns: int
    counters: dict


@dataclass(slots=True)
class _AutopilotAttitude:
    """The autopilot's attitude and its disagreement with ours: an attitude_monitor.Disagreement
    (frozen, so queued as it is, not copied field by field)."""

    d: Any


@dataclass(slots=True)
class _Timesync:
    """The autopilot's clock estimate after one accepted TIMESYNC sample: a
    timesync.TimesyncStatus (frozen, so queued as it is)."""

    status: Any


@dataclass(slots=True)
class _Log:
    """A health event for /log (foxglove.Log)."""

    t_ns: int
    severity: int  # MAVLink's, 0 emergency … 7 debug
    text: str


@dataclass(slots=True)
class _StateSnapshot:
    """The estimator state after the sample at ``t_ns``: the first message of a rotated file."""

    t_ns: int
    state: list
    estimator: str
    next_index: int  # number of the first sample the new file holds


@dataclass(slots=True)
class _NewFile:
    pass


@dataclass(slots=True)
class _Close:
    pass


#: messages and samples (/imu/raw rows) each record kind carries, for what a full queue or a
#: failing disk loses (the queue and the handlers both count from here); kinds not listed
#: carry one message and no sample
_CARRIES: dict[type, Callable[[Any], tuple[int, int]]] = {
    _Raw: lambda item: (1, 1),
    _Sample: lambda item: (2 + (item.truth_q is not None), 1),
    _Block: lambda item: ((1 if item.one_message else len(item.t_ns)) * (2 + (item.truth_q is not None)),
                          len(item.t_ns)),
    _AutopilotAttitude: lambda item: (3, 0),  # /autopilot/attitude, /tf, /monitor
}


#: rows at most in one joined /imu/raw_block (FlightLogWriter._joined_with_queued)
JOINED_BLOCK_MAX_ROWS = 256


def _continues(block: _Block, nxt: _Block) -> bool:
    """Whether ``nxt`` can be written in the same block messages as ``block``: the next rows,
    the same estimator and fields, and ``block`` without diagnostics of its own (those go
    with a message's last row)."""
    return (nxt.one_message and nxt.first_index == block.first_index + len(block.t_ns)
            and nxt.estimator == block.estimator and block.diagnostics is None
            and (nxt.t_source_ns is None) == (block.t_source_ns is None)
            and (nxt.temperature is None) == (block.temperature is None)
            and (nxt.truth_q is None) == (block.truth_q is None)
            and (nxt.raw is None) == (block.raw is None)
            and (nxt.raw is None or (nxt.raw.keys() == block.raw.keys()
                                     and all(nxt.raw[k].shape[1:] == block.raw[k].shape[1:] for k in nxt.raw))))


def _join(parts: list[_Block]) -> _Block:
    """Consecutive blocks (``_continues``) as one; the last one's bias and diagnostics."""

    def cat(field: str) -> np.ndarray | None:
        arrays = [getattr(p, field) for p in parts]
        return None if arrays[0] is None else np.concatenate(arrays)

    last = parts[-1]
    raw = None if last.raw is None else {k: np.concatenate([p.raw[k] for p in parts]) for k in last.raw}
    return _Block(t_ns=cat("t_ns"), t_source_ns=cat("t_source_ns"), rows=cat("rows"), flags=cat("flags"), raw=raw,
                  temperature=cat("temperature"), first_index=parts[0].first_index, q=cat("q"),
                  estimator=last.estimator, bias=last.bias, truth_q=cat("truth_q"), diagnostics=last.diagnostics,
                  one_message=True)


def _carried(item: Any) -> tuple[int, int]:
    """(messages, samples) of one queue record."""
    count = _CARRIES.get(type(item))
    return (1, 0) if count is None else count(item)


@dataclass(frozen=True, slots=True)
class Outage:
    """What an I/O outage (or the whole run) kept out of the files."""

    seconds: float  # s logging was stopped, monotonic clock
    messages: int  # messages not written (all channels)
    samples: int  # of which /imu/raw samples


class _Rotation(enum.IntEnum):
    """The rotation handshake between the writer thread and the caller's ``write_*``."""

    IDLE = 0  # no rotation pending
    DUE = 1  # the file is due: the writer thread waits for the caller's state snapshot
    SNAPSHOT_QUEUED = 2  # a _StateSnapshot is queued; the writer thread rotates when it gets it


_IDLE_WAIT_S = 0.2  # longest sleep of an idle writer thread, s
#: how long after the loop's wake-up the writer thread stays asleep, ns: time for the loop's
#: thread to take the interpreter
_AFTER_WAKE_NS = 50_000


class LoopWakeups(Protocol):
    """What the writer reads of the service loop's scheduler (``scheduler.FixedRateScheduler``)."""

    #: the loop's next wake-up, monotonic ns; None when not known ahead (a data-ready line)
    next_wake_ns: int | None
    #: the loop's period, ns
    period_ns: int


def _tolist(x: Any) -> list[float]:
    # called twice per sample on the loop thread: the exact-type test is the cheap common case
    if type(x) is np.ndarray:
        return x.tolist()
    return x.tolist() if hasattr(x, "tolist") else [float(v) for v in x]


def log_file_name(prefix: str, when: _dt.datetime) -> str:
    """``prefix-YYYYmmddTHHMMSSZ.mcap`` of a UTC start time."""
    return f"{prefix}-{when.strftime('%Y%m%dT%H%M%SZ')}.mcap"


class FlightLogWriter:
    """Records a flight to MCAP files in ``directory`` from the service's real-time loop.

    directory: folder for the logs, created if missing (the service's default is
        ``./flight-logs`` in the working directory).
    prefix: file names are ``{prefix}-{UTC start, YYYYmmddTHHMMSSZ}.mcap``.
    chunk_size: bytes of uncompressed messages after which a chunk is closed (compressed with
        zstd). Chunks are also closed every ``flush_interval_s``.
    flush_interval_s: at most this long (s) between a message and its ``fsync`` to disk.
    rotate_bytes, rotate_seconds: start a new file once the current one is this large / old.
        Rotation happens at a sample boundary (before a raw sample), and the new file starts
        with the current configuration (live parameter changes folded in).
    metadata: key/values stored in each file's MCAP metadata record "ahrs-service".
    queue_size: messages that may wait for the background thread; beyond it they are dropped
        (counted in ``dropped``). The default holds ~20 s of a 1 kHz loop.
    tf_rate_hz: rate of ``/tf`` transforms for Foxglove's 3-D panel (None: every attitude).
    retry_first_s, retry_factor, retry_max_s: back-off after an I/O error: the first retry
        ``retry_first_s`` s after it, each later one ``retry_factor`` times the previous
        delay, at most ``retry_max_s`` s; a success resets it.
    first_sample_index: number given to the first ``write_raw`` sample (the /imu/raw
        ``index`` that /params ``sample_index`` refers to): pass the estimator's sample count
        when a writer is (re)opened mid-run.
    loop: the service loop's scheduler. The writer thread then does not start a record it
        cannot finish (by its recent records' durations) before the loop's next wake-up, and
        sleeps until just after it: one interpreter runs both threads, and a wake-up that
        has to wait for the writer to give up the interpreter is late by up to the
        interpreter's switch interval and more (the loop's wake-up jitter).
    block_messages_above_hz: a block (``write_block``) of samples faster than this (by its
        rows' mean spacing after the first; a lone row never) is written as one message per channel (/imu/raw_block,
        /attitude_block, /attitude/truth_block), with /attitude (and /tf) at ``tf_rate_hz``
        for Foxglove's plots; slower ones, and every block when None, one message per sample.
        0: every block as one message.

    The ``write_*`` methods never raise because of the disk and never block; see ``status``,
    ``last_error``, ``dropped`` and :meth:`stats`.
    """

    def __init__(
        self,
        directory: str | os.PathLike = "flight-logs",
        *,
        prefix: str = "flight",
        chunk_size: int = 128 * 1024,
        flush_interval_s: float = 1.0,
        rotate_bytes: int | None = None,
        rotate_seconds: float | None = None,
        metadata: Mapping[str, Any] | None = None,
        queue_size: int = 65536,
        tf_rate_hz: float | None = 50.0,
        retry_first_s: float = 0.5,
        retry_factor: float = 2.0,
        retry_max_s: float = 30.0,
        fsync: bool = True,
        first_sample_index: int = 0,
        loop: LoopWakeups | None = None,
        block_messages_above_hz: float | None = None,
    ) -> None:
        self.directory = Path(directory)
        self.prefix = prefix
        self.chunk_size = int(chunk_size)
        self.flush_interval_s = float(flush_interval_s)
        self.rotate_bytes = rotate_bytes
        self.rotate_seconds = rotate_seconds
        self.metadata = dict(metadata or {})
        self.queue_size = int(queue_size)
        self.tf_period_ns = 0 if not tf_rate_hz else int(1e9 / tf_rate_hz)
        self.retry_first_s = float(retry_first_s)
        self.retry_factor = float(retry_factor)
        self.retry_max_s = float(retry_max_s)
        self._retries = 0  # failed attempts since the last success: the back-off's exponent
        self.fsync = fsync

        #: "starting" | "ok" | "error" | "closed"
        self.status = "starting"
        self.last_error = ""
        self.files: list[Path] = []  # every file started, in order
        self.written = 0
        self.errors = 0
        self.samples = int(first_sample_index)  # number of the next write_raw sample
        self._dropped_full = 0  # caller thread only
        self._dropped_io = 0  # writer thread only
        self._samples_dropped_full = 0  # of those, samples (/imu/raw): caller thread only
        self._samples_dropped_io = 0  # writer thread only
        #: the file refused by the disk and kept open for a retry (see McapLogFile.retry)
        self._stalled = False
        self._outage_since: float | None = None  # monotonic s of the failure, while in error
        self.outage_s = 0.0  # seconds not logged because of I/O errors, over the whole run
        self.outages = 0  # times logging stopped because of an I/O error
        #: the last outage that ended: (seconds, messages, samples) not logged — the service
        #: reports it when logging resumes
        self.last_outage: Outage | None = None
        self._outage_start_counts = (0, 0)
        self._q: collections.deque = collections.deque()
        self._wake = threading.Event()
        # an idle writer thread sleeps this long (close() wakes it): at 1 kHz it then writes
        # ~200 samples per wake-up, and on a VM every wake-up starts with cold caches
        self._idle_wait_s = min(_IDLE_WAIT_S, self.flush_interval_s / 5)
        self._wake_at = max(1, self.queue_size // 8)
        self._closing = False
        self._file: McapLogFile | None = None
        self._opened_at = 0.0
        self._last_flush = time.monotonic()
        self._next_retry = 0.0
        self._config: dict[str, Any] | None = None
        self._last_loop: dict[str, Any] = {}  # the last /loop's stats: the tail of a file ended short
        self._last_tf_ns: int | None = None
        self._state_seen = False  # the caller passes its estimator state to write_attitude
        # rotation handshake (see _Rotation); the lock makes the caller's DUE -> SNAPSHOT_QUEUED
        # and the writer thread's cancelling (-> IDLE) exclusive
        self._rotation = _Rotation.IDLE
        self._rotation_lock = threading.Lock()
        self._rotation_since = 0.0
        self._loop = loop
        #: a block whose rows come closer than this (s, their mean spacing) is one message per channel
        self.block_messages_below_dt_s = (
            -1.0 if block_messages_above_hz is None else math.inf if block_messages_above_hz <= 0
            else 1.0 / float(block_messages_above_hz))
        #: a record's handling time, ns: the recent largest, decaying by 1/16 a record
        self._record_ns = 0.0
        self._thread = threading.Thread(target=self._run, name="flight-log-writer", daemon=True)
        self._thread.start()
        atexit.register(self.close)

    # ---------------------------------------------------------------- caller side (cheap)
    @property
    def dropped(self) -> int:
        """Messages lost: queue full, or not written because of an I/O error."""
        return self._dropped_full + self._dropped_io

    @property
    def samples_not_logged(self) -> int:
        """Samples (/imu/raw rows) given to the writer that are not in any file."""
        return self._samples_dropped_full + self._samples_dropped_io

    def not_logged(self) -> "Outage":
        """What is missing from the files: messages, samples, and the seconds logging was
        stopped by I/O errors (an outage still running counted up to now)."""
        seconds = self.outage_s
        if self._outage_since is not None:
            seconds += time.monotonic() - self._outage_since
        return Outage(seconds, self.dropped, self.samples_not_logged)

    def _put(self, item: Any) -> bool:
        # one producer (the service loop): len() then append() cannot overshoot by more than one
        n = len(self._q)
        if self._closing or n >= self.queue_size:
            messages, samples = _carried(item)
            self._dropped_full += messages
            self._samples_dropped_full += samples
            return False
        if n == self._wake_at:  # a producer faster than real time: the thread must not sleep on
            self._wake.set()
        self._q.append(item)
        return True

    def write_raw(
        self,
        t_ns: int,
        row: np.ndarray,
        flags: int,
        raw: Mapping[str, Any] | None = None,
        temperature: float | None = None,
    ) -> None:
        """One sample row (10,) exactly as fed to the estimator: gyr rad/s, acc m/s², mag µT
        (NaN: none), dt s; ``flags`` the sample's validity bits, ``raw`` the driver's raw
        counts, ``temperature`` °C."""
        self._put(_Raw(t_ns, row.tolist(), flags, raw, temperature, self.samples))
        self.samples += 1

    def write_attitude(
        self,
        t_ns: int,
        q: Any,
        estimator: str,
        bias: Any = None,
        diagnostics: Mapping[str, Any] | None = None,
        state: np.ndarray | None = None,
    ) -> None:
        """The estimate after the sample at ``t_ns``: q_earth←body [w, x, y, z], gyro bias rad/s.

        state: the estimator's state array (``est.state``, not copied unless needed). With it,
            a rotation starts the new file with a snapshot of the state (/estimator/state), so
            every file replays exactly; without it, a later file replays from a fresh estimator.
        """
        diag = None if diagnostics is None else dict(diagnostics)
        self._put(_Attitude(t_ns, _tolist(q), estimator, None if bias is None else _tolist(bias), diag))
        if state is not None:
            self._offer_state(t_ns, state, estimator)

    def write_sample(
        self,
        t_ns: int,
        row: np.ndarray,
        flags: int,
        *,
        q: np.ndarray,
        estimator: str,
        bias: np.ndarray | None = None,
        state: np.ndarray | None = None,
        raw: Mapping[str, Any] | None = None,
        temperature: float | None = None,
        truth_q: np.ndarray | None = None,
        diagnostics: Mapping[str, Any] | None = None,
    ) -> None:
        """``write_raw`` + ``write_attitude`` (+ ``write_truth`` when ``truth_q`` is given) of one
        sample as one queue entry: the service's per-sample call, a third of the caller's cost.
        Same arguments and units as those three (keywords after ``flags``); the file holds
        the same messages. ``diagnostics`` (the estimator's, copied here) fills this sample's
        /attitude ``diagnostics``; the service passes it at its diagnostics rate, else None ({})."""
        self._put(
            _Sample(
                t_ns,
                row.tolist(),
                flags,
                raw,
                temperature,
                self.samples,
                _tolist(q),
                estimator,
                None if bias is None else _tolist(bias),
                None if truth_q is None else _tolist(truth_q),
                None if diagnostics is None else dict(diagnostics),
            )
        )
        self.samples += 1
        if state is not None:
            self._offer_state(t_ns, state, estimator)

    def write_block(
        self,
        t_ns: np.ndarray,
        rows: np.ndarray,
        flags: np.ndarray,
        *,
        q: np.ndarray,
        estimator: str,
        t_source_ns: np.ndarray | None = None,
        bias: np.ndarray | None = None,
        state: np.ndarray | None = None,
        raw: Mapping[str, np.ndarray] | None = None,
        temperature: np.ndarray | None = None,
        truth_q: np.ndarray | None = None,
        diagnostics: Mapping[str, Any] | None = None,
    ) -> None:
        """A block of n samples as one queue entry; the file holds the same per-sample
        messages as n ``write_sample`` calls (/imu/raw and /attitude per row, /attitude/truth
        per row with ``truth_q``), so Foxglove plots and replay see every sample.

        t_ns (n,) int64 each sample's time (ns, recovered onto the sensor's clock: the times
        ``dt`` came from); t_source_ns (n,) the source's own stamps (host read times), stored
        beside them (``t_source_ns`` in /imu/raw); rows (n, 10) exactly as fed to the
        estimator; flags (n,); q (n, 4) q_earth←body after each row; raw {name: (n, …)}
        counts; temperature (n,) °C (NaN unknown); truth_q (n, 4). ``bias`` (rad/s),
        ``diagnostics`` and ``state`` are the estimator's after the **last** row: the bias and
        diagnostics go into the last row's /attitude only (the batch kernel keeps no state per
        row), the state is offered for a rotation's snapshot as in ``write_attitude``.
        """
        n = len(t_ns)
        if n == 0:
            return
        rows = np.array(rows, dtype=np.float64)
        self._put(
            _Block(
                np.array(t_ns, dtype=np.int64),
                None if t_source_ns is None else np.array(t_source_ns, dtype=np.int64),
                rows,
                np.array(flags, dtype=np.int64),
                None if raw is None else {k: np.array(v) for k, v in raw.items()},
                # NaN (unknown) stays NaN: encode writes it as null, as write_sample's None
                None if temperature is None else np.array(temperature, dtype=np.float64),
                self.samples,
                np.array(q, dtype=np.float64),
                estimator,
                None if bias is None else _tolist(bias),
                None if truth_q is None else np.array(truth_q, dtype=np.float64),
                None if diagnostics is None else dict(diagnostics),
                self._one_message(t_ns),
            )
        )
        self.samples += n
        if state is not None:
            self._offer_state(int(t_ns[-1]), state, estimator)

    def _one_message(self, t_ns: np.ndarray) -> bool:
        """Whether a block with these row times is written as one message per channel: its
        rows' mean spacing after the first (whose dt is the long step after a gap that starts
        a block) is below ``block_messages_below_dt_s``. A lone row is one message a sample
        (but with ``block_messages_above_hz = 0``): its spacing alone is whatever a clock's
        correction made it — a log of the simulated GY-80 (800 Hz rows) once held a one-row
        /imu/raw_block, its dt under 0.67 ms."""
        below = self.block_messages_below_dt_s
        n = len(t_ns)
        if n < 2:
            return below == math.inf
        return (int(t_ns[-1]) - int(t_ns[0])) * 1e-9 / (n - 1) < below

    def _offer_state(self, t_ns: int, state: np.ndarray, estimator: str) -> None:
        self._state_seen = True
        if self._rotation == _Rotation.DUE:
            with self._rotation_lock:
                if self._rotation == _Rotation.DUE:
                    # the file ends after this sample; the next starts from this very state
                    self._rotation = _Rotation.SNAPSHOT_QUEUED
                    if not self._put(_StateSnapshot(t_ns, state.tolist(), estimator, self.samples)):
                        self._rotation = _Rotation.DUE  # queue full: ask again with a later sample

    def write_truth(self, t_ns: int, q: Any, movement: bool | None = None, source: str = "") -> None:
        """Ground-truth q_earth←body [w, x, y, z] (NED) for the sample at ``t_ns``."""
        self._put(_Truth(t_ns, _tolist(q), movement, source))

    def write_loop(self, t_ns: int, stats: Mapping[str, Any]) -> None:
        """Scheduler statistics (period/jitter s, overruns, load, sensor fault counters)."""
        self._put(_Loop(t_ns, dict(stats)))

    def write_config(self, t_ns: int, config: Mapping[str, Any], reason: str = "start") -> None:
        """The effective configuration, with config['estimator'] = {'name': …, 'params': {…}}."""
        # a deep copy the caller cannot change any more; unknown types (paths …) become strings
        self._put(_Config(t_ns, json.loads(json.dumps(jsonable(config), default=str)), reason))

    def write_param_change(
        self, t_ns: int, sample_index: int | None, name: str, old: Any, new: Any, source: str = ""
    ) -> None:
        """A live parameter change, effective from sample number ``sample_index``: the number of
        samples fed to the estimator before the change (None: ``samples``, the count of
        ``write_raw`` calls so far — right when every fed sample is written)."""
        index = self.samples if sample_index is None else int(sample_index)
        self._put(_ParamChange(t_ns, index, name, old, new, source))

    def write_log(self, t_ns: int, severity: int, text: str) -> None:
        """A health event on /log (foxglove.Log); ``severity`` is MAVLink's (0 emergency … 7
        debug), mapped to Foxglove's level by :func:`~ahrs_service.logs.schemas.log_level`."""
        self._put(_Log(t_ns, int(severity), str(text)))

    def write_autopilot_attitude(self, d: Any) -> None:
        """One comparison of the attitude monitor (``attitude_monitor.Disagreement``): the
        autopilot's attitude on /autopilot/attitude and as frame ``autopilot`` on /tf, the
        disagreement on /monitor, all at the autopilot's time mapped onto ours."""
        self._put(_AutopilotAttitude(d))

    def write_timesync(self, status: Any) -> None:
        """The TIMESYNC estimate (``timesync.TimesyncStatus``) on /timesync: offset and drift
        of the autopilot's clock against ours, at the sample's time on our clock."""
        self._put(_Timesync(status))

    def write_mavlink(self, t_ns: int, counters: Mapping[str, Any]) -> None:
        """MAVLink traffic counters."""
        self._put(_Mavlink(t_ns, dict(counters)))

    def new_file(self) -> None:
        """Finishes the current file; the next message starts a new one (with the configuration).

        Call it before ``write_config`` when the estimator is rebuilt (another filter, new
        calibration): each file then starts with a fresh estimator and replays exactly.
        """
        self._put(_NewFile())

    def stats(self) -> dict[str, Any]:
        """Counters for /loop and the service's health report."""
        f = self._file
        return {
            "status": self.status,
            "last_error": self.last_error,
            "written": self.written,
            "dropped": self.dropped,
            "errors": self.errors,
            "queued": len(self._q),
            "file": str(f.path) if f is not None else None,
            "files": len(self.files),
            "samples_not_logged": self.samples_not_logged,
            "outage_s": round(self.not_logged().seconds, 3),
            "outages": self.outages,
        }

    def close(self, timeout: float = 30.0) -> None:
        """Writes everything queued, finishes the file (summary, indexes) and stops the thread."""
        if self._closing:
            self._thread.join(timeout)
            return
        self._closing = True
        self._q.append(_Close())
        self._wake.set()
        self._thread.join(timeout)
        try:
            atexit.unregister(self.close)
        except Exception:  # noqa: BLE001 - interpreter shutting down
            pass

    def __enter__(self) -> "FlightLogWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---------------------------------------------------------------- writer thread
    def _run(self) -> None:
        q = self._q
        while True:
            if q:
                paced = self._loop is not None
                if paced:
                    pause = self._pause_for_the_loop(time.monotonic_ns())
                    if pause:
                        time.sleep(pause)
                    started = time.monotonic_ns()
                item = q.popleft()
                if type(item) is _Close:
                    break
                try:
                    self._handle(item)
                except Exception as exc:  # noqa: BLE001 - a bad message must not end the recording
                    self._dropped_io += 1
                    self._fail(exc) if isinstance(exc, OSError) else self._note(exc)
                if paced:
                    self._record_ns = max(float(time.monotonic_ns() - started), self._record_ns * (15 / 16))
            else:
                self._wake.wait(self._idle_wait_s)
                self._wake.clear()
            now = time.monotonic()
            # flushed now if the next look could come too late for flush_interval_s
            if now - self._last_flush + self._idle_wait_s >= self.flush_interval_s:
                self._last_flush = now
                self._flush()
        self._finish()

    def _pause_for_the_loop(self, now_ns: int) -> float:
        """How long (s) the writer thread sleeps before its next record at ``now_ns``: past
        the loop's next wake-up when the record might not be done by then (twice the recent
        records' duration), else 0. At most half the loop's period is given up, so the
        writer keeps up."""
        wake = self._loop.next_wake_ns
        if wake is None:
            return 0.0
        ahead = wake - now_ns
        if 0 < ahead < min(2.0 * self._record_ns + _AFTER_WAKE_NS, 0.5 * self._loop.period_ns):
            return (ahead + _AFTER_WAKE_NS) * 1e-9
        return 0.0

    def _flush(self) -> None:
        f = self._file
        if f is None:
            return
        if self._stalled:  # an idle writer retries too, not only when messages arrive
            if time.monotonic() >= self._next_retry:
                self._resume()
            return
        if f.unflushed == 0:
            return
        try:
            f.flush(self.fsync)
        except Exception as exc:  # noqa: BLE001 - disk errors must not stop the thread
            self._fail(exc)

    def _close_file(self) -> None:
        """Finishes the current file (summary, indexes); on failure counts what it held
        unflushed and leaves what is on disk (a valid prefix, ``log recover`` completes it)."""
        f = self._file
        self._file = None
        self._stalled = False
        if f is None:
            return
        try:
            f.close(self.fsync)
        except Exception as exc:  # noqa: BLE001
            deleted = isinstance(exc, LogFileDeleted)  # then nothing of it is left
            self._lose(*((f.messages, f.samples) if deleted else (f.unflushed, f.unflushed_samples)))
            self._error(exc, f)
            if not deleted and isinstance(exc, OSError) and self._end_short(f):
                return
            f.abandon()

    def _end_short(self, f: McapLogFile) -> bool:
        """A file the disk refused its end (the disk still full at the end of the run): ends
        it with the writer's final counters instead — a /log line and a /loop whose ``log``
        holds ``samples_not_logged`` as the service's summary states it — so that ``log info``
        and ``log recover`` report what the file misses, not a clean cut of "0 bytes lost".
        False when even that does not fit (the file is left as its valid prefix)."""
        now = time.monotonic_ns()
        lost = self.not_logged()
        text = (f"flight log ended short: {self.last_error}; not logged: {lost.samples} samples, "
                f"{lost.messages} messages, {lost.seconds:.1f} s")
        counters = {"t_ns": now, "log": self.stats()}
        # the room left may be a few hundred bytes (the rest of the file's last block on a
        # full disk; the limit under RLIMIT_FSIZE): the whole tail first, then the counters alone
        tails = ([("/log", now, log_message(now, 3, text)), ("/loop", now, {**jsonable(self._last_loop), **counters})],
                 [("/loop", now, counters)])
        for tail in tails:
            try:
                f.end_short(tail, self.fsync)
            except OSError:
                continue
            self.written += len(tail)
            return True
        return False  # not even the counters fit: the prefix stays

    def _finish(self) -> None:
        self._close_file()
        self._end_outage()
        self.status = "closed"

    def _error(self, exc: BaseException, f: McapLogFile | None = None) -> None:
        self.errors += 1
        if isinstance(exc, OSError):
            # the path and the system's text ("No space left on device"), the errno's name
            path = exc.filename if exc.filename is not None else (f.path if f is not None else self.directory)
            code = errno_mod.errorcode.get(exc.errno or 0, "")
            self.last_error = f"{path}: {exc.strerror or exc}" + (f" ({code})" if code else "")
        else:
            self.last_error = f"{type(exc).__name__}: {exc}"
        if self._outage_since is None:  # set exactly while status is "error"
            self._outage_since = time.monotonic()
            self.outages += 1
            self._outage_start_counts = (self.dropped, self.samples_not_logged)
        self.status = "error"

    def _note(self, exc: BaseException) -> None:
        """A message that could not be encoded or handled: counted, the file goes on."""
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"

    def _lose(self, messages: int, samples: int = 0) -> None:
        self._dropped_io += messages
        self._samples_dropped_io += samples

    def retry_delay(self, attempt: int) -> float:
        """Seconds from the ``attempt``-th failure in a row (0: the first) to the next try."""
        return min(self.retry_max_s, self.retry_first_s * self.retry_factor ** min(attempt, 64))

    def _schedule_retry(self) -> None:
        self._next_retry = time.monotonic() + self.retry_delay(self._retries)
        self._retries += 1

    def _end_outage(self) -> None:
        if self._outage_since is None:
            return
        seconds = time.monotonic() - self._outage_since
        self.outage_s += seconds
        self._outage_since = None
        m0, s0 = self._outage_start_counts
        self.last_outage = Outage(seconds, self.dropped - m0, self.samples_not_logged - s0)

    def _fail(self, exc: BaseException) -> None:
        """An error writing the current file. An OSError (the disk): the file stays open with
        its bytes staged and is retried with back-off. Anything else (the file's own state may
        be broken): what it held unflushed is lost and the next retry starts a new file."""
        f = self._file
        self._error(exc, f)
        if isinstance(exc, LogFileDeleted) and f is not None:
            # nothing of it can be read any more: all it held is lost; a new file comes next
            self._lose(f.messages, f.samples)
            self._file = None
            self._stalled = False
            f.abandon()
        elif isinstance(exc, OSError) and f is not None:
            self._stalled = True
        else:
            self._file = None
            self._stalled = False
            if f is not None:
                self._lose(f.unflushed, f.unflushed_samples)
                f.abandon()
        self._schedule_retry()

    def _resume(self) -> bool:
        """Retries the stalled file; True when the disk took its staged bytes."""
        try:
            self._file.retry(self.fsync)
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)
            return False
        self._stalled = False
        self._recovered()
        return True

    def _recovered(self) -> None:
        self._retries = 0
        self._end_outage()
        self.status = "ok"

    def _open(self, reason: str | None = None) -> bool:
        now = time.monotonic()
        if now < self._next_retry:
            return False
        try:
            if self.directory.exists() and not self.directory.is_dir():
                # mkdir would say "File exists", which reads as if all were well
                raise NotADirectoryError(errno_mod.ENOTDIR, os.strerror(errno_mod.ENOTDIR), str(self.directory))
            self.directory.mkdir(parents=True, exist_ok=True)
            stamp = _dt.datetime.now(_dt.timezone.utc)
            base = log_file_name(self.prefix, stamp)
            path = self.directory / base
            for n in range(1, 1000):  # a second file in the same second gets a suffix
                if not path.exists():
                    break
                path = self.directory / base.replace(".mcap", f"-{n}.mcap")
            meta = {**self.metadata, "start_utc": stamp.isoformat(), "file_index": len(self.files)}
            self._file = McapLogFile(path, chunk_size=self.chunk_size, metadata=meta, exclusive=True)
        except Exception as exc:  # noqa: BLE001
            self._error(exc)
            self._schedule_retry()
            return False
        self.files.append(path)
        self._opened_at = now
        self._last_tf_ns = None
        self._recovered()
        if self._config is not None:
            reason = reason or ("start" if len(self.files) == 1 else "rotation")
            self._write("/config", self._config["t_ns"], {**self._config, "reason": reason})
        return True

    def _should_rotate(self) -> bool:
        f = self._file
        if self._stalled:
            return False
        if self.rotate_bytes is not None and f.size >= self.rotate_bytes:
            return True
        return self.rotate_seconds is not None and time.monotonic() - self._opened_at >= self.rotate_seconds

    def _write(self, topic: str, t_ns: int, message: dict[str, Any], samples: int | None = None) -> None:
        """Encodes and writes one message; ``samples``: the IMU samples it carries (None: one
        on /imu/raw, else none)."""
        if samples is None:
            samples = int(topic == "/imu/raw")
        if self._file is None:  # an earlier write of the same record failed: _fail counted what the file held
            self._lose(1, samples)
            return
        try:
            data = encode(message)
        except (TypeError, ValueError) as exc:
            # a message the caller filled with something JSON cannot hold: lose it, not the file
            self._lose(1, samples)
            self._note(exc)
            return
        try:
            self._file.write_encoded(topic, t_ns, data, samples=samples)
            self.written += 1
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)

    def _handle(self, item: Any) -> None:
        """Hands one queue record to the handler of its kind."""
        self._HANDLERS[type(item)](self, item)

    # one handler per record kind (_HANDLERS maps each record class to its handler)
    def _ensure_file(self, messages: int, reason: str | None = None, samples: int = 0) -> bool:
        """True when a file takes messages (opening one, or retrying the stalled one, when the
        back-off allows); else counts ``messages`` (of which ``samples`` samples) as lost."""
        if self._file is not None and not self._stalled:
            return True
        if self._file is None:
            if self._open(reason):
                return True
        elif time.monotonic() >= self._next_retry and self._resume():
            return True
        self._lose(messages, samples)
        return False

    def _ensure_item(self, item: Any) -> bool:
        """``_ensure_file`` for what ``item`` carries (``_CARRIES``, counted only when lost)."""
        if self._file is not None and not self._stalled:
            return True
        messages, samples = _carried(item)
        return self._ensure_file(messages, samples=samples)

    def _rotate_if_due(self) -> None:
        """At a sample boundary: rotates, or asks the caller for a state snapshot first."""
        if self._file is None or not self._should_rotate():
            return
        now = time.monotonic()
        if not self._state_seen or (self._rotation == _Rotation.DUE and now - self._rotation_since > 2.0):
            # no state snapshot coming (or it stopped coming): rotate here, without one
            self._cancel_rotation()
            self._finish_for_rotation()
        elif self._rotation == _Rotation.IDLE:
            self._rotation, self._rotation_since = _Rotation.DUE, now

    def _on_new_file(self, item: _NewFile) -> None:
        self._cancel_rotation()  # the new file replaces a pending rotation
        if self._file is not None:
            self._finish_for_rotation()

    def _on_config(self, item: _Config) -> None:
        self._config = {"t_ns": int(item.t_ns), "config": item.config, "reason": item.reason}
        if self._file is None:
            self._ensure_file(1, item.reason)  # _open writes the configuration as the file's first message
            return
        self._write("/config", item.t_ns, self._config)

    def _on_param_change(self, item: _ParamChange) -> None:
        self._fold_param(item.name, item.new)
        if not self._ensure_file(1):
            return
        msg = {
            "t_ns": int(item.t_ns),
            "sample_index": item.sample_index,
            "name": str(item.name),
            "old": jsonable(item.old),
            "new": jsonable(item.new),
            "source": str(item.source),
        }
        self._write("/params", item.t_ns, msg)

    def _on_state_snapshot(self, item: _StateSnapshot) -> None:
        if self._rotation:  # else stale: new_file() or a rotation without it already made a new file
            self._rotate_with_state(item)

    def _on_raw(self, item: _Raw) -> None:
        self._rotate_if_due()
        if self._ensure_item(item):
            self._write("/imu/raw", item.t_ns, raw_message(item.t_ns, item.row, item.flags, item.raw, item.temperature, item.index))

    def _on_sample(self, item: _Sample) -> None:
        self._rotate_if_due()
        if not self._ensure_item(item):
            return
        t_ns = item.t_ns
        self._write("/imu/raw", t_ns, raw_message(t_ns, item.row, item.flags, item.raw, item.temperature, item.index))
        self._write_attitude(t_ns, item.q, item.estimator, item.bias, item.diagnostics)
        if item.truth_q is not None:
            self._write("/attitude/truth", t_ns, truth_message(t_ns, item.truth_q))

    def _on_block(self, item: _Block) -> None:
        self._rotate_if_due()  # at the block's start: a rotation's snapshot is a block's end state
        if item.one_message:
            item = self._joined_with_queued(item)
        if not self._ensure_item(item):
            return
        if item.one_message:
            self._write_block_messages(item)
            return
        n = len(item.t_ns)
        truth = None if item.truth_q is None else item.truth_q.tolist()
        per_row = 2 + (truth is not None)
        sources = None if item.t_source_ns is None else item.t_source_ns.tolist()
        temps = None if item.temperature is None else item.temperature.tolist()
        raw = None if item.raw is None else {k: v.tolist() for k, v in item.raw.items()}
        rows, flags, qs = item.rows.tolist(), item.flags.tolist(), item.q.tolist()
        last = n - 1
        for i, t_ns in enumerate(item.t_ns.tolist()):
            if self._file is None:  # a write before failed: _fail counted what the file held
                self._lose((n - i) * per_row, n - i)
                return
            self._write("/imu/raw", t_ns, raw_message(
                t_ns, rows[i], flags[i], None if raw is None else {k: v[i] for k, v in raw.items()},
                None if temps is None else temps[i], item.first_index + i,
                t_source_ns=None if sources is None else sources[i]))
            if i == last:
                self._write_attitude(t_ns, qs[i], item.estimator, item.bias, item.diagnostics)
            else:  # no bias of its own: the key is left out (not zeros a plot would show)
                self._write_attitude(t_ns, qs[i], item.estimator, None, None, with_bias=False)
            if truth is not None:
                self._write("/attitude/truth", t_ns, truth_message(t_ns, truth[i]))

    def _joined_with_queued(self, item: _Block) -> _Block:
        """``item`` and the one-message blocks queued right behind it that continue it, as one
        block: one /imu/raw_block and /attitude_block for all of them, up to the block whose
        last row makes the next /attitude preview due (``tf_rate_hz``: each message then ends
        with one, at that rate) and at most :data:`JOINED_BLOCK_MAX_ROWS` rows. A fast part's
        bursts of a few samples each cost a message per channel each, and the ``mcap``
        library's ``add_message`` is pure Python: joined, the writer pays it once per /tf
        period. Nothing else is queued between them (a rotation's snapshot, a config, the
        close stop the join where they stand)."""
        if self._last_tf_ns is None:
            return item
        q, parts = self._q, [item]
        rows = len(item.t_ns)
        preview_due_ns = self._last_tf_ns + self.tf_period_ns
        while q and int(parts[-1].t_ns[-1]) < preview_due_ns:
            nxt = q[0]
            if (type(nxt) is not _Block or not _continues(parts[-1], nxt)
                    or rows + len(nxt.t_ns) > JOINED_BLOCK_MAX_ROWS):
                break
            parts.append(q.popleft())
            rows += len(nxt.t_ns)
        return item if len(parts) == 1 else _join(parts)

    def _write_block_messages(self, item: _Block) -> None:
        """One /imu/raw_block, /attitude_block (and /attitude/truth_block) for the whole block;
        /attitude and /tf of its last row at ``tf_rate_hz`` (and whenever the block carries
        diagnostics), so Foxglove's plots and 3-D panel have the attitude."""
        t_ns = item.t_ns.tolist()
        t_last = t_ns[-1]
        n = len(t_ns)
        self._write("/imu/raw_block", t_last, raw_block_message(
            t_ns, item.rows, item.flags.tolist(), item.first_index, item.raw, item.temperature,
            None if item.t_source_ns is None else item.t_source_ns.tolist()), samples=n)
        self._write("/attitude_block", t_last,
                    attitude_block_message(t_ns, item.q, item.estimator, item.bias, item.diagnostics))
        if item.truth_q is not None:
            self._write("/attitude/truth_block", t_last, truth_block_message(t_ns, item.truth_q))
        if self._file is None:
            return
        q_last = item.q[-1].tolist()
        tf_due = self._last_tf_ns is None or t_last - self._last_tf_ns >= self.tf_period_ns
        if tf_due or item.diagnostics:  # not counted as carried: a preview of /attitude_block
            self._write_attitude(t_last, q_last, item.estimator, item.bias, item.diagnostics,
                                 with_bias=item.bias is not None)

    def _on_attitude(self, item: _Attitude) -> None:
        if self._ensure_file(1):
            self._write_attitude(item.t_ns, item.q, item.estimator, item.bias, item.diagnostics)

    def _on_truth(self, item: _Truth) -> None:
        if self._ensure_file(1):
            self._write("/attitude/truth", item.t_ns, truth_message(item.t_ns, item.q, item.movement, item.source))

    def _on_loop(self, item: _Loop) -> None:
        self._last_loop = dict(item.stats)
        if self._ensure_file(1):
            self._write("/loop", item.t_ns, {"t_ns": int(item.t_ns), **jsonable(item.stats)})

    def _on_mavlink(self, item: _Mavlink) -> None:
        if self._ensure_file(1):
            self._write("/mavlink", item.t_ns, {"t_ns": int(item.t_ns), "counters": jsonable(item.counters)})

    def _on_autopilot_attitude(self, item: _AutopilotAttitude) -> None:
        if self._ensure_item(item):
            d = item.d
            t = int(d.t_ns)
            for topic, message in autopilot_attitude_messages(t, list(d.q_autopilot), list(d.q_estimate), float(d.total_deg),
                                                              float(d.inclination_deg), float(d.heading_deg)).items():
                self._write(topic, t, message)

    def _on_timesync(self, item: _Timesync) -> None:
        if self._ensure_file(1):
            s = item.status
            t = int(s.local_ns)
            self._write("/timesync", t, {
                "t_ns": t, "offset_ns": int(s.offset_ns), "observed_offset_ns": int(s.observed_offset_ns),
                "drift_ppm": num_or_null(float(s.drift_ppm)), "rtt_ns": int(s.rtt_ns), "synced": bool(s.synced),
                "samples": int(s.samples),
            })

    def _on_log(self, item: _Log) -> None:
        if self._ensure_file(1):
            self._write("/log", item.t_ns, log_message(item.t_ns, item.severity, item.text))

    _HANDLERS: dict[type, Callable[[FlightLogWriter, Any], None]] = {
        _NewFile: _on_new_file,
        _Config: _on_config,
        _ParamChange: _on_param_change,
        _StateSnapshot: _on_state_snapshot,
        _Raw: _on_raw,
        _Sample: _on_sample,
        _Block: _on_block,
        _Attitude: _on_attitude,
        _Truth: _on_truth,
        _Loop: _on_loop,
        _Mavlink: _on_mavlink,
        _AutopilotAttitude: _on_autopilot_attitude,
        _Timesync: _on_timesync,
        _Log: _on_log,
    }

    def _write_attitude(self, t_ns: int, q: list[float], estimator: str, bias: Any, diagnostics: Any,
                        with_bias: bool = True) -> None:
        message = attitude_message(t_ns, q, estimator, bias, diagnostics)
        if not with_bias:
            del message["gyro_bias"]
        self._write("/attitude", t_ns, message)
        if (
            self._file is not None  # /tf is not counted as carried: not written, not lost
            and (self._last_tf_ns is None or t_ns - self._last_tf_ns >= self.tf_period_ns)
            and all(map(math.isfinite, q))  # a transform with null rotation would break the 3-D panel
        ):
            self._last_tf_ns = t_ns
            self._write("/tf", t_ns, tf_message(t_ns, q))

    def _cancel_rotation(self) -> None:
        # a snapshot write_attitude queues after this finds no rotation pending and is ignored
        with self._rotation_lock:
            self._rotation = _Rotation.IDLE

    def _rotate_with_state(self, item: _StateSnapshot) -> None:
        self._cancel_rotation()
        if self._file is not None:
            self._finish_for_rotation()
        if not self._ensure_file(1):
            return
        msg = {
            "t_ns": int(item.t_ns),
            "sample_index": int(item.next_index),
            "estimator": str(item.estimator),
            "state": item.state,
        }
        self._write("/estimator/state", item.t_ns, msg)

    def _fold_param(self, name: str, new: Any) -> None:
        # a new file must start from the parameters in force, or its replay would not match
        cfg = self._config
        if cfg is None:
            return
        est = cfg["config"].get("estimator")
        if isinstance(est, dict):
            est.setdefault("params", {})[str(name)] = jsonable(new)

    def _finish_for_rotation(self) -> None:
        self._close_file()
        self._next_retry = 0.0
