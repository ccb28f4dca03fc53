"""One MCAP flight-log file written synchronously, through the ``mcap`` library's public API.

:class:`McapLogFile` registers each channel (and its JSON schema, once) on first use and
writes messages with ``mcap.writer.Writer``'s public methods only (``register_schema``,
``register_channel``, ``add_message``, ``add_metadata``, ``flush``, ``finish``), so a new
``mcap`` release can change its internals without changing what is written (a file ended
short by a full disk gets its last records from ``mcap.records``' public record classes:
:meth:`McapLogFile.end_short`). ``flush`` closes
the open chunk and ``fsync``\\ s the file: everything written so far survives a crash, and
:func:`ahrs_service.logs.recover.recover` turns a file cut off later back into a valid one.

**A failed write loses nothing already written and leaves no torn record.** The ``Writer``
writes into :class:`_StagedOutput`, which keeps the bytes in memory until ``flush`` (or
``close``) commits them with ``os.pwrite`` at the end of what is already on disk. If the disk
refuses them (ENOSPC, EFBIG under ``RLIMIT_FSIZE``, EIO …), the file is cut back to its last
committed length — always the end of a complete record — and the bytes stay staged: the
same call later (``retry``) writes them and the file goes on where it was. The file on disk
is therefore at every moment a valid MCAP prefix (``ahrs-service log recover`` completes it),
one file per recording however long the disk stays full, and ``discard`` removes a file that
never got a byte to disk instead of leaving an empty or "bad magic" one behind.

Not thread-safe: :class:`ahrs_service.logs.writer.FlightLogWriter` owns one on its
background thread; imports, recovery and replay (``broad_import``, ``replay``) use it
directly, where nothing runs in real time.

Requires mcap >= 1.5 (``Writer.flush``; see pyproject.toml).
"""

from __future__ import annotations

import errno
import os
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Message, Schema
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from ahrs_service.logs import schemas
from ahrs_service.logs.schemas import encode

#: the MCAP header's ``library`` field
LIBRARY = "ahrs-service"
#: staged bytes beyond which a write commits them at once (without fsync): an import or a
#: replay that never flushes writes as it goes instead of holding its whole file in memory
COMMIT_BYTES = 4 * 1024 * 1024


class LogFileDeleted(FileNotFoundError):
    """The file was deleted (or its folder removed) while it was being written: what it held
    is gone, and writing on would only fill an inode nobody can open."""


class _StagedOutput:
    """The ``Writer``'s output stream: bytes wait in memory until :meth:`commit` writes them.

    ``tell`` is the offset the next byte will have in the file (committed + staged), which is
    what the ``Writer`` records in its chunk and summary indexes.
    """

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.committed = 0  # bytes on disk (and fsync'ed when asked): always a record boundary
        self._staged = bytearray()

    def write(self, data: bytes) -> int:
        self._staged += data
        return len(data)

    def tell(self) -> int:
        return self.committed + len(self._staged)

    def flush(self) -> None:
        """The ``Writer`` flushes its stream; the bytes go to the disk only in :meth:`commit`."""

    @property
    def staged(self) -> int:
        return len(self._staged)

    def commit(self, fsync: bool) -> None:
        """Writes the staged bytes after the committed ones; on any OSError the file is cut
        back to the committed length, the bytes stay staged, and the error is raised."""
        view = memoryview(self._staged)
        done = 0
        try:
            while done < len(view):
                # released even when pwrite raises: an error's traceback keeps its arguments,
                # and an unreleased view of the buffer forbids resizing it later
                with view[done:] as rest:
                    done += os.pwrite(self.fd, rest, self.committed + done)
            if fsync:
                os.fsync(self.fd)
        except OSError:
            view.release()
            try:
                os.ftruncate(self.fd, self.committed)  # a torn record must not stay on disk
            except OSError:
                pass  # read_log and recover stop at a torn record anyway
            raise
        view.release()
        self.committed += done
        del self._staged[:]

    def drop_staged(self) -> int:
        """Forgets the staged bytes (a file ended short: :meth:`McapLogFile.end_short`);
        returns how many there were."""
        n = len(self._staged)
        self._staged = bytearray()  # a new buffer: nothing may still view the old one
        return n


