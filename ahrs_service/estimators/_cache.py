"""Keeps numba's on-disk kernel cache of this package consistent with its sources.

numba keys a cached kernel (``cache=True``) on the time stamp of the file that defines it,
but every estimator kernel inlines code from other files: ``_kernel.py``, ``quaternion.py``
and sibling modules. After any of those changes (``git pull`` on an editable install, an
edit), the cached kernels of the files that did not change would run the old code. So the
package stamps its cache folder with a digest of all those sources and empties it when the
digest differs; the kernels are then compiled again once.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

_HERE = Path(__file__).resolve().parent
# modules that call kernels but that no kernel reads (functions or constants) from: editing
# them must not cost a recompilation of everything
_NOT_KERNEL_SOURCES = {"_cache.py", "offline.py", "uncertainty.py"}
_SOURCES = sorted(p for p in _HERE.glob("*.py") if p.name not in _NOT_KERNEL_SOURCES) + [_HERE.parent / "quaternion.py"]
_CACHE = _HERE / "__pycache__"
_STAMP = _CACHE / "kernel-sources.sha256"


def sources_digest() -> str:
    """SHA-256 over every source file the estimator kernels are compiled from."""
    h = hashlib.sha256()
    for path in _SOURCES:
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def drop_stale_kernels() -> bool:
    """Deletes this package's cached kernels when their sources changed; True if it did.

    Best effort: a read-only installation keeps its cache (it cannot have been edited).
    """
    digest = sources_digest()
    try:
        if _STAMP.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        _CACHE.mkdir(exist_ok=True)
        for f in list(_CACHE.glob("*.nbi")) + list(_CACHE.glob("*.nbc")):
            f.unlink(missing_ok=True)
        _STAMP.write_text(digest)
    except OSError:
        return False
    return True
