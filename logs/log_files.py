"""The flight-log writer's file lifecycle: opening, rotation, disk outages, retry, closing.

:class:`LogFiles` is owned by the writer thread of
:class:`~ahrs_service.logs.writer.FlightLogWriter` and used by nothing else: it holds the
current :class:`~ahrs_service.logs.mcap_file.McapLogFile`, writes encoded messages to it and
keeps the writer's status and loss counters.

Errors (unwritable directory, disk full, any ``OSError``) never reach the caller: they set
``status``/``last_error`` (the path and the system's error text), the messages that could not
be written are counted (:class:`Losses`, ``outage_s``), and the next attempt comes after a
back-off: ``retry_first_s`` after the failure, then each delay ``retry_factor`` times the
previous, at most ``retry_max_s``. A file the disk refused stays open with its unwritten bytes
staged (``logs/mcap_file.py``): when the disk takes them again the same file goes on — one
file per recording, no empty or torn leftovers.
"""

from __future__ import annotations

import datetime as _dt
import errno as errno_mod
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from ahrs_service.logs.mcap_file import LogFileDeleted, McapLogFile
from ahrs_service.logs.records import carried
from ahrs_service.logs.schemas import encode, jsonable, log_message


def _estimator_param_names(name: Any) -> frozenset[str]:
    """The parameter names of estimator ``name`` (none for a name no estimator has)."""
    from ahrs_service.estimators.registry import get

    try:
        return frozenset(get(str(name)).param_names())
    except (KeyError, ValueError):
        return frozenset()


@dataclass(frozen=True, slots=True)
class Outage:
    """What an I/O outage (or the whole run) kept out of the files."""

    seconds: float  # s logging was stopped, monotonic clock
    messages: int  # messages not written (all channels)
    samples: int  # of which /imu/raw samples


@dataclass(slots=True)
class Losses:
    """Messages and samples given to the writer that are in no file, by where they were lost.

    Each count has one writing thread: the queue's on the caller's (a full queue refuses a
    record), the files' on the writer thread (an I/O error, a message JSON cannot hold).
    """

    queue_full_messages: int = 0
    queue_full_samples: int = 0  # of those, samples (/imu/raw rows)
    io_messages: int = 0
    io_samples: int = 0  # of those, samples (/imu/raw rows)

    @property
    def messages(self) -> int:
        """Messages lost, all causes."""
        return self.queue_full_messages + self.io_messages

    @property
    def samples(self) -> int:
        """Samples (/imu/raw rows) lost, all causes."""
        return self.queue_full_samples + self.io_samples


def log_file_name(prefix: str, when: _dt.datetime) -> str:
    """``prefix-YYYYmmddTHHMMSSZ.mcap`` of a UTC start time."""
    return f"{prefix}-{when.strftime('%Y%m%dT%H%M%SZ')}.mcap"


