"""Keeps numba's on-disk kernel cache of this package consistent with its sources.

numba keys a cached kernel (``cache=True``) on the time stamp of the file that defines it,
but every estimator kernel inlines code from other files: ``_kernel.py``, sibling modules and
the ground floor's ``core/quaternion.py`` (and the row layouts of ``core/layout.py`` and
``core/samples.py``, constants in compiled code). After any of those changes (``git pull`` on an editable install, an
edit), the cached kernels of the files that did not change would run the old code. So the
package stamps its cache folder with a digest of all those sources and empties it when the
digest differs; the kernels are then compiled again once.

The folder is numba's: ``__pycache__`` beside the sources, or, when ``$NUMBA_CACHE_DIR`` is
set (the systemd unit sets it, see docs/systemd.md), the sub-folder numba derives from the
sources' folder there (numba's rule for a user-provided cache directory: the folder's name,
``_``, the SHA-1 of its absolute path; numba 0.59–0.68).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

_HERE = Path(__file__).resolve().parent
# modules that call kernels but that no kernel reads (functions or constants) from: editing
# them must not cost a recompilation of everything
_NOT_KERNEL_SOURCES = {"_cache.py", "offline.py", "uncertainty.py"}
_CORE = _HERE.parent / "core"
_SOURCES = sorted(p for p in _HERE.glob("*.py") if p.name not in _NOT_KERNEL_SOURCES) + [
    _CORE / "quaternion.py", _CORE / "layout.py", _CORE / "samples.py"]


def cache_dir() -> Path:
    """The folder numba keeps this package's cached kernels in (see the module's doc)."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    if not root:
        return _HERE / "__pycache__"
    return Path(root) / f"{_HERE.name}_{hashlib.sha1(str(_HERE).encode()).hexdigest()}"


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
    cache = cache_dir()
    stamp = cache / "kernel-sources.sha256"
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        cache.mkdir(parents=True, exist_ok=True)
        for f in list(cache.glob("*.nbi")) + list(cache.glob("*.nbc")):
            f.unlink(missing_ok=True)
        stamp.write_text(digest)
    except OSError:
        return False
    return True


def kernels_cached(module: str) -> bool:
    """Whether the cache holds compiled kernels of estimator module ``module`` (e.g.
    ``"robust"``): False means its first use compiles (seconds for a paper filter, minutes for
    robust). An index file per compiled kernel, ``<module>.<function>-<line>.py<ver>.nbi``."""
    try:
        return any(cache_dir().glob(f"{module}.*.nbi"))
    except OSError:
        return False
