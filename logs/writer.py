"""Flight-log recording to MCAP: a cheap, never-raising writer for the service loop.

:class:`FlightLogWriter` is what the service uses. Its ``write_*`` methods only copy their
arguments into plain Python values and append them to a bounded queue (about a microsecond
each); a background thread encodes the messages to JSON and writes them with the ``mcap``
library. The thread closes the current chunk and ``fsync``\\ s the file at least every
``flush_interval_s`` seconds, so a crash (power loss, SIGKILL) loses at most about that much
data; :func:`ahrs_service.logs.recover.recover` turns such a file back into a valid one.

Errors (unwritable directory, disk full, any ``OSError``) never reach the caller: they set
``status``/``last_error``, the messages that could not be written are counted in
``dropped``, and the writer tries again with a new file every ``retry_interval_s``.

:class:`McapLogFile` is the synchronous layer underneath, used directly by imports, recovery
and replay, where nothing runs in real time.

Example (the service's estimation loop)::

    log = FlightLogWriter("flight-logs", metadata={"vehicle": "rov-1"})
    log.write_config(t_ns, {"estimator": {"name": "madgwick", "params": est.get_params()}})
    ...
    q = est.update_row(row)                       # row: the (10,) sample row fed to it
    log.write_raw(t_ns, row, sample.flags, sample.raw, sample.temperature_c)
    log.write_attitude(t_ns, q, est.name, est.state[8:11], est.diagnostics, state=est.state)
    # or both in one call (and one queue entry), as the service does at its rate:
    log.write_sample(t_ns, row, sample.flags, q, est.name, est.state[8:11], est.state, sample.raw)
    ...
    log.write_param_change(t_ns, None, "beta", old, new, "mavlink")  # after est.set_params
    ...
    log.close()
"""

from __future__ import annotations

import atexit
import collections
import datetime as _dt
import itertools
import json
import math
import os
import struct
import threading
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from mcap.opcode import Opcode
from mcap.records import MessageIndex
from mcap.writer import CompressionType, Writer

from ahrs_service.logs import schemas
from ahrs_service.logs.schemas import (
    attitude_message,
    encode,
    jsonable,
    log_message,
    raw_message,
    tf_message,
    truth_message,
)

LIBRARY = "ahrs-service"

# --------------------------------------------------------------------------- synchronous file

_MESSAGE_HEADER = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log and publish time


class _PackedMessageIndex(MessageIndex):
    """A chunk's MessageIndex record written with one ``struct`` call for all its entries (the
    library writes each timestamp and offset on its own: two calls per message)."""

    def write(self, stream: Any) -> None:
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write2(self.channel_id)
        stream.write4(len(self.records) * 16)
        stream.write(struct.pack(f"<{2 * len(self.records)}Q", *itertools.chain.from_iterable(self.records)))
        stream.finish_record()


