"""The queue records of the flight-log writer: one small class per message kind.

The service's thread fills them in :class:`~ahrs_service.logs.writer.FlightLogWriter`'s
``write_*`` methods and the writer thread hands each to its encoder
(:mod:`ahrs_service.logs.encoders`). They hold plain Python values (lists, not arrays) or
copies of the caller's arrays: the caller may reuse its own at once.

:data:`CARRIES` says how many messages and samples a record turns into, so that the queue
(a full one refuses a record) and the files (a failing disk loses one) count the same
"not logged".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np


@dataclass(slots=True)
class Raw:
    """One /imu/raw sample."""

    t_ns: int
    row: list  # the sample row [gx, gy, gz, ax, ay, az, mx, my, mz, dt]
    flags: int
    raw: Any
    temperature: float | None
    index: int  # the sample's number since the writer started


@dataclass(slots=True)
class Attitude:
    """One /attitude estimate (and /tf at its rate)."""

    t_ns: int
    q: list  # q_earth←body [w, x, y, z]
    estimator: str
    bias: list | None  # rad/s, body frame
    diagnostics: dict | None


@dataclass(slots=True)
class Sample:
    """/imu/raw + /attitude (+ /attitude/truth) of one sample: the service's per-sample entry."""

    t_ns: int
    row: list
    flags: int
    raw: Any
    temperature: float | None
    index: int
    q: list
    estimator: str
    bias: list | None
    truth_q: list | None
    diagnostics: dict | None  # the estimator's, at the service's diagnostics rate; else None


@dataclass(slots=True)
class Block:
    """The samples of one block and their estimates: the service's one entry per burst.
    Written as /imu/raw + /attitude (+ /attitude/truth) per row, or, when ``one_message``,
    as one /imu/raw_block + /attitude_block (+ /attitude/truth_block). The arrays are the
    caller's, copied (the caller may reuse its own at once)."""

    t_ns: np.ndarray  # (n,) int64 recovered sample times, ns
    t_source_ns: np.ndarray | None  # (n,) the source's own stamps, ns
    rows: np.ndarray  # (n, 10) float64 sample rows as fed to the estimator
    flags: np.ndarray  # (n,)
    raw: dict | None  # {name: (n, …) array} driver counts
    temperature: np.ndarray | None  # (n,) °C, NaN where unknown (encode writes null)
    first_index: int
    q: np.ndarray  # (n, 4)
    estimator: str
    bias: list | None  # after the last row, rad/s body FRD: written with the last row only
    truth_q: np.ndarray | None  # (n, 4)
    diagnostics: dict | None  # the estimator's after the last row, at the diagnostics rate
    one_message: bool  # the samples come faster than block_messages_above_hz: block channels


@dataclass(slots=True)
class Truth:
    """One /attitude/truth ground-truth attitude."""

    t_ns: int
    q: list
    movement: bool | None
    source: str


@dataclass(slots=True)
class Loop:
    """The scheduler's statistics for /loop."""

    t_ns: int
    stats: dict


@dataclass(slots=True)
class Config:
    """The effective configuration for /config (a deep copy, JSON values only)."""

    t_ns: int
    config: dict
    reason: str


@dataclass(slots=True)
class ParamChange:
    """A live parameter change for /params."""

    t_ns: int
    sample_index: int
    name: str
    old: Any
    new: Any
    source: str


@dataclass(slots=True)
class Mavlink:
    """MAVLink traffic counters for /mavlink."""

    t_ns: int
    counters: dict


@dataclass(slots=True)
class AutopilotAttitude:
    """The autopilot's attitude and its disagreement with ours: an attitude_monitor.Disagreement
    (frozen, so queued as it is, not copied field by field)."""

    d: Any


@dataclass(slots=True)
class Timesync:
    """The autopilot's clock estimate after one accepted TIMESYNC sample: a
    timesync.TimesyncStatus (frozen, so queued as it is)."""

    status: Any


@dataclass(slots=True)
class Log:
    """A health event for /log (foxglove.Log)."""

    t_ns: int
    severity: int  # MAVLink's, 0 emergency … 7 debug
    text: str


@dataclass(slots=True)
class StateSnapshot:
    """The estimator state after the sample at ``t_ns``: the first message of a rotated file."""

    t_ns: int
    state: list
    estimator: str
    next_index: int  # number of the first sample the new file holds


@dataclass(slots=True)
class NewFile:
    """Finish the current file; the next message starts a new one."""


@dataclass(slots=True)
class Close:
    """The last record: the writer thread finishes the file and stops."""


#: messages and samples (/imu/raw rows) each record kind carries, for what a full queue or a
#: failing disk loses (the queue and the files both count from here); kinds not listed
#: carry one message and no sample
CARRIES: dict[type, Callable[[Any], tuple[int, int]]] = {
    Raw: lambda item: (1, 1),
    Sample: lambda item: (2 + (item.truth_q is not None), 1),
    Block: lambda item: ((1 if item.one_message else len(item.t_ns)) * (2 + (item.truth_q is not None)),
                         len(item.t_ns)),
    AutopilotAttitude: lambda item: (3, 0),  # /autopilot/attitude, /tf, /monitor
}


def carried(item: Any) -> tuple[int, int]:
    """(messages, samples) of one queue record."""
    count = CARRIES.get(type(item))
    return (1, 0) if count is None else count(item)