class McapLogFile:
    """One MCAP file being written, synchronously; channels are registered on first use.

    path: the file; ``exclusive`` refuses to overwrite an existing one.
    chunk_size: bytes of uncompressed messages after which a chunk is closed (zstd).
    metadata: key/values stored in the file's MCAP metadata record "ahrs-service".
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
        flags = os.O_WRONLY | os.O_CREAT | (os.O_EXCL if exclusive else os.O_TRUNC)
        self._out = _StagedOutput(os.open(self.path, flags, 0o644))
        try:
            self._w = Writer(self._out, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._w.start(profile="", library=LIBRARY)
            if metadata:
                self._w.add_metadata("ahrs-service", {str(k): str(v) for k, v in metadata.items()})
        except BaseException:
            os.close(self._out.fd)
            raise
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._seq: dict[int, int] = {}
        self.unflushed = 0  # messages written since the last commit (lost if the process dies now)
        #: IMU samples written (/imu/raw messages, /imu/raw_block rows)
        self.samples = 0
        self._committed_samples = 0  # of which on disk at the last commit
        self._committed_topics: set[str] = set()  # channels (and their schemas) on disk
        self.closed = False
        self._finished = False  # the summary is staged: only commit() is left to do

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
        """Writes one message; ``log_time_ns`` is the sample time (monotonic ns), the publish
        time the wall clock now (ns since the epoch) unless given."""
        self.write_encoded(topic, log_time_ns, encode(message), publish_time_ns)

    def write_encoded(self, topic: str, log_time_ns: int, data: bytes, publish_time_ns: int | None = None,
                      *, samples: int | None = None) -> None:
        """Writes one message already encoded (``schemas.encode``) on ``topic``.

        samples: IMU samples the message carries (counted in :attr:`samples`); None: one for
        /imu/raw, none for any other topic. An /imu/raw_block message gives its row count."""
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._new_channel(topic)
        seq = self._seq[cid] + 1
        self._w.add_message(
            cid, int(log_time_ns), data, time.time_ns() if publish_time_ns is None else int(publish_time_ns), seq
        )
        self._seq[cid] = seq  # counted once written: messages and samples count from here
        self.samples += (topic == "/imu/raw") if samples is None else samples
        self.unflushed += 1
        if self._out.staged >= COMMIT_BYTES:
            self.retry(fsync=False)

    def add_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        """A metadata record ``name`` with string key/values."""
        self._w.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def flush(self, fsync: bool = True) -> None:
        """Closes the current chunk and pushes it to the disk: everything so far survives a
        crash. On an OSError nothing is lost yet: the bytes stay staged for :meth:`retry`."""
        self._w.flush()
        self.retry(fsync)

    def retry(self, fsync: bool = True) -> None:
        """Writes what a failed ``flush`` or ``close`` left staged (raises OSError again if
        the disk still refuses it); afterwards the file goes on as if nothing had happened.
        Raises :class:`LogFileDeleted` when the file has no name on disk any more."""
        if os.fstat(self._out.fd).st_nlink == 0:
            raise LogFileDeleted(errno.ENOENT, "deleted while being written", str(self.path))
        self._out.commit(fsync)
        self.unflushed = 0
        self._committed_samples = self.samples
        self._committed_topics = set(self._channels)

    @property
    def messages(self) -> int:
        """Messages written into this file, in all (the channels' sequence counters)."""
        return sum(self._seq.values())

    @property
    def unflushed_samples(self) -> int:
        """IMU samples written since the last commit."""
        return self.samples - self._committed_samples

    @property
    def size(self) -> int:
        """Bytes written so far, on disk or staged (the open chunk not counted)."""
        return self._out.tell()

    @property
    def committed_bytes(self) -> int:
        """Bytes on disk: a valid MCAP prefix (0: nothing reached the disk yet)."""
        return self._out.committed

    def close(self, fsync: bool = True) -> None:
        """Finishes the file with its summary and indexes. On an OSError the file stays open
        with the summary staged: :meth:`retry` then :meth:`close` again, or :meth:`abandon`."""
        if self.closed:
            return
        if not self._finished:
            self._finished = True
            self._w.finish()
        self.retry(fsync)
        self.closed = True
        os.close(self._out.fd)

    def end_short(self, tail: Sequence[tuple[str, int, Mapping[str, Any]]], fsync: bool = True) -> None:
        """Ends a file whose last bytes the disk refused (a full disk at the end of a run):
        the staged bytes are dropped (the caller counts what they held), and after what is
        on disk come ``tail`` — (topic, log time ns, message), e.g. the writer's final
        counters — as messages outside any chunk, a DataEnd and a footer without summary
        section: a complete MCAP, read as a stream (no index), a few hundred bytes where the
        refused chunk and summary did not fit, that says what the file misses. Written
        with the mcap library's record classes (``mcap.records``), as its ``Writer`` writes
        them. Raises OSError if even that does not fit; the file is then its valid prefix
        as before (``abandon`` it)."""
        if self.closed:
            return
        if self._out.committed == 0:  # the header never reached the disk: nothing to end
            raise OSError(errno.ENOSPC, "nothing of the file reached the disk", str(self.path))
        for topic, _, _ in tail:  # ids for channels not used yet (their records are in the tail)
            if topic not in self._channels:
                self._new_channel(topic)
        self._out.drop_staged()
        self.samples, self.unflushed = self._committed_samples, 0  # what is on disk (the tail has none)
        out = RecordBuilder()
        on_disk = set(self._committed_topics)
        schemas_on_disk = {schemas.CHANNELS[t][0] for t in on_disk}
        for topic, log_time_ns, message in tail:
            cid = self._channels[topic]
            name, _ = schemas.CHANNELS[topic]
            sid = self._schemas[name]
            if name not in schemas_on_disk:
                Schema(id=sid, name=name, encoding=schemas.SCHEMA_ENCODING, data=schemas.schema_bytes(topic)).write(out)
                schemas_on_disk.add(name)
            if topic not in on_disk:
                Channel(id=cid, topic=topic, message_encoding=schemas.MESSAGE_ENCODING, schema_id=sid,
                        metadata={}).write(out)
                on_disk.add(topic)
            self._seq[cid] += 1
            Message(channel_id=cid, sequence=self._seq[cid], log_time=int(log_time_ns), publish_time=time.time_ns(),
                    data=encode(message)).write(out)
        DataEnd(data_section_crc=0).write(out)  # 0: not computed (the MCAP specification)
        Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(out)
        self._out.write(out.end() + MCAP0_MAGIC)
        self._out.commit(fsync)  # OSError: cut back to the prefix, as any failed commit
        self.closed = self._finished = True
        os.close(self._out.fd)

    def abandon(self) -> None:
        """Gives the file up after an I/O error: what is on disk stays (a valid MCAP prefix
        that ``ahrs-service log recover`` completes); a file with nothing on disk is removed."""
        if self.closed:
            return
        self.closed = True
        try:
            os.close(self._out.fd)
        except OSError:
            pass
        if self._out.committed == 0:
            self.discard()

    def discard(self) -> None:
        """Removes the file (one that never got its first bytes to disk)."""
        try:
            self.path.unlink()
        except OSError:
            pass

    def __enter__(self) -> "McapLogFile":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
