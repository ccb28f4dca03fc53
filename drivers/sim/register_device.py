"""The base of every simulated twin: a register file behind the part's sub-address rules,
latched from the simulator's physics at the part's output data rate.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from typing import Any

import numpy as np


def _with_period(physics: Callable[..., dict]) -> Callable[[float, float], dict]:
    """``physics(t, period)``: the simulator's readings at t for a part sampling every
    ``period`` s. A simulator that takes ``period=`` (``SimulatedImu``) draws each reading's
    noise over the reading part's own sampling band, so two parts whose sample grids almost
    coincide do not make each other's readings noisier; a plain ``physics(t)`` is called as is."""
    try:
        takes_period = "period" in inspect.signature(physics).parameters
    except (TypeError, ValueError):
        takes_period = False
    if takes_period:
        return lambda t, period: physics(t, period=period)
    return lambda t, period: physics(t)


def to_counts(value: float, lsb: float, lo: int, hi: int) -> int:
    """A physical value quantised to counts of size ``lsb`` and clipped to [lo, hi]."""
    c = value / lsb
    if not math.isfinite(c):
        return hi if c > 0 else lo
    c = int(round(c))
    return lo if c < lo else hi if c > hi else c


def counts_array(values: np.ndarray, lsb: float, lo: int, hi: int) -> np.ndarray:
    """:func:`to_counts` element-wise over an array: int64 counts, the same rounding (half to
    even, as Python's ``round``) and clipping; +inf → ``hi``, −inf and NaN → ``lo``."""
    c = np.asarray(values, dtype=float) / lsb
    out = np.clip(np.rint(c), lo, hi)
    out[np.isnan(c)] = lo
    return out.astype(np.int64)


def i16_bytes(v: int, big_endian: bool) -> tuple[int, int]:
    """Two's-complement 16-bit value as (first byte, second byte) in the given order."""
    v &= 0xFFFF
    return ((v >> 8, v & 0xFF) if big_endian else (v & 0xFF, v >> 8))


