"""The MAVLink parameter protocol: a table of named values the service exposes.

The service registers each parameter with a getter and (for writable ones) a setter; this
module never stores values itself, so what a ground station reads is always what is in force.

Wire rules followed (https://mavlink.io/en/services/parameter.html):

* names are 1..16 ASCII characters; types are MAV_PARAM_TYPE_REAL32 or MAV_PARAM_TYPE_INT32;
* PARAM_REQUEST_LIST → every parameter as PARAM_VALUE with param_index/param_count;
* PARAM_REQUEST_READ → one PARAM_VALUE, by name, or by index when param_index ≥ 0;
* PARAM_SET → validated (finite, a normal float32 or 0 for REAL32, integral for INT32, within
  min/max, setter accepts) and
  applied; the answer is PARAM_VALUE with the value actually in force. A rejected set answers
  the unchanged value and a STATUSTEXT with the reason. A set to the value already in force
  (equal in the float32 the wire carries) is accepted without calling the setter: a ground
  station that writes back what it read changes nothing and leaves no record.

INT32 values travel as the float value by default ("C-cast" encoding, what ArduPilot and
MAVProxy use); integers are therefore limited to ±2²⁴, where a float32 is exact. The
"bytewise" encoding (PX4's: the int's bits reinterpreted as the float field) can be chosen per
table. The encoding in use is advertised in AUTOPILOT_VERSION capabilities.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Callable, Iterator

from ahrs_service.protocols.mavlink.dialect import mavlink

REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
INT32 = mavlink.MAV_PARAM_TYPE_INT32
FLT_MIN = 1.1754943508222875e-38  # smallest normal float32: a REAL32 below it (non-zero) is refused
FLT_MAX = 3.4028234663852886e38
INT32_EXACT_LIMIT = 1 << 24  # |n| up to 2**24 survives the float32 of C-cast encoding
C_CAST = "c_cast"
BYTEWISE = "bytewise"

Value = float | int


@dataclass
class Parameter:
    """One registered parameter. ``setter`` None means read-only."""

    name: str
    param_type: int
    getter: Callable[[], Value]
    setter: Callable[[Value], None] | None = None
    minimum: float | None = None
    maximum: float | None = None
    on_change: Callable[[str, Value], None] | None = None
    description: str = ""


@dataclass
class SetResult:
    """Outcome of a set: ``accepted``, the value in force afterwards, a reason if rejected,
    the value before (``old``) and whether the value in force changed."""

    accepted: bool
    value: Value
    reason: str = ""
    old: Value | None = None
    changed: bool = False


class ParameterTable:
    """Named parameters in registration order (that order is their param_index)."""

    def __init__(self, encoding: str = C_CAST) -> None:
        if encoding not in (C_CAST, BYTEWISE):
            raise ValueError(f"parameter encoding must be {C_CAST!r} or {BYTEWISE!r}, got {encoding!r}")
        self.encoding = encoding
        self._params: list[Parameter] = []
        self._index: dict[str, int] = {}

    # ------------------------------------------------------------------ registration
    def add(self, name: str, getter: Callable[[], Value], setter: Callable[[Value], None] | None = None, *,
            param_type: int | str = REAL32, minimum: float | None = None, maximum: float | None = None,
            on_change: Callable[[str, Value], None] | None = None, description: str = "") -> Parameter:
        """Registers a parameter.

        name: 1..16 ASCII characters, unique (MAVLink convention: upper case, e.g. ``AHRS_BETA``).
        param_type: MAV_PARAM_TYPE_REAL32 / MAV_PARAM_TYPE_INT32, or ``"REAL32"`` / ``"INT32"``.
        minimum, maximum: inclusive bounds checked on every PARAM_SET.
        on_change(name, new_value): called after a set that changed the value.
        """
        if isinstance(param_type, str):
            param_type = {"REAL32": REAL32, "INT32": INT32}.get(param_type.upper(), -1)
        if param_type not in (REAL32, INT32):
            raise ValueError(f"parameter {name!r}: type must be REAL32 or INT32")
        if not name or len(name) > 16 or not name.isascii() or "\x00" in name:
            raise ValueError(f"parameter name must be 1..16 ASCII characters, got {name!r}")
        if name in self._index:
            raise ValueError(f"parameter {name!r} is already registered")
        if minimum is not None and maximum is not None and minimum > maximum:
            raise ValueError(f"parameter {name!r}: minimum {minimum} > maximum {maximum}")
        p = Parameter(name, param_type, getter, setter, minimum, maximum, on_change, description)
        self._index[name] = len(self._params)
        self._params.append(p)
        return p

    def __len__(self) -> int:
        return len(self._params)

    def __contains__(self, name: object) -> bool:
        return name in self._index

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self._params)

    def names(self) -> list[str]:
        return [p.name for p in self._params]

    def index(self, name: str) -> int:
        return self._index[name]

    def get(self, name: str) -> Value:
        """Current value of ``name`` (from its getter)."""
        p = self._params[self._index[name]]
        return self._coerce(p, p.getter())

    # ------------------------------------------------------------------ setting
    def set(self, name: str, value: Value) -> SetResult:
        """Validates and applies ``value``; never raises for a bad value (see SetResult)."""
        if name not in self._index:
            raise KeyError(name)
        p = self._params[self._index[name]]
        reason = self._check(p, value)
        old = self.get(name)
        if not reason:
            # + 0.0: a PARAM_SET of -0.0 stores (and echoes) 0.0, not "-0" (RATE_ATT_HZ = -0 Hz)
            new = int(value) if p.param_type == INT32 else float(value) + 0.0
            if self._same_on_the_wire(p, new, old):
                return SetResult(True, old, old=old)
            try:
                p.setter(new)  # type: ignore[misc]  # _check rejected read-only parameters
            except (ValueError, TypeError) as exc:
                reason = f"refused: {exc}"
            else:
                now = self.get(name)
                if p.on_change is not None and now != old:
                    p.on_change(name, now)
                return SetResult(True, now, old=old, changed=now != old)
        return SetResult(False, self.get(name), reason, old=old)

    @staticmethod
    def _same_on_the_wire(p: Parameter, new: Value, old: Value) -> bool:
        """Whether ``new`` is the value in force as PARAM_VALUE carries it: a REAL32 read as
        float32 and written back (0.1 → 0.10000000149) is no change."""
        if p.param_type == INT32:
            return int(new) == int(old)
        return _float32(float(new)) == _float32(float(old))

    @staticmethod
    def _check(p: Parameter, value: Value) -> str:
        if p.setter is None:
            return "read-only"
        v = float(value)
        if not math.isfinite(v):
            return "not a finite number"
        if p.param_type == REAL32 and (abs(v) > FLT_MAX or 0.0 < abs(v) < FLT_MIN):
            return f"{v:g} outside the normal REAL32 range"
        if p.param_type == INT32 and v != round(v):
            return f"{v:g} is not an integer"
        if p.param_type == INT32 and not -(2**31) <= v <= 2**31 - 1:
            return f"{v:g} outside the INT32 range"
        if p.minimum is not None and v < p.minimum:
            return f"{v:g} below minimum {p.minimum:g}"
        if p.maximum is not None and v > p.maximum:
            return f"{v:g} above maximum {p.maximum:g}"
        return ""

    @staticmethod
    def _coerce(p: Parameter, value: Value) -> Value:
        return int(value) if p.param_type == INT32 else float(value)

    # ------------------------------------------------------------------ wire encoding
    def encode_value(self, p: Parameter) -> float:
        """The float for PARAM_VALUE.param_value of ``p`` under this table's encoding."""
        value = self.get(p.name)
        if p.param_type == INT32 and self.encoding == BYTEWISE:
            return struct.unpack("<f", struct.pack("<i", int(value)))[0]
        return float(value)

    def decode_value(self, p: Parameter, wire_value: float, wire_type: int) -> Value:
        """The value a PARAM_SET carries for ``p``; ``wire_type`` is the message's param_type."""
        if p.param_type == INT32 and self.encoding == BYTEWISE and wire_type == INT32:
            return struct.unpack("<i", struct.pack("<f", wire_value))[0]
        return float(wire_value)

    def param_value_message(self, p: Parameter) -> "mavlink.MAVLink_param_value_message":
        """PARAM_VALUE for ``p`` with its index and the table's count."""
        return mavlink.MAVLink_param_value_message(
            p.name.encode("ascii"), self.encode_value(p), p.param_type, len(self._params), self._index[p.name]
        )

    # ------------------------------------------------------------------ protocol messages
    def handle_request_list(self) -> list["mavlink.MAVLink_param_value_message"]:
        """PARAM_VALUE for every parameter, in index order."""
        return [self.param_value_message(p) for p in self._params]

    def handle_request_read(self, msg: "mavlink.MAVLink_param_request_read_message") -> list:
        """PARAM_VALUE of the requested parameter, or [] if there is no such parameter."""
        if msg.param_index >= 0:
            if msg.param_index >= len(self._params):
                return []
            return [self.param_value_message(self._params[msg.param_index])]
        name = _param_id(msg.param_id)
        if name not in self._index:
            return []
        return [self.param_value_message(self._params[self._index[name]])]

    def handle_set(self, msg: "mavlink.MAVLink_param_set_message") -> tuple[list, str, SetResult | None]:
        """(answers, rejection reason, outcome) for a PARAM_SET; answers is [] and the
        outcome None for an unknown name."""
        name = _param_id(msg.param_id)
        if name not in self._index:
            return [], f"unknown parameter {name}", None
        p = self._params[self._index[name]]
        result = self.set(name, self.decode_value(p, msg.param_value, msg.param_type))
        reason = "" if result.accepted else f"{name} rejected: {result.reason}"
        return [self.param_value_message(p)], reason, result


def _float32(x: float) -> float:
    """``x`` rounded to the nearest float32 (what a PARAM_VALUE carries); overflow is infinite."""
    try:
        return struct.unpack("<f", struct.pack("<f", x))[0]
    except OverflowError:
        return math.copysign(math.inf, x)


def _param_id(raw: str | bytes) -> str:
    # pymavlink hands char[16] fields over as str already cut at the first NUL
    if isinstance(raw, bytes):
        raw = raw.split(b"\x00", 1)[0].decode("ascii", errors="replace")
    return raw