class _ChunkedWriter(Writer):
    """``mcap.Writer`` whose ``add_message`` writes the Message record with one ``struct`` call.

    The library builds a ``Message`` object and writes its six fields one by one, about 10 µs
    a message on the reference machine; the service writes three messages a sample at 1 kHz.
    This does the same bookkeeping (statistics, chunk times, message index) on the library's
    own objects and appends the same bytes — tests/test_logs_writer.py checks that whole files
    come out byte-identical — and falls back to the library's method should a later ``mcap``
    release lay its internals out differently.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        chunk = getattr(self, "_Writer__chunk_builder", None)
        buffer = getattr(getattr(chunk, "record_writer", None), "_buffer", None)
        self._chunk_limit = getattr(self, "_Writer__chunk_size", None)
        self._fast = (
            chunk is not None
            and hasattr(buffer, "write")
            and hasattr(self, "_Writer__statistics")
            and hasattr(self, "_Writer__finalize_chunk")
            and isinstance(self._chunk_limit, int)
            and isinstance(getattr(chunk, "message_indices", None), dict)
        )

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        if not self._fast:
            super().add_message(channel_id, log_time, data, publish_time, sequence)
            return
        stats = self._Writer__statistics  # type: ignore[attr-defined]
        if stats.message_count == 0 or log_time < stats.message_start_time:
            stats.message_start_time = log_time
        if log_time > stats.message_end_time:
            stats.message_end_time = log_time
        stats.channel_message_counts[channel_id] += 1
        stats.message_count += 1
        chunk = self._Writer__chunk_builder  # type: ignore[attr-defined]
        if chunk.num_messages == 0 or log_time < chunk.message_start_time:
            chunk.message_start_time = log_time
        if log_time > chunk.message_end_time:
            chunk.message_end_time = log_time
        index = chunk.message_indices.get(channel_id)
        if not index:
            index = chunk.message_indices[channel_id] = _PackedMessageIndex(channel_id=channel_id, records=[])
        buffer = chunk.record_writer._buffer
        index.records.append((log_time, buffer.tell()))
        chunk.num_messages += 1
        buffer.write(_MESSAGE_HEADER.pack(Opcode.MESSAGE, 22 + len(data), channel_id, sequence, log_time, publish_time))
        buffer.write(data)
        # the library's __maybe_finalize_chunk, without its three property calls per message
        if buffer.tell() > self._chunk_limit:
            self._Writer__finalize_chunk()  # type: ignore[attr-defined]


class McapLogFile:
    """One MCAP file being written, synchronously. Channels are registered on first use.

    Not thread-safe; :class:`FlightLogWriter` owns one on its background thread.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        chunk_size: int = 128 * 1024,
        metadata: Mapping[str, Any] | None = None,
        exclusive: bool = False,
    ) -> None:
        self.path = Path(path)
        self._f = open(self.path, "xb" if exclusive else "wb")
        try:
            self._w = _ChunkedWriter(self._f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._w.start(profile="", library=LIBRARY)
            if metadata:
                self._w.add_metadata("ahrs-service", {str(k): str(v) for k, v in metadata.items()})
        except BaseException:
            self._f.close()
            raise
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.unflushed = 0  # messages written since the last flush (lost if the process dies now)
        self.closed = False

    def _new_channel(self, topic: str) -> int:
        """Registers ``topic``'s channel (and its schema, once) on first use."""
        name, _ = schemas.CHANNELS[topic]
        sid = self._schemas.get(name)
        if sid is None:
            sid = self._w.register_schema(name, schemas.SCHEMA_ENCODING, schemas.schema_bytes(topic))
            self._schemas[name] = sid
        cid = self._w.register_channel(topic, schemas.MESSAGE_ENCODING, sid)
        self._channels[topic] = cid
        self._seq[cid] = 0
        return cid

    def write(self, topic: str, log_time_ns: int, message: Mapping[str, Any], publish_time_ns: int | None = None) -> None:
        """Writes one message; ``log_time_ns`` is the sample time, publish time the wall clock now."""
        self.write_encoded(topic, log_time_ns, encode(message), publish_time_ns)

    def write_encoded(self, topic: str, log_time_ns: int, data: bytes, publish_time_ns: int | None = None) -> None:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._new_channel(topic)
        seq = self._seq[cid] = self._seq[cid] + 1
        self._w.add_message(
            cid, int(log_time_ns), data, time.time_ns() if publish_time_ns is None else int(publish_time_ns), seq
        )
        self.unflushed += 1

    def add_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        self._w.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def flush(self, fsync: bool = True) -> None:
        """Closes the current chunk and pushes it to the disk: everything so far survives a crash."""
        self._w.flush()
        self._f.flush()
        if fsync:
            os.fsync(self._f.fileno())
        self.unflushed = 0

    @property
    def size(self) -> int:
        """Bytes on disk so far (the open chunk not counted)."""
        return self._f.tell()

    def close(self, fsync: bool = True) -> None:
        """Finishes the file with its summary and indexes."""
        if self.closed:
            return
        self.closed = True
        try:
            self._w.finish()
            self._f.flush()
            if fsync:
                os.fsync(self._f.fileno())
            self.unflushed = 0
        finally:
            self._f.close()

    def abandon(self) -> None:
        """Closes the handle without finishing (after an I/O error); recover() can still read it."""
        self.closed = True
        try:
            self._f.close()
        except OSError:
            pass

    def __enter__(self) -> "McapLogFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- threaded writer

_RAW, _ATT, _TRUTH, _LOOP, _CONFIG, _PARAM, _MAV, _CLOSE, _NEW_FILE, _STATE, _SAMPLE, _LOG = range(12)
_IDLE_WAIT_S = 0.2  # longest sleep of an idle writer thread, s


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
    retry_interval_s: after an I/O error, wait this long before trying a new file.
    first_sample_index: number given to the first ``write_raw`` sample (the /imu/raw
        ``index`` that /params ``sample_index`` refers to): pass the estimator's sample count
        when a writer is (re)opened mid-run.

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
        retry_interval_s: float = 2.0,
        fsync: bool = True,
        first_sample_index: int = 0,
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
        self.retry_interval_s = float(retry_interval_s)
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
        self._last_tf_ns: int | None = None
        self._state_seen = False  # the caller passes its estimator state to write_attitude
        # rotation handshake: 0 none, 1 due (writer thread asks for a state snapshot),
        # 2 snapshot queued (write_attitude answered; the writer thread rotates when it gets it).
        # The lock makes write_attitude's 1 -> 2 and the writer thread's cancelling (-> 0) exclusive.
        self._rotation = 0
        self._rotation_lock = threading.Lock()
        self._rotation_since = 0.0
        self._thread = threading.Thread(target=self._run, name="flight-log-writer", daemon=True)
        self._thread.start()
        atexit.register(self.close)

    # ---------------------------------------------------------------- caller side (cheap)
    @property
    def dropped(self) -> int:
        """Messages lost: queue full, or not written because of an I/O error."""
        return self._dropped_full + self._dropped_io

    def _put(self, item: tuple) -> bool:
        # one producer (the service loop): len() then append() cannot overshoot by more than one
        n = len(self._q)
        if self._closing or n >= self.queue_size:
            self._dropped_full += 1
            return False
        if n == self._wake_at:  # a producer faster than real time: the thread must not sleep on
            self._wake.set()
        self._q.append(item)
        return True

    def write_raw(
        self, t_ns: int, row: np.ndarray, flags: int, raw: Mapping[str, Any] | None = None, temperature: float | None = None
    ) -> None:
        """One sample row (10,) exactly as fed to the estimator: gyr rad/s, acc m/s², mag µT (NaN: none), dt s."""
        self._put((_RAW, t_ns, row.tolist(), flags, raw, temperature, self.samples))
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
        self._put((_ATT, t_ns, _tolist(q), estimator, None if bias is None else _tolist(bias), diag))
        if state is not None:
            self._offer_state(t_ns, state, estimator)

    def write_sample(
        self,
        t_ns: int,
        row: np.ndarray,
        flags: int,
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
        Same arguments and units as those three; the file holds the same messages.
        ``diagnostics`` (the estimator's, copied here) fills this sample's /attitude
        ``diagnostics``; the service passes it at its diagnostics rate, else None ({})."""
        self._put(
            (
                _SAMPLE,
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

    def _offer_state(self, t_ns: int, state: np.ndarray, estimator: str) -> None:
        self._state_seen = True
        if self._rotation == 1:
            with self._rotation_lock:
                if self._rotation == 1:
                    # the file ends after this sample; the next starts from this very state
                    self._rotation = 2
                    if not self._put((_STATE, t_ns, state.tolist(), estimator, self.samples)):
                        self._rotation = 1  # queue full: ask again with a later sample

    def write_truth(self, t_ns: int, q: Any, movement: bool | None = None, source: str = "") -> None:
        """Ground-truth q_earth←body [w, x, y, z] (NED) for the sample at ``t_ns``."""
        self._put((_TRUTH, t_ns, _tolist(q), movement, source))

    def write_loop(self, t_ns: int, stats: Mapping[str, Any]) -> None:
        """Scheduler statistics (period/jitter s, overruns, load, sensor fault counters)."""
        self._put((_LOOP, t_ns, dict(stats)))

    def write_config(self, t_ns: int, config: Mapping[str, Any], reason: str = "start") -> None:
        """The effective configuration, with config['estimator'] = {'name': …, 'params': {…}}."""
        # a deep copy the caller cannot change any more; unknown types (paths …) become strings
        self._put((_CONFIG, t_ns, json.loads(json.dumps(jsonable(config), default=str)), reason))

    def write_param_change(
        self, t_ns: int, sample_index: int | None, name: str, old: Any, new: Any, source: str = ""
    ) -> None:
        """A live parameter change, effective from sample number ``sample_index``: the number of
        samples fed to the estimator before the change (None: ``samples``, the count of
        ``write_raw`` calls so far — right when every fed sample is written)."""
        index = self.samples if sample_index is None else int(sample_index)
        self._put((_PARAM, t_ns, index, name, old, new, source))

    def write_log(self, t_ns: int, severity: int, text: str) -> None:
        """A health event on /log (foxglove.Log); ``severity`` is MAVLink's (0 emergency … 7
        debug), mapped to Foxglove's level by :func:`~ahrs_service.logs.schemas.log_level`."""
        self._put((_LOG, t_ns, int(severity), str(text)))

    def write_mavlink(self, t_ns: int, counters: Mapping[str, Any]) -> None:
        """MAVLink traffic counters."""
        self._put((_MAV, t_ns, dict(counters)))

    def new_file(self) -> None:
        """Finishes the current file; the next message starts a new one (with the configuration).

        Call it before ``write_config`` when the estimator is rebuilt (another filter, new
        calibration): each file then starts with a fresh estimator and replays exactly.
        """
        self._put((_NEW_FILE, 0))

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
        }

    def close(self, timeout: float = 30.0) -> None:
        """Writes everything queued, finishes the file (summary, indexes) and stops the thread."""
        if self._closing:
            self._thread.join(timeout)
            return
        self._closing = True
        self._q.append((_CLOSE,))
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
                item = q.popleft()
                if item[0] == _CLOSE:
                    break
                try:
                    self._handle(item)
                except Exception as exc:  # noqa: BLE001 - a bad message must not end the recording
                    self._dropped_io += 1
                    self._error(exc)
            else:
                self._wake.wait(self._idle_wait_s)
                self._wake.clear()
            now = time.monotonic()
            # flushed now if the next look could come too late for flush_interval_s
            if now - self._last_flush + self._idle_wait_s >= self.flush_interval_s:
                self._last_flush = now
                self._flush()
        self._finish()

    def _flush(self) -> None:
        f = self._file
        if f is None or f.unflushed == 0:
            return
        try:
            f.flush(self.fsync)
        except Exception as exc:  # noqa: BLE001 - disk errors must not stop the thread
            self._fail(exc)

    def _close_file(self) -> None:
        """Finishes the current file (summary, indexes); on failure counts what it held unflushed."""
        f = self._file
        self._file = None
        if f is None:
            return
        try:
            f.close(self.fsync)
        except Exception as exc:  # noqa: BLE001
            self._dropped_io += f.unflushed
            self._error(exc)
            f.abandon()

    def _finish(self) -> None:
        self._close_file()
        self.status = "closed"

    def _error(self, exc: BaseException) -> None:
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"
        self.status = "error"

    def _fail(self, exc: BaseException) -> None:
        """An I/O error on the current file: count what it held unflushed, drop it, retry later."""
        self._error(exc)
        f = self._file
        self._file = None
        if f is not None:
            self._dropped_io += f.unflushed
            f.abandon()
        self._next_retry = time.monotonic() + self.retry_interval_s

    def _open(self, reason: str | None = None) -> bool:
        now = time.monotonic()
        if now < self._next_retry:
            return False
        try:
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
            self._next_retry = now + self.retry_interval_s
            return False
        self.files.append(path)
        self._opened_at = now
        self._last_tf_ns = None
        self.status = "ok"
        if self._config is not None:
            reason = reason or ("start" if len(self.files) == 1 else "rotation")
            self._write("/config", self._config["t_ns"], {**self._config, "reason": reason})
        return True

    def _should_rotate(self) -> bool:
        f = self._file
        if self.rotate_bytes is not None and f.size >= self.rotate_bytes:
            return True
        return self.rotate_seconds is not None and time.monotonic() - self._opened_at >= self.rotate_seconds

    def _write(self, topic: str, t_ns: int, message: dict[str, Any]) -> None:
        try:
            data = encode(message)
        except (TypeError, ValueError) as exc:
            # a message the caller filled with something JSON cannot hold: lose it, not the file
            self._dropped_io += 1
            self._error(exc)
            self.status = "ok"
            return
        try:
            self._file.write_encoded(topic, t_ns, data)
            self.written += 1
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)

    def _handle(self, item: tuple) -> None:
        kind, t_ns = item[0], item[1]
        if kind == _NEW_FILE:
            self._cancel_rotation()  # the new file replaces a pending rotation
            if self._file is not None:
                self._finish_for_rotation()
            return
        if kind == _CONFIG:
            self._config = {"t_ns": int(t_ns), "config": item[2], "reason": item[3]}
        elif kind == _PARAM:
            self._fold_param(item[3], item[5])
        if kind == _STATE:
            if self._rotation:  # else stale: new_file() or a rotation without it already made a new file
                self._rotate_with_state(item)
            return
        if self._file is not None and (kind == _RAW or kind == _SAMPLE) and self._should_rotate():
            now = time.monotonic()
            if not self._state_seen or (self._rotation == 1 and now - self._rotation_since > 2.0):
                # no state snapshot coming (or it stopped coming): rotate here, without one
                self._cancel_rotation()
                self._finish_for_rotation()
            elif self._rotation == 0:
                self._rotation, self._rotation_since = 1, now
        if self._file is None:
            if not self._open(self._config["reason"] if kind == _CONFIG else None):
                self._dropped_io += 1 if kind != _SAMPLE else 2 + (item[10] is not None)
                return
            if kind == _CONFIG:
                return  # _open just wrote this configuration as the file's first message
        if kind == _SAMPLE:
            # (_SAMPLE, t_ns, row, flags, raw, temperature, index, q, estimator, bias, truth_q, diagnostics)
            self._write("/imu/raw", t_ns, raw_message(t_ns, *item[2:7]))
            self._write_attitude(t_ns, item[7], item[8], item[9], item[11])
            if item[10] is not None:
                if self._file is None:  # a write before failed: _fail counted what the file held
                    self._dropped_io += 1
                else:
                    self._write("/attitude/truth", t_ns, truth_message(t_ns, item[10]))
        elif kind == _RAW:
            self._write("/imu/raw", t_ns, raw_message(t_ns, *item[2:7]))
        elif kind == _ATT:
            self._write_attitude(t_ns, *item[2:6])
        elif kind == _TRUTH:
            self._write("/attitude/truth", t_ns, truth_message(t_ns, *item[2:5]))
        elif kind == _LOOP:
            self._write("/loop", t_ns, {"t_ns": int(t_ns), **jsonable(item[2])})
        elif kind == _CONFIG:
            self._write("/config", t_ns, self._config)
        elif kind == _PARAM:
            msg = {
                "t_ns": int(t_ns),
                "sample_index": item[2],
                "name": str(item[3]),
                "old": jsonable(item[4]),
                "new": jsonable(item[5]),
                "source": str(item[6]),
            }
            self._write("/params", t_ns, msg)
        elif kind == _LOG:
            self._write("/log", t_ns, log_message(t_ns, item[2], item[3]))
        elif kind == _MAV:
            self._write("/mavlink", t_ns, {"t_ns": int(t_ns), "counters": jsonable(item[2])})

    def _write_attitude(self, t_ns: int, q: list[float], estimator: str, bias: Any, diagnostics: Any) -> None:
        if self._file is None:  # the write before this one failed: _fail counted it, retry later
            self._dropped_io += 1
            return
        self._write("/attitude", t_ns, attitude_message(t_ns, q, estimator, bias, diagnostics))
        if (
            self._file is not None
            and (self._last_tf_ns is None or t_ns - self._last_tf_ns >= self.tf_period_ns)
            and all(map(math.isfinite, q))  # a transform with null rotation would break the 3-D panel
        ):
            self._last_tf_ns = t_ns
            self._write("/tf", t_ns, tf_message(t_ns, q))

    def _cancel_rotation(self) -> None:
        # a snapshot write_attitude queues after this finds no rotation pending and is ignored
        with self._rotation_lock:
            self._rotation = 0

    def _rotate_with_state(self, item: tuple) -> None:
        _, t_ns, state, estimator, next_index = item
        self._cancel_rotation()
        if self._file is not None:
            self._finish_for_rotation()
        if not self._open():
            self._dropped_io += 1
            return
        msg = {"t_ns": int(t_ns), "sample_index": int(next_index), "estimator": str(estimator), "state": state}
        self._write("/estimator/state", t_ns, msg)

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
