"""Reading damaged MCAP files as far as they are valid, and rewriting them as valid files.

A log whose writer died (SIGKILL, power loss, disk full) has no summary and no footer, and its
last record is usually cut short. :class:`RecordScanner` walks such a file record by record
— checking that each record is complete, that its opcode is known and that every chunk
decompresses and matches its CRC — and stops at the first damage, which it describes in a
:class:`Damage`. :func:`recover` writes every complete message into a new, indexed MCAP file.
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import CompressionType, Writer

from ahrs_service.core.paths import regular_file
from ahrs_service.logs.magic import MCAP_MAGIC as MAGIC

_RECORDS = {
    Opcode.HEADER: Header,
    Opcode.FOOTER: Footer,
    Opcode.SCHEMA: Schema,
    Opcode.CHANNEL: Channel,
    Opcode.MESSAGE: Message,
    Opcode.CHUNK: Chunk,
    Opcode.MESSAGE_INDEX: MessageIndex,
    Opcode.CHUNK_INDEX: ChunkIndex,
    Opcode.ATTACHMENT: Attachment,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex,
    Opcode.STATISTICS: Statistics,
    Opcode.METADATA: Metadata,
    Opcode.METADATA_INDEX: MetadataIndex,
    Opcode.SUMMARY_OFFSET: SummaryOffset,
    Opcode.DATA_END: DataEnd,
}
# a record longer than this is taken as a corrupt length field, not a real record
_MAX_RECORD = 1 << 31
#: uncompressed bytes one chunk may hold. Writers close chunks at about 1 MiB (this project's,
#: the mcap library's default 1 MiB, Foxglove's 4 MiB ...); a chunk that says it holds more is
#: taken as a corrupt or hostile size field (a zstd "bomb" of zeros is a few kB per GiB), not
#: decompressed into memory
MAX_CHUNK_BYTES = 256 << 20
# records a chunk may hold (the format: Schema, Channel, Message); others are damage
_IN_CHUNK = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)


def chunk_bytes(compression: str, data: bytes, uncompressed_size: int, crc: int) -> bytes:
    """A chunk's records, decompressed: never more than ``uncompressed_size`` (itself at most
    :data:`MAX_CHUNK_BYTES`) bytes are produced, whatever the compressed stream or its frame
    header claim, and the result must have exactly that size and, when ``crc`` is not 0, that
    CRC-32. ValueError saying what is wrong otherwise."""
    if uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk says it holds {uncompressed_size} bytes uncompressed, "
                         f"over the reader's limit of {MAX_CHUNK_BYTES >> 20} MiB")
    if compression == "zstd":
        import zstandard

        try:
            reader = zstandard.ZstdDecompressor().stream_reader(io.BytesIO(data), read_across_frames=True)
            out = reader.read(uncompressed_size + 1)  # one byte more tells a stream that is longer
        except zstandard.ZstdError as exc:
            raise ValueError(f"chunk does not decompress (zstd: {exc})") from None
    elif compression == "lz4":
        import lz4.frame

        try:
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=uncompressed_size + 1)
        except RuntimeError as exc:
            raise ValueError(f"chunk does not decompress (lz4: {exc})") from None
    elif compression == "":
        out = data
    else:
        raise ValueError(f"unknown chunk compression {compression[:40]!r}")
    if len(out) != uncompressed_size:
        more = "more than" if len(out) > uncompressed_size else f"{len(out)} bytes, not"
        raise ValueError(f"chunk decompresses to {more} the {uncompressed_size} bytes it states")
    if crc and zlib.crc32(out) != crc:
        raise ValueError("chunk fails its CRC")
    return out


@dataclass
class Damage:
    """Where and why a file stops being readable.

    offset: byte offset of the first damaged record (everything before it is valid).
    file_size: bytes in the file. bytes_lost = file_size − offset (the partial chunk and
        anything after it; messages the writer still held in memory are not counted).
    """

    offset: int
    file_size: int
    reason: str

    @property
    def bytes_lost(self) -> int:
        return self.file_size - self.offset

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "bytes_lost": self.bytes_lost}

    def __str__(self) -> str:
        return f"damaged at byte {self.offset} of {self.file_size} ({self.bytes_lost} bytes lost): {self.reason}"


class RecordScanner:
    """Iterates the records of an MCAP file in order, chunks opened, up to the first damage.

    Yields Header, Schema, Channel, Message, Metadata, Attachment … records (chunk contents
    in place of their chunk). After iteration, ``damage`` is None for a sound, complete file,
    ``complete`` tells whether the footer and closing magic were reached.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self.damage: Damage | None = None
        self.complete = False
        self.valid_end = 0
        #: byte offset of the record the records yielded last came from (a chunk's, for its messages)
        self.record_offset = 0

    def __iter__(self) -> Iterator[Any]:
        size = self.path.stat().st_size
        with open(self.path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                self.damage = Damage(0, size, "not an MCAP file (bad magic)")
                return
            pos = 8
            self.valid_end = pos
            while True:
                if pos == size:
                    self.damage = Damage(pos, size, "file ends without footer (writer did not finish)")
                    return
                if size - pos < 9:
                    self.damage = Damage(pos, size, f"record header cut short ({size - pos} of 9 bytes)")
                    return
                opcode, length = struct.unpack("<BQ", f.read(9))
                if opcode not in _RECORDS.keys() and not 0x80 <= opcode <= 0xFF:
                    self.damage = Damage(pos, size, f"invalid opcode 0x{opcode:02x}")
                    return
                if length > _MAX_RECORD or pos + 9 + length > size:
                    self.damage = Damage(
                        pos, size, f"record (opcode 0x{opcode:02x}) cut short: needs {length} bytes, {size - pos - 9} left"
                    )
                    return
                body = f.read(length)
                try:
                    records = self._parse(opcode, body)
                except Exception as exc:  # noqa: BLE001 - any parse failure is damage at this record
                    self.damage = Damage(pos, size, f"record (opcode 0x{opcode:02x}) unreadable: {type(exc).__name__}: {exc}")
                    return
                self.record_offset = pos
                pos += 9 + length
                self.valid_end = pos
                for record in records:
                    yield record
                if opcode == Opcode.FOOTER:
                    if f.read(len(MAGIC)) == MAGIC:
                        self.complete = True
                        self.valid_end = pos + 8
                    else:
                        self.damage = Damage(pos, size, "closing magic missing after footer")
                    return

    @staticmethod
    def _parse(opcode: int, body: bytes) -> list[Any]:
        cls = _RECORDS.get(opcode)
        if cls is None:
            return []  # user-defined opcodes are skipped, as the format says
        stream = ReadDataStream(io.BytesIO(body))
        record = cls.read(stream, len(body)) if cls is Message else cls.read(stream)
        if stream.count > len(body):
            raise ValueError("record fields overrun the record")
        if isinstance(record, Chunk):
            # decompression and the uncompressed CRC catch a chunk damaged in the middle, and
            # each record inside is checked as the file's own records are
            return RecordScanner._chunk_records(record)
        return [record]

    @staticmethod
    def _chunk_records(chunk: Chunk) -> list[Any]:
        data = chunk_bytes(chunk.compression, chunk.data, chunk.uncompressed_size, chunk.uncompressed_crc)
        records: list[Any] = []
        pos = 0
        while pos < len(data):
            if len(data) - pos < 9:
                raise ValueError(f"record header cut short at byte {pos} of the chunk's {len(data)}")
            opcode, length = struct.unpack_from("<BQ", data, pos)
            if opcode not in _IN_CHUNK and not 0x80 <= opcode <= 0xFF:
                raise ValueError(f"invalid opcode 0x{opcode:02x} at byte {pos} of the chunk")
            if pos + 9 + length > len(data):
                raise ValueError(f"record (opcode 0x{opcode:02x}) at byte {pos} of the chunk needs {length} bytes, "
                                 f"{len(data) - pos - 9} left")
            records += RecordScanner._parse(opcode, data[pos + 9 : pos + 9 + length])
            pos += 9 + length
        return records


@dataclass
class RecoveryReport:
    """What :func:`recover` saved.

    messages: count per topic; start_ns/end_ns: log-time range of the saved messages;
    bytes_total/bytes_valid/bytes_lost: size of the input, of its valid prefix and the rest;
    damage: None when the input was complete and sound.
    """

    source: str
    output: str
    messages: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int | None = None
    bytes_total: int = 0
    bytes_valid: int = 0
    damage: Damage | None = None

    @property
    def bytes_lost(self) -> int:
        return self.bytes_total - self.bytes_valid

    @property
    def total_messages(self) -> int:
        return sum(self.messages.values())

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["damage"] = self.damage.as_dict() if self.damage else None
        d["bytes_lost"] = self.bytes_lost
        d["duration_s"] = None if self.start_ns is None else (self.end_ns - self.start_ns) / 1e9
        return d


def default_output(path: str | os.PathLike) -> Path:
    p = Path(path)
    return p.with_name(p.stem + ".recovered.mcap")


def recover(path: str | os.PathLike, out_path: str | os.PathLike | None = None) -> RecoveryReport:
    """Rewrites every complete message of a (possibly truncated) MCAP file into a valid one.

    Schemas, channels, metadata and attachments are kept; message bytes, log and publish times
    and sequence numbers are copied unchanged. The output (default ``NAME.recovered.mcap``
    beside the input) has a summary and chunk/message indexes, and a metadata record
    "recovery" describing the damage. ValueError, and no output file, when there is nothing to
    recover (no MCAP magic, or not one complete message).
    """
    src = Path(path)
    out = Path(out_path) if out_path is not None else default_output(src)
    regular_file(src)  # OSError naming it: missing, a directory, a FIFO (open() would block)
    if os.path.realpath(out) == os.path.realpath(src):  # realpath: a symbolic-link loop does not raise
        raise ValueError(f"{out}: is the input; recover writes a new file beside it (give another OUTPUT)")
    with open(src, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:  # nothing to recover: write no empty "recovered" file
            raise ValueError(f"{src}: not an MCAP file (bad magic): nothing to recover")
    report = RecoveryReport(source=str(src), output=str(out), bytes_total=src.stat().st_size)
    scanner = RecordScanner(src)
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    topics: dict[int, str] = {}
    try:
        with open(out, "wb") as f:
            w = Writer(f, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
            profile, library = "", "ahrs-service recover"
            started = False
            for rec in scanner:
                if isinstance(rec, Header):
                    profile = rec.profile
                    library = f"{rec.library} (recovered by ahrs-service)"
                    continue
                if not started:
                    w.start(profile=profile, library=library)
                    started = True
                if isinstance(rec, Schema):
                    if rec.id not in schema_ids:
                        schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in channel_ids:
                        channel_ids[rec.id] = w.register_channel(
                            rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0), rec.metadata
                        )
                        topics[rec.id] = rec.topic
                elif isinstance(rec, Message):
                    cid = channel_ids.get(rec.channel_id)
                    if cid is None:
                        continue  # a message whose channel record was lost cannot be decoded
                    w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    topic = topics[rec.channel_id]
                    report.messages[topic] = report.messages.get(topic, 0) + 1
                    report.start_ns = rec.log_time if report.start_ns is None else min(report.start_ns, rec.log_time)
                    report.end_ns = rec.log_time if report.end_ns is None else max(report.end_ns, rec.log_time)
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, rec.metadata)
                elif isinstance(rec, Attachment):
                    w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
            if not started:
                w.start(profile=profile, library=library)
            report.bytes_valid = scanner.valid_end
            report.damage = scanner.damage
            w.add_metadata(
                "recovery",
                {
                    "source": src.name,
                    "damage": str(scanner.damage) if scanner.damage else "none",
                    "bytes_lost": str(report.bytes_lost),
                    "messages": json.dumps(report.messages),
                },
            )
            w.finish()
    except BaseException:  # Ctrl-C, SIGTERM, a full disk: no half-written "recovered" file
        out.unlink(missing_ok=True)
        raise
    if report.total_messages == 0:  # a "recovered" file with nothing in it is no recovery
        out.unlink()
        damage = f" ({report.damage})" if report.damage else ""
        raise ValueError(f"{src}: no complete message{damage}: nothing to recover")
    return report
