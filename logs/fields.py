"""Strict access to the fields of a decoded log message, for every reader of flight logs.

A flight log may come from anywhere: a foreign writer, a file edited by hand, a bit flipped
in a chunk written without CRC. The readers (``reader.read_log``, ``loss.log_losses``, the
quick-look ``plot``) take each field through these accessors, which check its JSON type
(``bool`` is no number, a string is no number, an integer must fit int64) instead of letting
``int()``/``float()`` coerce it or fail with a bare ``TypeError``. A field that is wrong
raises :class:`BadMessage` naming the field and what it holds; the reader turns that into
damage at that message (``logs/reader.py``), so a hostile file is reported, never a traceback.

Full JSON Schema validation (``schemas.validate``) costs many times the decoding; these
checks cost a few isinstance calls and so are done on every message.
"""

from __future__ import annotations

import math
from typing import Any

from ahrs_service.logs.schemas import decode

_INT64 = (-(1 << 63), (1 << 63) - 1)


class BadMessage(ValueError):
    """A decoded message that is not what its topic's schema says (``field``: its JSON path)."""

    def __init__(self, field: str, what: str) -> None:
        super().__init__(f"{field}: {what}")
        self.field = field


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return f"the number {value!r}"
    if isinstance(value, str):
        return f"the string {value[:40]!r}"
    if isinstance(value, list):
        return f"an array of {len(value)}"
    return "an object" if isinstance(value, dict) else type(value).__name__


def decoded(data: bytes) -> dict[str, Any]:
    """The message's JSON object; BadMessage when the bytes are no JSON or no object."""
    try:
        m = decode(data)
    except RecursionError:
        raise BadMessage("$", "JSON nested too deep") from None
    except ValueError as exc:
        raise BadMessage("$", f"not JSON ({str(exc).splitlines()[0][:80]})") from None
    if not isinstance(m, dict):
        raise BadMessage("$", f"expected an object, got {_kind(m)}")
    return m


def integer(m: dict[str, Any], key: str, *, optional: bool = False) -> int | None:
    """``m[key]`` as an int64 (None when absent or null and ``optional``)."""
    v = m.get(key)
    if v is None and optional:
        return None
    if key not in m:
        raise BadMessage(f"$.{key}", "missing")
    if not isinstance(v, int) or isinstance(v, bool) or not _INT64[0] <= v <= _INT64[1]:
        raise BadMessage(f"$.{key}", f"expected a 64-bit integer, got {_kind(v)}")
    return v


def number(value: Any, field: str) -> float:
    """A JSON number or null as float (null → NaN)."""
    if value is None:
        return math.nan
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise BadMessage(field, f"expected a number or null, got {_kind(value)}")
    return float(value)


def scalar(m: dict[str, Any], key: str) -> float:
    """``m[key]``, present, as a float (null → NaN)."""
    if key not in m:
        raise BadMessage(f"$.{key}", "missing")
    return number(m[key], f"$.{key}")


def vector(m: dict[str, Any], key: str, n: int, *, nullable: bool = False) -> list[float]:
    """``m[key]`` as ``n`` floats (null items → NaN; a null or absent vector → NaN×n when ``nullable``)."""
    v = m.get(key)
    if type(v) is list and len(v) == n and all(type(x) is float for x in v):
        return v  # what this project's writer writes: no copy, no call per item
    if v is None and nullable:
        return [math.nan] * n
    if key not in m:
        raise BadMessage(f"$.{key}", "missing")
    if not isinstance(v, list) or len(v) != n:
        raise BadMessage(f"$.{key}", f"expected an array of {n} numbers, got {_kind(v)}")
    return [number(x, f"$.{key}[{i}]") for i, x in enumerate(v)]


def numbers(m: dict[str, Any], key: str, n: int | None = None) -> list[float]:
    """``m[key]`` as a list of floats (null items → NaN), of length ``n`` when given."""
    v = m.get(key)
    if not isinstance(v, list) or (n is not None and len(v) != n):
        want = "numbers" if n is None else f"{n} numbers"
        raise BadMessage(f"$.{key}", f"expected an array of {want}, got {_kind(v)}")
    return [number(x, f"$.{key}[{i}]") for i, x in enumerate(v)]


def integers(m: dict[str, Any], key: str, n: int | None = None, *, optional: bool = False) -> list[int] | None:
    """``m[key]`` as a list of int64 (of length ``n`` when given; None when absent or null
    and ``optional``) — a block message's per-row times, flags."""
    v = m.get(key)
    if v is None and optional:
        return None
    if not isinstance(v, list) or (n is not None and len(v) != n):
        want = "integers" if n is None else f"{n} integers"
        raise BadMessage(f"$.{key}", f"expected an array of {want}, got {_kind(v)}")
    for i, x in enumerate(v):
        if not isinstance(x, int) or isinstance(x, bool) or not _INT64[0] <= x <= _INT64[1]:
            raise BadMessage(f"$.{key}[{i}]", f"expected a 64-bit integer, got {_kind(x)}")
    return v


def vectors(m: dict[str, Any], key: str, n: int, width: int, *, nullable: bool = False) -> list[list[float]]:
    """``m[key]`` as ``n`` rows of ``width`` floats (a block message's per-row vectors; null
    items → NaN; with ``nullable`` a null row, or a null or absent array, → NaN rows)."""
    v = m.get(key)
    if v is None and nullable:
        return [[math.nan] * width for _ in range(n)]
    if not isinstance(v, list) or len(v) != n:
        raise BadMessage(f"$.{key}", f"expected an array of {n} rows, got {_kind(v)}")
    out = []
    for i, row in enumerate(v):
        if row is None and nullable:
            out.append([math.nan] * width)
        elif type(row) is list and len(row) == width and all(type(x) is float for x in row):
            out.append(row)
        elif isinstance(row, list) and len(row) == width:
            out.append([number(x, f"$.{key}[{i}][{j}]") for j, x in enumerate(row)])
        else:
            raise BadMessage(f"$.{key}[{i}]", f"expected an array of {width} numbers, got {_kind(row)}")
    return out


def obj(m: dict[str, Any], key: str, *, optional: bool = False) -> dict[str, Any]:
    """``m[key]`` as an object ({} when absent or null and ``optional``)."""
    v = m.get(key)
    if v is None and optional:
        return {}
    if not isinstance(v, dict):
        raise BadMessage(f"$.{key}", f"expected an object, got {_kind(v)}")
    return v


def string(m: dict[str, Any], key: str, *, optional: bool = False) -> str | None:
    """``m[key]`` as a string (None when absent or null and ``optional``)."""
    v = m.get(key)
    if v is None and optional:
        return None
    if not isinstance(v, str):
        raise BadMessage(f"$.{key}", f"expected a string, got {_kind(v)}")
    return v
