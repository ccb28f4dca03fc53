"""Recognising an MCAP file by its first bytes, before any reader opens it.

The bytes are spelled out rather than taken from ``mcap.writer``: checking a configured path
should not load the writer and its compressors.
"""

from __future__ import annotations

#: the first (and last) bytes of every MCAP file
MCAP_MAGIC = b"\x89MCAP0\r\n"


def starts_like_mcap(head: bytes) -> bool:
    """Whether ``head``, a file's first bytes, opens an MCAP file."""
    return head[:len(MCAP_MAGIC)] == MCAP_MAGIC
