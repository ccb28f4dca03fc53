"""Input files the commands and the service read: a path must name a regular file.

A FIFO blocks ``open()`` until some other process writes to it (``log info``, ``replay``,
``config --check`` and a SIGHUP reload of the service's loop hung on one without a writer),
and a log reader seeks, which no FIFO, socket or device can. :func:`regular_file` raises an
``OSError`` naming the path for each such case, so that ``cli.path_error`` and the
configuration's ``_unreadable`` make it the same one line as a missing file.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

_KINDS = ((stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"))


def regular_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path if it names a regular file (symbolic links followed). Else the
    OSError of :func:`os.stat` (missing, a symbolic-link loop, no permission on a folder),
    ``IsADirectoryError``, or ``OSError(EINVAL, "not a regular file (a FIFO)")`` and the like,
    each with ``filename`` set. Never opens the file."""
    p = Path(path)
    mode = os.stat(p).st_mode
    if stat.S_ISDIR(mode):
        raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(p))
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "a special file")
        raise OSError(errno.EINVAL, f"not a regular file ({kind})", str(p))
    return p
