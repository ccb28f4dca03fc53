"""Flight-log recording to MCAP: a cheap, never-raising writer for the service loop.

:class:`FlightLogWriter` is what the service uses. Its ``write_*`` methods only copy their
arguments into plain Python values and append one named record per call
(:mod:`ahrs_service.logs.records`) to a bounded queue; a background thread hands each record
to its encoder (:mod:`ahrs_service.logs.encoders`), which turns it into JSON messages written
to the current file of :class:`~ahrs_service.logs.log_files.LogFiles` (the file lifecycle:
opening, rotation, disk outages, retry, closing) through
:class:`~ahrs_service.logs.mcap_file.McapLogFile` (the MCAP file layer, ``logs/mcap_file.py``,
on the ``mcap`` library's public API). The thread closes the current chunk and ``fsync``\\ s
the file at least every ``flush_interval_s`` seconds, so a crash (power loss, SIGKILL) loses
at most about that much data; :func:`ahrs_service.logs.recover.recover` turns such a file
back into a valid one.

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

Adding a message kind: a record class in ``logs/records.py``, a ``write_*`` method here that
queues it, and an encoder method registered in ``RecordEncoders.handlers`` (``logs/encoders.py``).
A record that carries samples (or several messages) says how many in ``records.CARRIES``, and
its encoder checks for a file with ``LogFiles.ensure_item(item)``, so the queue and the disk
count the same "not logged".
"""

from __future__ import annotations

import atexit
import collections
import enum
import json
import math
import os
import threading
import time
from typing import Any, Callable, Mapping, Protocol

import numpy as np

from ahrs_service.logs.encoders import JOINED_BLOCK_MAX_ROWS, RecordEncoders
from ahrs_service.logs.log_files import LogFiles, Losses, Outage, log_file_name
from ahrs_service.logs.redaction import redact_config
from ahrs_service.logs.records import (
    Attitude,
    AutopilotAttitude,
    Block,
    Close,
    Config,
    Log,
    Loop,
    Mavlink,
    NewFile,
    ParamChange,
    Raw,
    Sample,
    StateSnapshot,
    Timesync,
    Truth,
    carried,
)
from ahrs_service.logs.schemas import jsonable

__all__ = ["FlightLogWriter", "JOINED_BLOCK_MAX_ROWS", "LoopWakeups", "Outage", "log_file_name"]


class _Rotation(enum.IntEnum):
    """The rotation handshake between the writer thread and the caller's ``write_*``."""

    IDLE = 0  # no rotation pending
    DUE = 1  # the file is due: the writer thread waits for the caller's state snapshot
    SNAPSHOT_QUEUED = 2  # a StateSnapshot is queued; the writer thread rotates when it gets it


_IDLE_WAIT_S = 0.2  # longest sleep of an idle writer thread, s
#: how long after the loop's wake-up the writer thread stays asleep, ns: time for the loop's
#: thread to take the interpreter
_AFTER_WAKE_NS = 50_000
#: how long (s) a due rotation waits for the caller's state snapshot before it goes on without one
_SNAPSHOT_WAIT_S = 2.0


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


