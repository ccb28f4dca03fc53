"""Writing the service's TOML configuration file: the one place that does it.

:func:`update_config_file` changes keys of a user's file in place with ``tomlkit`` (its
public API: ``parse``, item assignment, ``dumps``), so every comment, blank line, the key order,
inline tables such as ``board_options`` and the quoting of untouched values stay as the user
wrote them; only the values that change are re-rendered. The result must pass the service's
own validation (:func:`ahrs_service.config.validate`) before anything is written, and it
replaces the old file atomically: a temporary file in the same folder, written and
``fsync``-ed, renamed over the old one, then the folder ``fsync``-ed, so a power cut leaves
either the old file or the new one, never a truncated one. The previous file is kept beside
it as ``<name>.bak``.

Writers: the calibration (``ahrs-service calibrate … --config FILE --write``, a ground station's
MAV_CMD_PREFLIGHT_CALIBRATION), both through :func:`ahrs_service.calibration.storage.save_calibration`.
:func:`render` (:func:`ahrs_service.core.settings.render`, re-exported here) renders a whole
configuration dict (``run --print-default``).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Mapping

import tomlkit
from tomlkit.exceptions import TOMLKitError

from ahrs_service import config as config_mod
from ahrs_service.core.settings import plain, render

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = ["render", "update_config_file"]


def update_config_file(
    path: str | os.PathLike, updates: Mapping[str, Mapping[str, Any]], *, backup: bool = True
) -> Path:
    """Sets ``updates`` ({section: {key: value}}) in the TOML file at ``path``, keeping the rest.

    An existing key keeps its place and its trailing comment; a new key is appended to its
    section; a missing section is appended to the file; a missing file is created. backup:
    copy the old file to ``<path>.bak`` first. Returns the path written. Raises
    :class:`ahrs_service.config.ConfigError` (one line naming the file) when the file is not
    valid TOML, a section is not a table, or the result would not load; the file is then
    untouched.
    """
    path = Path(path)
    existed = path.exists()
    try:
        doc = tomlkit.parse(path.read_text(encoding="utf-8")) if existed else tomlkit.document()
    except (TOMLKitError, UnicodeDecodeError) as exc:
        raise config_mod.ConfigError(f"{path}: not valid TOML, not rewritten: {exc}") from None
    for section, keys in updates.items():
        if section not in doc:
            doc.add(section, tomlkit.table())
        table = doc[section]
        if not isinstance(table, Mapping):
            raise config_mod.ConfigError(f"{path}: [{section}] is not a table, not rewritten")
        for key, value in keys.items():
            table[key] = plain(value)
    text = tomlkit.dumps(doc)
    # the service must be able to start from what we write: check before touching the file
    config_mod.validate(tomllib.loads(text))
    if existed and backup:
        shutil.copy2(path, path.with_name(path.name + ".bak"))
    _replace_atomically(path, text, keep_mode=existed)
    return path


def _replace_atomically(path: Path, text: str, *, keep_mode: bool) -> None:
    """Writes ``text`` to a temporary file beside ``path``, fsyncs it and renames it over ``path``."""
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        if keep_mode:
            shutil.copymode(path, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    # the rename itself is durable only once the folder's entry is on disk
    try:
        dir_fd = os.open(folder, os.O_RDONLY)
    except OSError:  # a folder that cannot be opened for reading: the rename stands anyway
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
