"""Checked settings: the pieces every configuration section is declared with.

A section is a table ``{"key": (default, checker)}``; a checker takes the key's dotted name and
the value read from TOML and returns the cleaned value or raises :class:`ConfigError`, one line
that starts with the key's name and says what is accepted. The factories below never let NaN
or ±inf through. Sections are declared by the parts that use them (the estimators, the MAVLink
protocol, the log writer …) and composed into one configuration by ``ahrs_service.config``.

:func:`render` writes such a configuration back out as TOML.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any, Callable, Mapping

import tomlkit


class ConfigError(ValueError):
    """A configuration problem; the message names the key and the accepted values."""


#: a checker: (dotted key, value) -> the cleaned value, or ConfigError
Checker = Callable[[str, Any], Any]
#: one declared key: its default and its checker
Key = tuple[Any, Checker]
#: a section (or a sub-table): key name -> declaration
Section = dict[str, Key]


def number(lo: float | None = None, hi: float | None = None, integer: bool = False) -> Checker:
    """A finite number (int or float; bool refused) in [lo, hi]; None leaves that side open."""
    def check(key: str, v: Any) -> Any:
        ok_type = isinstance(v, int) if integer else isinstance(v, (int, float))
        kind = "an integer" if integer else "a number"
        accepted = f"{kind} in [{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}]"
        if isinstance(v, bool) or not ok_type:
            raise ConfigError(f"{key}: {v!r} is not {kind}; accepted: {accepted}")
        if not math.isfinite(v):
            raise ConfigError(f"{key}: {v!r} is not a finite number; accepted: {accepted}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise ConfigError(f"{key}: {v!r} is out of range; accepted: {accepted}")
        return int(v) if integer else float(v)

    return check


def rate_or_off(hi: float, lo: float) -> Checker:
    """A rate, Hz: 0 (off) or a number in [lo, hi]."""
    in_range = number(0.0, hi)

    def check(key: str, v: Any) -> float:
        v = in_range(key, v)
        if 0.0 < v < lo:
            raise ConfigError(f"{key}: {v!r} is too slow; accepted: 0 (off) or a number in [{lo}, {hi}]")
        return v

    return check


def choice(options: tuple[str, ...]) -> Checker:
    """One of ``options``."""
    def check(key: str, v: Any) -> Any:
        if not isinstance(v, str) or v not in options:
            raise ConfigError(f"{key}: {v!r} is not one of {', '.join(options)}")
        return v

    return check


def string(key: str, v: Any) -> str:
    """Any string."""
    if not isinstance(v, str):
        raise ConfigError(f"{key}: expected a string, got {v!r}")
    return v


def boolean(key: str, v: Any) -> bool:
    """true or false."""
    if not isinstance(v, bool):
        raise ConfigError(f"{key}: expected true or false, got {v!r}")
    return v


def string_list(key: str, v: Any) -> list[str]:
    """A list of strings."""
    if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
        raise ConfigError(f"{key}: expected a list of strings, got {v!r}")
    return list(v)


def table(key: str, v: Any) -> dict:
    """Any table."""
    if not isinstance(v, dict):
        raise ConfigError(f"{key}: expected a table, got {v!r}")
    return dict(v)


def finite_table(key: str, v: Any) -> dict:
    """A table whose numbers are all finite (estimator parameters, board options)."""
    v = table(key, v)
    for k, x in v.items():
        if isinstance(x, float) and not math.isfinite(x):
            raise ConfigError(f"{key}.{k}: {x!r} is not a finite number")
    return v


def vector3(lo: float, hi: float) -> Checker:
    """Three finite numbers, each in [lo, hi]."""
    in_range = number(lo, hi)

    def check(key: str, v: Any) -> list[float]:
        if not isinstance(v, list) or len(v) != 3:
            raise ConfigError(f"{key}: {v!r} is not a list of 3 numbers; accepted: 3 numbers in [{lo}, {hi}]")
        return [in_range(f"{key}[{i}]", x) for i, x in enumerate(v)]

    return check


def optional(check: Checker) -> Checker:
    """``check``, or unset (None)."""
    return lambda key, v: None if v is None else check(key, v)


def file_path(must_exist: bool = False) -> Checker:
    """A path string; with ``must_exist`` an empty string is allowed (unset) but a given path must
    exist (cross-key rules decide when an empty one is an error)."""
    def check(key: str, v: Any) -> str:
        v = string(key, v)
        if "\x00" in v:
            raise ConfigError(f"{key}: {v!r} contains a NUL character; accepted: a file path")
        if must_exist and v and not Path(v).exists():
            raise ConfigError(f"{key}: {v!r} does not exist; accepted: an existing file")
        return v

    return check


def directory(key: str, v: Any) -> str:
    """A folder to write into: a non-empty path (made if missing; one that cannot be written
    is the writer's to report and retry at run time, the service runs on meanwhile)."""
    v = file_path()(key, v)
    if not v.strip():
        raise ConfigError(f"{key}: {v!r} is empty; accepted: a folder path (e.g. \"flight-logs\")")
    return v


def check_keys(prefix: str, keys: Section, given: dict[str, Any], out: dict[str, Any]) -> None:
    """Each key of ``given`` through its checker in ``keys`` into ``out`` (a section, or a
    sub-table of :func:`subtable`); an unknown key names the accepted ones."""
    for key, value in given.items():
        if key not in keys:
            raise ConfigError(f"{prefix}.{key}: unknown key; accepted keys: {', '.join(keys)}")
        out[key] = keys[key][1](f"{prefix}.{key}", value)


def defaults_of(keys: Section) -> dict[str, Any]:
    """The defaults of a section, copied (a list default is not shared between configurations)."""
    return {k: copy.deepcopy(d) for k, (d, _) in keys.items()}


def subtable(keys: Section) -> Checker:
    """A sub-table (``[section.key]``) with keys of its own, declared like a section's."""
    def check(key: str, v: Any) -> dict:
        out = defaults_of(keys)
        check_keys(key, keys, table(key, v), out)
        return out

    return check


def short(value: str, limit: int = 80) -> str:
    """``repr(value)``, cut to about ``limit`` characters (a 5000-character path in an error)."""
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit - 5]}…{text[-4:]} ({len(value)} characters)"


def unreadable(exc: OSError) -> str:
    """What is wrong with a path that could not be read, as a phrase after its name."""
    if isinstance(exc, FileNotFoundError):
        return "does not exist"
    if isinstance(exc, IsADirectoryError):
        return "is a directory, not a file"
    if isinstance(exc, PermissionError):
        return "is not readable: permission denied"
    return f"cannot be read: {exc.strerror or exc}"


def plain(value: Any) -> Any:
    """``value`` as TOML's own types: numpy arrays and scalars become lists and floats."""
    if isinstance(value, Mapping):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if hasattr(value, "tolist"):  # numpy array or scalar
        return plain(value.tolist())
    return value


def render(cfg: Mapping[str, Mapping[str, Any]]) -> str:
    """A TOML document of a configuration dict ({section: {key: value}}); a key whose value is
    None (not set) becomes a comment ``# key = (not set)``, a dict a sub-table."""
    doc = tomlkit.document()
    for section, keys in cfg.items():
        toml_table = tomlkit.table()
        for key, value in keys.items():
            if value is None:
                toml_table.add(tomlkit.comment(f"{key} = (not set)"))
            else:
                toml_table.add(key, plain(value))
        doc.add(section, toml_table)
    return tomlkit.dumps(doc)
