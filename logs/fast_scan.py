"""A fast, read-only pass over an MCAP file's messages, for tools that read whole long logs.

:class:`~ahrs_service.logs.reader.MessageSource` goes through the ``mcap`` library, which
builds a record object per message: slow over a whole long log. :func:`scan_messages` walks
the same records with ``struct`` on the decompressed chunk bytes and hands out only the wanted topics' payloads, without objects —
the MCAP format's record layout (https://mcap.dev/spec): opcode u8, length u64, then the
fields; a Chunk's records are compressed with zstd (this project's writer) or stored.

Like the stream path of ``MessageSource`` it reads in file order up to the first damage (a
record cut short, a chunk that does not decompress or fails its CRC) and says where in
``ScanResult.damage``. Files with another chunk compression (lz4) raise ``ValueError``; the
caller falls back to ``MessageSource``.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Callable

from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES, check_read_budget
from ahrs_service.logs.magic import MCAP_MAGIC
from ahrs_service.logs.recover import chunk_bytes

_HEAD = struct.Struct("<BQ")
_CHUNK = struct.Struct("<QQQI")  # message start, message end, uncompressed size, uncompressed CRC
_MSG = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK_OP, _FOOTER = 0x03, 0x04, 0x05, 0x06, 0x02


@dataclass
class ScanResult:
    """What a scan read: messages handed out, and the damage that stopped it (None: sound)."""

    messages: int = 0
    damage: str | None = None


def _channel(body: bytes, channels: dict[int, str]) -> None:
    cid = int.from_bytes(body[0:2], "little")
    n = int.from_bytes(body[4:8], "little")
    channels[cid] = body[8 : 8 + n].decode()


def scan_messages(path: str | os.PathLike, handlers: dict[str, Callable[[int, bytes], None]],
                  budget_bytes: int = DEFAULT_READ_BUDGET_BYTES) -> ScanResult:
    """Calls ``handlers[topic](log_time_ns, data)`` for every message of a handled topic, in
    file order, up to the first damage (see :class:`ScanResult`). A log over the read budget
    raises :class:`~ahrs_service.logs.budget.ReadBudgetExceeded` first (``logs/budget.py``)."""
    check_read_budget(path, budget_bytes)
    result = ScanResult()
    channels: dict[int, str] = {}
    wanted: dict[int, Callable[[int, bytes], None] | None] = {}
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            result.damage = "not an MCAP file (bad magic)"
            return result
        pos = 8
        while True:
            head = f.read(9)
            if len(head) < 9:
                result.damage = f"file ends at byte {pos} without footer (writer did not finish)"
                return result
            op, length = _HEAD.unpack(head)
            if op == _FOOTER:
                return result
            if pos + 9 + length > size:
                result.damage = f"record at byte {pos} cut short: needs {length} bytes, {size - pos - 9} left"
                return result
            if op != _CHANNEL and op != _CHUNK_OP:
                f.seek(length, os.SEEK_CUR)  # indexes, statistics, metadata …: not messages
                pos += 9 + length
                continue
            body = f.read(length)
            if op == _CHANNEL:
                _channel(body, channels)
            else:
                _, _, raw_size, crc = _CHUNK.unpack_from(body, 0)
                n = int.from_bytes(body[28:32], "little")
                compression = body[32 : 32 + n].decode()
                p = 32 + n
                rec_len = int.from_bytes(body[p : p + 8], "little")
                data = body[p + 8 : p + 8 + rec_len]
                if compression not in ("zstd", ""):
                    raise ValueError(f"chunk compression {compression!r} not handled by the fast scan")
                try:  # bounded: a chunk never decompresses past the size it states (logs/recover.py)
                    records = chunk_bytes(compression, data, raw_size, crc)
                except ValueError as exc:  # a damaged or hostile chunk
                    result.damage = f"chunk at byte {pos}: {exc}"
                    return result
                count, bad = _chunk_messages(records, channels, wanted, handlers)
                result.messages += count
                if bad is not None:
                    result.damage = f"chunk at byte {pos}: {bad}"
                    return result
            pos += 9 + length


def _chunk_messages(records: bytes, channels: dict[int, str], wanted: dict, handlers: dict) -> tuple[int, str | None]:
    """Messages handed out, and what is wrong with the chunk's records (None: sound)."""
    pos, end, count = 0, len(records), 0
    unpack_head, unpack_msg = _HEAD.unpack_from, _MSG.unpack_from
    while pos < end:
        if pos + 9 > end:
            return count, f"record header cut short at byte {pos} of the chunk"
        op, length = unpack_head(records, pos)
        start = pos + 9
        pos = start + length
        if pos > end or (op == _MESSAGE and length < _MSG.size):
            return count, f"record (opcode 0x{op:02x}) at byte {start - 9} of the chunk needs {length} bytes, {end - start} left"
        if op == _MESSAGE:
            cid, _, log_time, _ = unpack_msg(records, start)
            handler = wanted.get(cid, False)
            if handler is False:
                handler = wanted[cid] = handlers.get(channels.get(cid, ""))
            if handler is not None:
                handler(log_time, records[start + 22 : pos])
                count += 1
        elif op == _CHANNEL:
            _channel(records[start:pos], channels)
            wanted.pop(int.from_bytes(records[start : start + 2], "little"), None)
        elif op != _SCHEMA and not 0x80 <= op <= 0xFF:
            return count, f"invalid opcode 0x{op:02x} at byte {start - 9} of the chunk"
    return count, None
