"""Recognising an HDF5 file (a BROAD recording) by its signature, without h5py."""

from __future__ import annotations

from pathlib import Path

#: the HDF5 format signature, at offset 0 or after a user block
HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
#: the first offset a user block may push the signature to; later ones double it
_FIRST_USER_BLOCK = 512


def has_hdf5_signature(path: Path, head: bytes) -> bool:
    """The HDF5 signature at offset 0 (``head``, the file's first bytes) or after a user block
    (512, 1024, 2048 … bytes)."""
    if head[:len(HDF5_SIGNATURE)] == HDF5_SIGNATURE:
        return True
    size = path.stat().st_size
    with path.open("rb") as f:
        offset = _FIRST_USER_BLOCK
        while offset + len(HDF5_SIGNATURE) <= size:
            f.seek(offset)
            if f.read(len(HDF5_SIGNATURE)) == HDF5_SIGNATURE:
                return True
            offset *= 2
    return False
