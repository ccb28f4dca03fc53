"""Simulation clocks: where "now" comes from for the simulated sensors.

Both clocks count seconds from the start of the simulation. ``to_ns`` maps a simulation time
onto the host's monotonic nanosecond clock, which is what ``ImuSample.t_ns`` carries.
"""

from __future__ import annotations

import time


class MonotonicClock:
    """Real time: ``time.monotonic`` relative to the moment the clock was created."""

    def __init__(self) -> None:
        self._start_ns = time.monotonic_ns()

    def now(self) -> float:
        """Seconds since the clock was created."""
        return (time.monotonic_ns() - self._start_ns) * 1e-9

    def to_ns(self, t: float) -> int:
        """Host monotonic timestamp (ns) of simulation time ``t`` (s)."""
        return self._start_ns + int(round(t * 1e9))


class ManualClock:
    """A clock that only moves when told to: for tests and faster-than-real-time runs."""

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        """Current simulation time in seconds."""
        return self._t

    def advance(self, dt: float) -> float:
        """Moves the clock forward by ``dt`` seconds (≥ 0) and returns the new time."""
        if not dt >= 0.0:
            raise ValueError(f"dt must be >= 0 s, got {dt}")
        self._t += float(dt)
        return self._t

    def set(self, t: float) -> None:
        """Jumps to time ``t``; going backwards is refused (the clock is monotonic)."""
        if not t >= self._t:
            raise ValueError(f"ManualClock cannot go back from {self._t} s to {t} s")
        self._t = float(t)

    def to_ns(self, t: float) -> int:
        """Timestamp in ns of simulation time ``t``: the manual clock starts at 0 ns."""
        return int(round(t * 1e9))
