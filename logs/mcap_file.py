"""One MCAP flight-log file written synchronously, through the ``mcap`` library's public API.

:class:`McapLogFile` registers each channel (and its JSON schema, once) on first use and
writes messages with ``mcap.writer.Writer``'s public methods only (``register_schema``,
``register_channel``, ``add_message``, ``add_metadata``, ``flush``, ``finish``), so a new
``mcap`` release can change its internals without changing what is written. ``flush`` closes
the open chunk and ``fsync``\\ s the file: everything written so far survives a crash, and
:func:`ahrs_service.logs.recover.recover` turns a file cut off later back into a valid one.

Not thread-safe: :class:`ahrs_service.logs.writer.FlightLogWriter` owns one on its
background thread; imports, recovery and replay (``broad_import``, ``replay``) use it
directly, where nothing runs in real time.

Requires mcap >= 1.5 (``Writer.flush``; see pyproject.toml).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping

from mcap.writer import CompressionType, Writer

from ahrs_service.logs import schemas
from ahrs_service.logs.schemas import encode

#: the MCAP header's ``library`` field
LIBRARY = "ahrs-service"


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
        self._f = open(self.path, "xb" if exclusive else "wb")
        try:
            self._w = Writer(self._f, chunk_size=chunk_size, compression=CompressionType.ZSTD)
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
        """Writes one message; ``log_time_ns`` is the sample time (monotonic ns), the publish
        time the wall clock now (ns since the epoch) unless given."""
        self.write_encoded(topic, log_time_ns, encode(message), publish_time_ns)

    def write_encoded(self, topic: str, log_time_ns: int, data: bytes, publish_time_ns: int | None = None) -> None:
        """Writes one message already encoded (``schemas.encode``) on ``topic``."""
        cid = self._channels.get(topic)
        if cid is None:
            cid = self._new_channel(topic)
        seq = self._seq[cid] = self._seq[cid] + 1
        self._w.add_message(
            cid, int(log_time_ns), data, time.time_ns() if publish_time_ns is None else int(publish_time_ns), seq
        )
        self.unflushed += 1

    def add_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        """A metadata record ``name`` with string key/values."""
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