class SimulatedRegisterDevice:
    """Base of the simulated twins: a register file, the part's pointer rules, ODR latching.

    source: the simulator (an object with ``physics(t) -> dict`` such as ``SimulatedImu``,
    or a plain callable ``t -> dict``) giving "gyr" rad/s, "acc" m/s² specific force, "mag"
    µT (all (3,) in the board's axes), optionally "temperature_c" and "truth".

    Subclasses set ``POWER_ON`` (register → value), ``WRITABLE`` (registers the host may
    write), override :meth:`rate_hz` (current output data rate or None when not measuring),
    :meth:`latch` (physics → data registers) and the hooks :meth:`on_write` /
    :meth:`on_read`. ``ST_SUBADDRESS`` selects ST's rule: auto-increment only when the MSB
    of the sub-address is set.
    """

    PART = "simulated device"
    DEFAULT_ADDRESS = 0x00
    #: the simulated unit's oscillator error (+0.007 = 0.7 % fast); 0 for parts polled on
    #: the host's clock, a documented 0.5–2 % on every part read through its FIFO
    CLOCK_ERROR = 0.0
    POWER_ON: dict[int, int] = {}
    WRITABLE: frozenset[int] = frozenset()
    ST_SUBADDRESS = False

    def __init__(self, source: Any = None, address: int | None = None) -> None:
        self.address = self.DEFAULT_ADDRESS if address is None else int(address)
        #: the source's ``physics_block(t, period)`` when it has one (``SimulatedImu``): a
        #: FIFO burst's readings in one call (see :meth:`latch_run`)
        self._physics_block: Callable[[np.ndarray, float], Any] | None = None
        if source is None:
            self._physics: Callable[[float, float], dict] | None = None
        else:
            physics = getattr(source, "physics", source)
            if not callable(physics):
                raise TypeError(f"{self.PART}: source needs physics(t) -> dict, got {source!r}")
            self._physics = _with_period(physics)
            self._physics_block = getattr(source, "physics_block", None)
        self.regs = bytearray(256)
        self.latched: dict | None = None  # physics dict of the sample now in the data registers
        self.latched_t: float | None = None
        self.samples_latched = 0
        self._t0: float | None = None  # start of the measurement schedule
        self._k = 0  # index of the last latched (or skipped) sample
        #: the part's oscillator error: it samples at (1 + clock_error) × its nominal rate
        #: (real parts run 0.5–2 % off; the sensor clock recovery must find the true rate).
        #: Each FIFO twin's default is its class's CLOCK_ERROR (a documented unit's error)
        self.clock_error = float(self.CLOCK_ERROR)
        self.power_on_reset(0.0)

    # ----------------------------------------------------------------- state
    def power_on_reset(self, now: float) -> None:
        """Registers to power-on values, measurement stopped (a power cycle)."""
        self.regs[:] = bytes(256)
        for r, v in self.POWER_ON.items():
            self.regs[r] = v
        self.latched = None
        self.latched_t = None
        self._t0 = None
        self.reset_state(now)

    def reset_state(self, now: float) -> None:
        """Extra per-part state to clear on power-on (hook)."""

    def restart_measurement(self, now: float) -> None:
        """(Re)starts the output schedule: samples at now + k / rate, k = 1, 2, …"""
        self._t0 = now
        self._k = 0

    def stop_measurement(self) -> None:
        self._t0 = None

    @property
    def samples_due(self) -> int:
        """Samples the part has produced since its measurement last (re)started: latched,
        overrun or dropped by a full FIFO alike (the twin's own count, for tests)."""
        return self._k

    @property
    def measuring(self) -> bool:
        """True while the part produces samples (configured and powered up)."""
        return self._t0 is not None and bool(self.rate_hz())

    def rate_hz(self) -> float | None:
        """Output data rate from the current configuration, or None when not measuring."""
        return None

    def sampling_rate_hz(self) -> float | None:
        """The rate the part really samples at: the configured one off by ``clock_error``."""
        rate = self.rate_hz()
        return rate * (1.0 + self.clock_error) if rate else None

    def locked(self) -> bool:
        """True while the part holds its output registers (no new data placed)."""
        return False

    def update(self, now: float) -> None:
        """Latches the newest sample due by ``now`` (older due samples are overrun/skipped)."""
        if self._t0 is None:
            return
        rate = self.sampling_rate_hz()
        if not rate:
            return
        # the tiny epsilon keeps a clock stepped exactly on the sample grid on the right side
        k = math.floor((now - self._t0) * rate + 1e-7)
        if k <= self._k or self.locked():
            return
        room = self.fifo_room()
        if room is not None:
            self._update_fifo(k, rate, room)
            return
        skipped = k - self._k - 1
        self._k = k
        t = self._t0 + k / rate
        phys = self._physics(t, 1.0 / rate) if self._physics is not None else _ZERO_PHYSICS
        self.latched, self.latched_t = phys, t
        self.samples_latched += 1
        self.latch(phys, t, skipped)

    def _update_fifo(self, k: int, rate: float, room: int) -> None:
        """A part with its FIFO on takes every due sample in order: the ones that fit (plus
        one, so the part sees its own overflow) are latched; the rest are overflowed, the
        oldest or the newest ones as the part's FIFO mode keeps (:meth:`fifo_keeps_oldest`),
        without computing them. The one FIFO latching of every twin (I2C and SPI parts)."""
        due = k - self._k
        push = min(due, room + 1)
        first = self._k + 1 if self.fifo_keeps_oldest() else k - push + 1
        if due > push:
            self.fifo_dropped(due - push)
        self.latch_run(self._t0 + np.arange(first, first + push) / rate, 1.0 / rate)
        self._k = k

    def latch_run(self, t: np.ndarray, period: float) -> None:
        """Latches the samples at the ascending times ``t`` (s) one after the other, as a
        FIFO takes them (:meth:`latch` each). Hook: a twin may latch the run at once from
        the source's ``physics_block`` (the MPU-9250's does), with the same registers,
        bytes and FIFO behaviour."""
        for x in t.tolist():
            phys = self._physics(x, period) if self._physics is not None else _ZERO_PHYSICS
            self.latched, self.latched_t = phys, x
            self.samples_latched += 1
            self.latch(phys, x, 0)

    def fifo_room(self) -> int | None:
        """Frames the FIFO can still take, or None while the FIFO is off (hook: FIFO parts)."""
        return None

    def fifo_keeps_oldest(self) -> bool:
        """True when a full FIFO refuses new samples, False when it overwrites the oldest."""
        return True

    def fifo_dropped(self, n: int) -> None:
        """``n`` samples did not fit in the FIFO (hook: count them, set the overrun flag)."""

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        """Writes one sample into the data registers and sets the status bits (hook)."""

    # ----------------------------------------------------------------- bus side
    def decode_subaddress(self, sub: int) -> tuple[int, bool]:
        """(register, auto-increment) from the sub-address byte sent by the host."""
        if self.ST_SUBADDRESS:
            return sub & 0x7F, bool(sub & 0x80)
        return sub, True

    def next_pointer(self, reg: int) -> int:
        """Register after ``reg`` in a burst (parts with wrapping pointers override)."""
        return (reg + 1) & 0xFF

    def bus_read(self, sub: int, n: int, now: float) -> list[int]:
        """A read transaction of ``n`` bytes from sub-address ``sub`` at time ``now``."""
        self.update(now)
        reg, inc = self.decode_subaddress(sub)
        out = []
        touched = []
        for _ in range(n):
            out.append(self.read_register(reg))
            touched.append(reg)
            if inc:
                reg = self.next_pointer(reg)
        self.on_read(touched, now)
        return out

    def read_register(self, reg: int) -> int:
        return self.regs[reg]

    def bus_write(self, sub: int, data: list[int], now: float) -> None:
        """A write transaction of ``data`` starting at sub-address ``sub``."""
        self.update(now)
        reg, inc = self.decode_subaddress(sub)
        for value in data:
            if reg in self.WRITABLE:
                old = self.regs[reg]
                self.regs[reg] = value
                self.on_write(reg, value, old, now)
            if inc:
                reg = self.next_pointer(reg)

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        """Side effects of a host write (start/stop measuring, resets) (hook)."""

    def on_read(self, regs: list[int], now: float) -> None:
        """Side effects of reading ``regs`` in one transaction (clear flags) (hook)."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(0x{self.address:02X})"


_ZERO_PHYSICS: dict = {"gyr": (0.0, 0.0, 0.0), "acc": (0.0, 0.0, 0.0),
                       "mag": (0.0, 0.0, 0.0), "temperature_c": 25.0}