def _kept_by(part: str, name: str, doc: str) -> property:
    """A writer attribute that lives in one of its parts (``_log_files``, ``_encoders``): read
    and set through the writer as before the parts existed."""
    return property(lambda self: getattr(getattr(self, part), name),
                    lambda self, value: setattr(getattr(self, part), name, value), doc=doc)


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

    # settings and counters of the file lifecycle (LogFiles) and the encoders, as attributes
    directory = _kept_by("_log_files", "directory", "Folder of the logs (a Path).")
    prefix = _kept_by("_log_files", "prefix", "File name prefix.")
    chunk_size = _kept_by("_log_files", "chunk_size", "Bytes of uncompressed messages per chunk.")
    metadata = _kept_by("_log_files", "metadata", "Each file's MCAP metadata record \"ahrs-service\".")
    fsync = _kept_by("_log_files", "fsync", "Whether flushes and closes sync the file to disk.")
    rotate_bytes = _kept_by("_log_files", "rotate_bytes", "A file this large (bytes) is rotated; None: never.")
    rotate_seconds = _kept_by("_log_files", "rotate_seconds", "A file this old (s) is rotated; None: never.")
    retry_first_s = _kept_by("_log_files", "retry_first_s", "First retry after an I/O error, s.")
    retry_factor = _kept_by("_log_files", "retry_factor", "Each later retry delay, times the previous.")
    retry_max_s = _kept_by("_log_files", "retry_max_s", "Longest retry delay, s.")
    status = _kept_by("_log_files", "status", "\"starting\" | \"ok\" | \"error\" | \"closed\".")
    last_error = _kept_by("_log_files", "last_error", "The last error: the path and the system's text.")
    files = _kept_by("_log_files", "files", "Every file started, in order (Paths).")
    written = _kept_by("_log_files", "written", "Messages written.")
    errors = _kept_by("_log_files", "errors", "Errors met (I/O and messages that could not be encoded).")
    outage_s = _kept_by("_log_files", "outage_s", "Seconds not logged because of I/O errors (outages ended).")
    outages = _kept_by("_log_files", "outages", "Times logging stopped because of an I/O error.")
    last_outage = _kept_by("_log_files", "last_outage", "The last outage that ended (an Outage), else None.")
    tf_period_ns = _kept_by("_encoders", "tf_period_ns", "Least time between two /tf, ns; 0: every attitude.")

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
        self.flush_interval_s = float(flush_interval_s)
        self.queue_size = int(queue_size)
        self.samples = int(first_sample_index)  # number of the next write_raw sample
        self._losses = Losses()
        self._log_files = LogFiles(
            directory, prefix=prefix, chunk_size=chunk_size, metadata=metadata or {}, fsync=fsync,
            rotate_bytes=rotate_bytes, rotate_seconds=rotate_seconds, retry_first_s=retry_first_s,
            retry_factor=retry_factor, retry_max_s=retry_max_s, losses=self._losses, final_counters=self.stats)
        self._q: collections.deque = collections.deque()
        self._encoders = RecordEncoders(self._log_files, self._q, tf_period_ns=0 if not tf_rate_hz else int(1e9 / tf_rate_hz),
                                        rotate_if_due=self._rotate_if_due)
        #: the handler of each record kind: the encoders', and the writer's own for the records
        #: that steer the files
        self._handlers: dict[type, Callable[[Any], None]] = {
            **self._encoders.handlers(), NewFile: self._on_new_file, StateSnapshot: self._on_state_snapshot}
        self._wake = threading.Event()
        # an idle writer thread sleeps this long (close() wakes it): at 1 kHz it then writes
        # ~200 samples per wake-up, and on a VM every wake-up starts with cold caches
        self._idle_wait_s = min(_IDLE_WAIT_S, self.flush_interval_s / 5)
        self._wake_at = max(1, self.queue_size // 8)
        self._closing = False
        self._last_flush = time.monotonic()
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
        return self._losses.messages

    @property
    def samples_not_logged(self) -> int:
        """Samples (/imu/raw rows) given to the writer that are not in any file."""
        return self._losses.samples

    def not_logged(self) -> Outage:
        """What is missing from the files: messages, samples, and the seconds logging was
        stopped by I/O errors (an outage still running counted up to now)."""
        return self._log_files.not_logged()

    def retry_delay(self, attempt: int) -> float:
        """Seconds from the ``attempt``-th failure in a row (0: the first) to the next try."""
        return self._log_files.retry_delay(attempt)

    def _put(self, item: Any) -> bool:
        # one producer (the service loop): len() then append() cannot overshoot by more than one
        n = len(self._q)
        if self._closing or n >= self.queue_size:
            messages, samples = carried(item)
            losses = self._losses
            losses.queue_full_messages += messages
            losses.queue_full_samples += samples
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
        self._put(Raw(t_ns, row.tolist(), flags, raw, temperature, self.samples))
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
        self._put(Attitude(t_ns, _tolist(q), estimator, None if bias is None else _tolist(bias), diag))
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
        sample as one queue entry: the service's per-sample call, cheaper than the three.
        Same arguments and units as those three (keywords after ``flags``); the file holds
        the same messages. ``diagnostics`` (the estimator's, copied here) fills this sample's
        /attitude ``diagnostics``; the service passes it at its diagnostics rate, else None ({})."""
        self._put(
            Sample(
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
            Block(
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
        correction made it, not the source's rate."""
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
                    if not self._put(StateSnapshot(t_ns, state.tolist(), estimator, self.samples)):
                        self._rotation = _Rotation.DUE  # queue full: ask again with a later sample

    def write_truth(self, t_ns: int, q: Any, movement: bool | None = None, source: str = "") -> None:
        """Ground-truth q_earth←body [w, x, y, z] (NED) for the sample at ``t_ns``."""
        self._put(Truth(t_ns, _tolist(q), movement, source))

    def write_loop(self, t_ns: int, stats: Mapping[str, Any]) -> None:
        """Scheduler statistics (period/jitter s, overruns, load, sensor fault counters)."""
        self._put(Loop(t_ns, dict(stats)))

    def write_config(self, t_ns: int, config: Mapping[str, Any], reason: str = "start") -> None:
        """The effective configuration, with config['estimator'] = {'name': …, 'params': {…}};
        secrets (``mavlink.signing_key`` …) are recorded as ``"<redacted>"`` (``logs/redaction.py``)."""
        # a deep copy the caller cannot change any more; unknown types (paths …) become strings
        self._put(Config(t_ns, json.loads(json.dumps(redact_config(jsonable(config)), default=str)), reason))

    def write_param_change(
        self, t_ns: int, sample_index: int | None, name: str, old: Any, new: Any, source: str = ""
    ) -> None:
        """A live parameter change, effective from sample number ``sample_index``: the number of
        samples fed to the estimator before the change (None: ``samples``, the count of
        ``write_raw`` calls so far — right when every fed sample is written)."""
        index = self.samples if sample_index is None else int(sample_index)
        self._put(ParamChange(t_ns, index, name, old, new, source))

    def write_log(self, t_ns: int, severity: int, text: str) -> None:
        """A health event on /log (foxglove.Log); ``severity`` is MAVLink's (0 emergency … 7
        debug), mapped to Foxglove's level by :func:`~ahrs_service.logs.schemas.log_level`."""
        self._put(Log(t_ns, int(severity), str(text)))

    def write_autopilot_attitude(self, d: Any) -> None:
        """One comparison of the attitude monitor (``attitude_monitor.Disagreement``): the
        autopilot's attitude on /autopilot/attitude and as frame ``autopilot`` on /tf, the
        disagreement on /monitor, all at the autopilot's time mapped onto ours."""
        self._put(AutopilotAttitude(d))

    def write_timesync(self, status: Any) -> None:
        """The TIMESYNC estimate (``timesync.TimesyncStatus``) on /timesync: offset and drift
        of the autopilot's clock against ours, at the sample's time on our clock."""
        self._put(Timesync(status))

    def write_mavlink(self, t_ns: int, counters: Mapping[str, Any]) -> None:
        """MAVLink traffic counters."""
        self._put(Mavlink(t_ns, dict(counters)))

    def new_file(self) -> None:
        """Finishes the current file; the next message starts a new one (with the configuration).

        Call it before ``write_config`` when the estimator is rebuilt (another filter, new
        calibration): each file then starts with a fresh estimator and replays exactly.
        """
        self._put(NewFile())

    def stats(self) -> dict[str, Any]:
        """Counters for /loop and the service's health report."""
        files = self._log_files
        f = files.current
        return {
            "status": files.status,
            "last_error": files.last_error,
            "written": files.written,
            "dropped": self.dropped,
            "errors": files.errors,
            "queued": len(self._q),
            "file": str(f.path) if f is not None else None,
            "files": len(files.files),
            "samples_not_logged": self.samples_not_logged,
            "outage_s": round(files.not_logged().seconds, 3),
            "outages": files.outages,
        }

    def close(self, timeout: float = 30.0) -> None:
        """Writes everything queued, finishes the file (summary, indexes) and stops the thread."""
        if self._closing:
            self._thread.join(timeout)
            return
        self._closing = True
        self._q.append(Close())
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
        files = self._log_files
        while True:
            if q:
                paced = self._loop is not None
                if paced:
                    pause = self._pause_for_the_loop(time.monotonic_ns())
                    if pause:
                        time.sleep(pause)
                    started = time.monotonic_ns()
                item = q.popleft()
                if type(item) is Close:
                    break
                try:
                    self._handle(item)
                except Exception as exc:  # noqa: BLE001 - a bad message must not end the recording
                    files.record_failed(exc)
                if paced:
                    self._record_ns = max(float(time.monotonic_ns() - started), self._record_ns * (15 / 16))
            else:
                self._wake.wait(self._idle_wait_s)
                self._wake.clear()
            now = time.monotonic()
            # flushed now if the next look could come too late for flush_interval_s
            if now - self._last_flush + self._idle_wait_s >= self.flush_interval_s:
                self._last_flush = now
                files.flush()
        files.finish()

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

    def _handle(self, item: Any) -> None:
        """Hands one queue record to the handler of its kind."""
        self._handlers[type(item)](item)

    # rotation, the writer thread's side of the handshake with the caller's _offer_state
    def _rotate_if_due(self) -> None:
        """At a sample boundary: rotates, or asks the caller for a state snapshot first."""
        files = self._log_files
        if files.current is None or not files.should_rotate():
            return
        now = time.monotonic()
        if not self._state_seen or (self._rotation == _Rotation.DUE and now - self._rotation_since > _SNAPSHOT_WAIT_S):
            # no state snapshot coming (or it stopped coming): rotate here, without one
            self._cancel_rotation()
            files.finish_for_rotation()
        elif self._rotation == _Rotation.IDLE:
            self._rotation, self._rotation_since = _Rotation.DUE, now

    def _cancel_rotation(self) -> None:
        # a snapshot write_attitude queues after this finds no rotation pending and is ignored
        with self._rotation_lock:
            self._rotation = _Rotation.IDLE

    def _on_new_file(self, item: NewFile) -> None:
        self._cancel_rotation()  # the new file replaces a pending rotation
        if self._log_files.current is not None:
            self._log_files.finish_for_rotation()

    def _on_state_snapshot(self, item: StateSnapshot) -> None:
        if not self._rotation:  # stale: new_file() or a rotation without it already made a new file
            return
        self._cancel_rotation()
        if self._log_files.current is not None:
            self._log_files.finish_for_rotation()
        self._encoders.state_snapshot(item)
