"""How many bytes reading a log may decompress: a log is refused before its first chunk is opened
when its chunks state more than the read budget allows.

Each chunk is decompressed to no more than the size its record states (``recover.chunk_bytes``
refuses one that decompresses to anything else), so the stated sizes, summed over the file's
records without decompressing anything (one small read per chunk), bound what a read will
hold. Two limits (docs/logs.md, "Decompression budget"):

- **the budget** (:data:`DEFAULT_READ_BUDGET_BYTES`, ``--read-budget-mb``): bytes in all, which
  bounds the memory a read takes (the reader keeps every row);
- **the expansion** (:data:`MAX_EXPANSION`): decompressed bytes per byte of file beyond
  :data:`EXPANSION_FREE_BYTES`. The project's logs decompress to about 4 times their size
  (zstd over JSON numbers); a "bomb" of repeated messages to thousands of times.

A refused log raises :class:`ReadBudgetExceeded`, a ValueError whose text is one line: the
path, where the chunk that crosses the limit starts, the bytes and the limit (its ``damage``:
the same as a :class:`~ahrs_service.logs.recover.Damage`).
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

from ahrs_service.logs.magic import MCAP_MAGIC
from ahrs_service.logs.recover import MAX_CHUNK_BYTES, Damage

#: bytes all chunks of one log may decompress to. The largest log the project writes in one
#: sitting: a 10-minute run at the fastest rate still logged one message per sample
#: (``log.block_messages_above_hz``, 1500 Hz) at the ~990 bytes per sample of /imu/raw,
#: /attitude and /tf measured on the default run (7.8 MB for 7 920 samples), about 0.9 GB;
#: four times that for margin. Longer unrotated logs need ``--read-budget-mb``.
DEFAULT_READ_BUDGET_BYTES = 4 << 30
#: decompressed bytes per byte of file a log may need (the project's logs: 3.9 on the default
#: run, 7.5 on a still simulated sensor without noise, the most repetitive the service writes)
MAX_EXPANSION = 100.0
#: decompressed bytes any log may need whatever its expansion, so that a short log of repeated
#: values is never refused: a read holds about 7 bytes of rows per byte decompressed (the
#: 762 600-row bomb of 137 MB took 942 MB), so about 110 MB at most here
EXPANSION_FREE_BYTES = 16 << 20

_HEAD = struct.Struct("<BQ")
_CHUNK_OP, _FOOTER = 0x06, 0x02
_CHUNK_SIZE_FIELD = struct.Struct("<Q")  # after message start and end time (2 × u64)


class ReadBudgetExceeded(ValueError):
    """A log whose chunks state more decompressed bytes than the read may take."""

    def __init__(self, path: Path, damage: Damage) -> None:
        super().__init__(f"{path}: refused, nothing read: the chunk at byte {damage.offset} of {damage.file_size} "
                         f"{damage.reason}")
        self.path = path
        self.damage = damage


def budget_bytes_from_mb(mb: float) -> int:
    """``--read-budget-mb`` (MiB, > 0) as bytes; ValueError naming the option otherwise."""
    if not (isinstance(mb, (int, float)) and mb > 0 and mb < 1 << 40):
        raise ValueError(f"--read-budget-mb: {mb!r} must be a number of MiB above 0")
    return int(mb * (1 << 20))


def check_read_budget(path: str | os.PathLike, budget_bytes: int = DEFAULT_READ_BUDGET_BYTES) -> int:
    """The decompressed bytes the log at ``path`` states (its chunks' uncompressed sizes, plus
    the records stored outside chunks); :class:`ReadBudgetExceeded` when they pass
    ``budget_bytes`` or :data:`MAX_EXPANSION` times the file's size. Walks the file's records
    up to the footer, the first record that is cut short or the first chunk over
    ``recover.MAX_CHUNK_BYTES`` (the read stops there and reports that damage)."""
    path = Path(path)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if f.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
            return 0  # the read reports "not an MCAP file"
        expansion_limit = max(EXPANSION_FREE_BYTES, int(MAX_EXPANSION * size))
        total, pos = 0, len(MCAP_MAGIC)
        while pos + _HEAD.size <= size:
            f.seek(pos)
            op, length = _HEAD.unpack(f.read(_HEAD.size))
            if op == _FOOTER or pos + _HEAD.size + length > size:
                break
            stated = length
            if op == _CHUNK_OP and length >= 24:
                f.seek(16, os.SEEK_CUR)
                stated = _CHUNK_SIZE_FIELD.unpack(f.read(8))[0]
                if stated > MAX_CHUNK_BYTES:
                    break  # never decompressed: the read stops at this chunk and reports it
            if total + stated > budget_bytes or total + stated > expansion_limit:
                over_budget = total + stated > budget_bytes
                limit = (f"the read budget of {budget_bytes / (1 << 20):g} MiB (--read-budget-mb)" if over_budget
                         else f"{MAX_EXPANSION:g} times the file's {size} bytes (a decompression bomb?)")
                raise ReadBudgetExceeded(path, Damage(pos, size, (
                    f"takes what the log decompresses to {total + stated} bytes, more than {limit}")))
            total += stated
            pos += _HEAD.size + length
    return total