class LogFiles:
    """The sequence of MCAP files one writer records to, and what went wrong with them.

    directory, prefix, chunk_size, metadata, fsync, rotate_bytes, rotate_seconds,
    retry_first_s, retry_factor, retry_max_s: as :class:`~ahrs_service.logs.writer.FlightLogWriter`'s.
    losses: the writer's loss counters; the files add theirs to its ``io_*`` counts.
    final_counters: the writer's ``stats()``, for the /loop a file the disk refused its end
        closes with.

    Not thread-safe: only the writer thread calls its methods; other threads read the counters.
    """

    def __init__(
        self,
        directory: str | os.PathLike,
        *,
        prefix: str,
        chunk_size: int,
        metadata: Mapping[str, Any],
        fsync: bool,
        rotate_bytes: int | None,
        rotate_seconds: float | None,
        retry_first_s: float,
        retry_factor: float,
        retry_max_s: float,
        losses: Losses,
        final_counters: Callable[[], dict[str, Any]],
    ) -> None:
        self.directory = Path(directory)
        self.prefix = prefix
        self.chunk_size = int(chunk_size)
        self.metadata = dict(metadata)
        self.fsync = fsync
        self.rotate_bytes = rotate_bytes
        self.rotate_seconds = rotate_seconds
        self.retry_first_s = float(retry_first_s)
        self.retry_factor = float(retry_factor)
        self.retry_max_s = float(retry_max_s)
        self.losses = losses
        self._final_counters = final_counters

        #: "starting" | "ok" | "error" | "closed"
        self.status = "starting"
        self.last_error = ""
        self.files: list[Path] = []  # every file started, in order
        self.written = 0
        self.errors = 0
        self.outage_s = 0.0  # seconds not logged because of I/O errors, over the whole run
        self.outages = 0  # times logging stopped because of an I/O error
        #: the last outage that ended: what it kept out of the files — the service reports it
        #: when logging resumes
        self.last_outage: Outage | None = None
        self._outage_since: float | None = None  # monotonic s of the failure, while in error
        self._outage_start_losses = (0, 0)  # (messages, samples) lost before the outage

        #: the file being written; None before the first, after a failure that gave it up,
        #: between a rotation's close and the next message
        self.current: McapLogFile | None = None
        #: the current file was refused by the disk and is kept open for a retry (McapLogFile.retry)
        self._stalled = False
        self._retries = 0  # failed attempts since the last success: the back-off's exponent
        self._next_retry = 0.0  # monotonic s
        self._opened_at = 0.0  # monotonic s

        #: the /config message each new file starts with (live parameter changes folded in)
        self.config: dict[str, Any] | None = None
        #: the last /loop's statistics: the tail of a file ended short
        self.last_loop: dict[str, Any] = {}
        #: time of the last /tf in the current file, ns; None: a new file starts its /tf afresh
        self.last_tf_ns: int | None = None

    # ---------------------------------------------------------------- messages
    def write(self, topic: str, t_ns: int, message: dict[str, Any], samples: int | None = None) -> None:
        """Encodes and writes one message; ``samples``: the IMU samples it carries (None: one
        on /imu/raw, else none)."""
        if samples is None:
            samples = int(topic == "/imu/raw")
        if self.current is None:  # an earlier write of the same record failed: _fail counted what the file held
            self.lose(1, samples)
            return
        try:
            data = encode(message)
        except (TypeError, ValueError) as exc:
            # a message the caller filled with something JSON cannot hold: lose it, not the file
            self.lose(1, samples)
            self._note(exc)
            return
        try:
            self.current.write_encoded(topic, t_ns, data, samples=samples)
            self.written += 1
        except Exception as exc:  # noqa: BLE001
            self._fail(exc)

    def ensure_file(self, messages: int, reason: str | None = None, samples: int = 0) -> bool:
        """True when a file takes messages (opening one, or retrying the stalled one, when the
        back-off allows); else counts ``messages`` (of which ``samples`` samples) as lost.
        ``reason``: the /config ``reason`` of a file opened here (None: start or rotation)."""
        if self.current is not None and not self._stalled:
            return True
        if self.current is None:
            if self._open(reason):
                return True
        elif time.monotonic() >= self._next_retry and self._resume():
            return True
        self.lose(messages, samples)
        return False

    def ensure_item(self, item: Any) -> bool:
        """``ensure_file`` for what a queue record carries (``records.CARRIES``, counted only
        when lost)."""
        if self.current is not None and not self._stalled:
            return True
        messages, samples = carried(item)
        return self.ensure_file(messages, samples=samples)

    def fold_param(self, name: str, new: Any) -> None:
        """A live parameter change into the configuration the next file starts with."""
        # a new file must start from the parameters in force, or its replay would not match
        cfg = self.config
        if cfg is None:
            return
        est = cfg["config"].get("estimator")
        # only the estimator's own parameters: /params also records a ground station's other
        # writes (declination, stream rates, calibrations), which the estimator table must not take
        if isinstance(est, dict) and str(name) in _estimator_param_names(est.get("name")):
            est.setdefault("params", {})[str(name)] = jsonable(new)

    def lose(self, messages: int, samples: int = 0) -> None:
        """Counts messages (of which ``samples`` samples) the files did not take."""
        losses = self.losses
        losses.io_messages += messages
        losses.io_samples += samples

    def record_failed(self, exc: BaseException) -> None:
        """A queue record whose encoder raised: one message lost; an ``OSError`` is the disk's
        (the file is retried), anything else a bad message (the file goes on)."""
        self.losses.io_messages += 1
        if isinstance(exc, OSError):
            self._fail(exc)
        else:
            self._note(exc)

    # ---------------------------------------------------------------- lifecycle
    def flush(self) -> None:
        """Closes the current chunk and syncs the file (``fsync``); a stalled file is retried
        instead, once its back-off has passed."""
        f = self.current
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

    def should_rotate(self) -> bool:
        """Whether the current file (not None) is as large or as old as a file may be."""
        f = self.current
        if self._stalled:
            return False
        if self.rotate_bytes is not None and f.size >= self.rotate_bytes:
            return True
        return self.rotate_seconds is not None and time.monotonic() - self._opened_at >= self.rotate_seconds

    def finish_for_rotation(self) -> None:
        """Finishes the current file; the next message opens a new one at once (no back-off)."""
        self._close_file()
        self._next_retry = 0.0

    def finish(self) -> None:
        """Finishes the last file at the end of the run; ``status`` becomes "closed"."""
        self._close_file()
        self._end_outage()
        self.status = "closed"

    def retry_delay(self, attempt: int) -> float:
        """Seconds from the ``attempt``-th failure in a row (0: the first) to the next try."""
        return min(self.retry_max_s, self.retry_first_s * self.retry_factor ** min(attempt, 64))

    def not_logged(self) -> Outage:
        """What is missing from the files: messages, samples, and the seconds logging was
        stopped by I/O errors (an outage still running counted up to now)."""
        seconds = self.outage_s
        if self._outage_since is not None:
            seconds += time.monotonic() - self._outage_since
        losses = self.losses
        return Outage(seconds, losses.messages, losses.samples)

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
            self.current = McapLogFile(path, chunk_size=self.chunk_size, metadata=meta, exclusive=True)
        except Exception as exc:  # noqa: BLE001
            self._error(exc)
            self._schedule_retry()
            return False
        self.files.append(path)
        self._opened_at = now
        self.last_tf_ns = None
        self._recovered()
        if self.config is not None:
            reason = reason or ("start" if len(self.files) == 1 else "rotation")
            self.write("/config", self.config["t_ns"], {**self.config, "reason": reason})
        return True

    def _close_file(self) -> None:
        """Finishes the current file (summary, indexes); on failure counts what it held
        unflushed and leaves what is on disk (a valid prefix, ``log recover`` completes it)."""
        f = self.current
        self.current = None
        self._stalled = False
        if f is None:
            return
        try:
            f.close(self.fsync)
        except Exception as exc:  # noqa: BLE001
            deleted = isinstance(exc, LogFileDeleted)  # then nothing of it is left
            self.lose(*((f.messages, f.samples) if deleted else (f.unflushed, f.unflushed_samples)))
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
        counters = {"t_ns": now, "log": self._final_counters()}
        # the room left may be a few hundred bytes (the rest of the file's last block on a
        # full disk; the limit under RLIMIT_FSIZE): the whole tail first, then the counters alone
        tails = ([("/log", now, log_message(now, 3, text)), ("/loop", now, {**jsonable(self.last_loop), **counters})],
                 [("/loop", now, counters)])
        for tail in tails:
            try:
                f.end_short(tail, self.fsync)
            except OSError:
                continue
            self.written += len(tail)
            return True
        return False  # not even the counters fit: the prefix stays

    # ---------------------------------------------------------------- errors and retry
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
            self._outage_start_losses = (self.losses.messages, self.losses.samples)
        self.status = "error"

    def _note(self, exc: BaseException) -> None:
        """A message that could not be encoded or handled: counted, the file goes on."""
        self.errors += 1
        self.last_error = f"{type(exc).__name__}: {exc}"

    def _schedule_retry(self) -> None:
        self._next_retry = time.monotonic() + self.retry_delay(self._retries)
        self._retries += 1

    def _end_outage(self) -> None:
        if self._outage_since is None:
            return
        seconds = time.monotonic() - self._outage_since
        self.outage_s += seconds
        self._outage_since = None
        m0, s0 = self._outage_start_losses
        self.last_outage = Outage(seconds, self.losses.messages - m0, self.losses.samples - s0)

    def _fail(self, exc: BaseException) -> None:
        """An error writing the current file. An OSError (the disk): the file stays open with
        its bytes staged and is retried with back-off. Anything else (the file's own state may
        be broken): what it held unflushed is lost and the next retry starts a new file."""
        f = self.current
        self._error(exc, f)
        if isinstance(exc, LogFileDeleted) and f is not None:
            # nothing of it can be read any more: all it held is lost; a new file comes next
            self.lose(f.messages, f.samples)
            self.current = None
            self._stalled = False
            f.abandon()
        elif isinstance(exc, OSError) and f is not None:
            self._stalled = True
        else:
            self.current = None
            self._stalled = False
            if f is not None:
                self.lose(f.unflushed, f.unflushed_samples)
                f.abandon()
        self._schedule_retry()

    def _resume(self) -> bool:
        """Retries the stalled file; True when the disk took its staged bytes."""
        try:
            self.current.retry(self.fsync)
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
