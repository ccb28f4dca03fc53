"""What every I2C sensor driver shares, and the base of their simulated twins.

:class:`I2CDevice` is the driver side: register access with a retry policy (transient
``OSError`` retried, every failure and retry counted in a :class:`SourceDiagnostics`), the
identity check, burst reads, counts → SI conversion and the saturation test.

:class:`SimulatedRegisterDevice` is the part side: a 256-byte register file behind the
part's sub-address rules (auto-increment, pointer wrap), whose data registers are latched
from the simulator's physics at the configured output data rate on the bus clock.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ahrs_service.drivers.base import SourceDiagnostics
from ahrs_service.drivers.i2c.bus import SMBUS_BLOCK_MAX, I2CBus

#: standard gravity: accelerometer counts are in g
STANDARD_GRAVITY = 9.80665
DEG2RAD = math.pi / 180.0


class I2CDeviceError(OSError):
    """A device did not answer (or kept failing) after the retries: names bus, address, register."""

    def __init__(self, bus: str, address: int, part: str, register: int, action: str,
                 cause: OSError):
        self.bus, self.address, self.part, self.register = bus, address, part, register
        self.cause = cause
        super().__init__(
            cause.errno,
            f"{part} at {bus} address 0x{address:02X}: {action} register 0x{register:02X} "
            f"failed: {cause.strerror or cause}",
        )


class DeviceIdentityError(RuntimeError):
    """The device at an address is not the expected part (identity register mismatch)."""

    def __init__(self, bus: str, address: int, part: str, register: int, read: bytes,
                 expected: Sequence[bytes], what: str):
        self.bus, self.address, self.part, self.register = bus, address, part, register
        self.read, self.expected = read, list(expected)
        exp = " or ".join(_hex(e) for e in expected)
        super().__init__(
            f"{bus} address 0x{address:02X}: expected {part}, but {what} (register "
            f"0x{register:02X}) reads {_hex(read)}, expected {exp} — another part at this "
            f"address, or a wrong address/board setting?"
        )


def run_retried(call: Callable[[], Any], retries: int, diagnostics: SourceDiagnostics,
                error: Callable[[OSError], OSError]) -> Any:
    """The one retry policy of every register transfer (I2C parts and the I2C/SPI transports):
    ``call()`` is repeated on a transient ``OSError`` up to ``retries`` times; every failure is
    counted in ``diagnostics.bus_errors`` (and each repeat in ``retries``), ``last_error`` holds
    ``error(exc)``'s message, which is raised (from the cause) when the retries are spent."""
    attempt = 0
    while True:
        try:
            return call()
        except OSError as exc:
            diagnostics.bus_errors += 1
            err = error(exc)
            diagnostics.last_error = str(err)
            if attempt >= retries:
                raise err from exc
            attempt += 1
            diagnostics.retries += 1


def _hex(b: bytes) -> str:
    return " ".join(f"0x{x:02X}" for x in b)


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


class I2CDevice:
    """Driver base: one part at one address on one bus.

    retries: how many times a failed transfer is repeated before :class:`I2CDeviceError`.
    diagnostics: counters shared with the board (``bus_errors``, ``retries``, ``last_error``).

    Subclasses set ``PART`` (name for messages), ``DEFAULT_ADDRESS``, and after
    :meth:`configure` the conversion ``scale`` ((3,) SI units per count, sensor axes) and
    ``full_scale`` (counts at or beyond which an axis is saturated).
    """

    PART = "I2C device"
    DEFAULT_ADDRESS = 0x00
    #: sub-address bit that requests auto-increment (0x80 on ST parts, none elsewhere)
    AUTO_INCREMENT_FLAG = 0x00

    def __init__(self, bus: I2CBus, address: int | None = None, *,
                 diagnostics: SourceDiagnostics | None = None, retries: int = 2) -> None:
        self.bus = bus
        self.address = self.DEFAULT_ADDRESS if address is None else int(address)
        if not 0x03 <= self.address <= 0x77:
            raise ValueError(f"{self.PART}: I2C address 0x{self.address:02X} is outside 0x03..0x77")
        if retries < 0:
            raise ValueError(f"{self.PART}: retries must be >= 0, got {retries}")
        self.diagnostics = diagnostics if diagnostics is not None else SourceDiagnostics()
        self.retries = int(retries)
        self.scale = np.ones(3)
        self.full_scale = 32767

    # ---------------------------------------------------------------- transfers
    def _transfer(self, fn: Callable[..., Any], reg: int, action: str, *args: Any) -> Any:
        """Runs one bus call, retrying transient OSErrors; all failures are counted."""
        # messages name the register as in the datasheet, without ST's increment flag
        return run_retried(lambda: fn(self.address, reg, *args), self.retries, self.diagnostics,
                           lambda exc: I2CDeviceError(self.bus.name, self.address, self.PART,
                                                      reg & ~self.AUTO_INCREMENT_FLAG, action, exc))

    def read_u8(self, reg: int) -> int:
        """One register byte (retried)."""
        return self._transfer(self.bus.read_byte_data, reg, "reading")

    def write_u8(self, reg: int, value: int) -> None:
        """Writes one register byte (retried)."""
        self._transfer(self.bus.write_byte_data, reg, "writing", value)

    def read_block(self, reg: int, n: int) -> list[int]:
        """``n`` bytes from ``reg`` in one burst (retried); ``reg`` includes any auto-increment
        bit. Up to 32 bytes an SMBus block, longer a plain I2C read (``bus.max_read_bytes``)."""
        if n <= SMBUS_BLOCK_MAX:
            return self._transfer(self.bus.read_i2c_block_data, reg, "reading", n)
        return self._transfer(self.bus.read_burst, reg, "reading", n)

    def read_fifo_frames(self, fifo: "FifoLayout", frames: int) -> bytes:
        """``frames`` whole FIFO frames popped from ``fifo.data_register``, oldest first, in as
        few transfers as the part and the bus allow (see :class:`FifoLayout`); each transfer
        retried."""
        per = fifo.frames_per_transfer
        total = frames * fifo.frame_bytes
        if per == 0:  # a byte stream: any split, the bus's longest reads
            step = self.bus.max_read_bytes
        else:
            step = per * fifo.frame_bytes
        out = bytearray()
        while len(out) < total:
            out += bytes(self.read_block(fifo.data_register, min(step, total - len(out))))
        return bytes(out)

    def write_verified(self, reg: int, value: int, what: str) -> None:
        """Writes a configuration byte and reads it back; a mismatch means a wrong part."""
        self.write_u8(reg, value)
        got = self.read_u8(reg)
        if got != value:
            raise DeviceIdentityError(self.bus.name, self.address, self.PART, reg, bytes([got]),
                                      [bytes([value])], f"{what} read back after writing")

    def check_identity(self, reg: int, expected: bytes | Sequence[bytes], what: str) -> bytes:
        """Reads ``len(expected)`` identity bytes from ``reg`` and compares.

        expected: one byte string, or a list of accepted alternatives of equal length.
        Raises :class:`DeviceIdentityError` (wrong part) or :class:`I2CDeviceError` (nothing
        answers), both naming bus, address and register.
        """
        options = [expected] if isinstance(expected, (bytes, bytearray)) else list(expected)
        n = len(options[0])
        got = bytes(self.read_block(reg, n) if n > 1 else [self.read_u8(reg)])
        if got not in options:
            raise DeviceIdentityError(self.bus.name, self.address, self.PART, reg, got, options, what)
        return got

    # ---------------------------------------------------------------- conversion
    def configure(self) -> None:
        """Checks the identity and writes the configuration (called again after a loss)."""
        raise NotImplementedError

    def to_si(self, counts: Sequence[int]) -> np.ndarray:
        """(3,) float64 in SI units (sensor axes) from (3,) raw counts."""
        return np.multiply(counts, self.scale)

    @property
    def resolution(self) -> float:
        """Size of one output step in SI units (largest axis): the quantisation of a reading."""
        return float(np.max(self.scale))

    def is_saturated(self, counts: Sequence[int]) -> bool:
        """True when any axis is at or beyond the rated full scale (reading not trustworthy)."""
        fs = self.full_scale
        return counts[0] >= fs or counts[0] <= -fs or counts[1] >= fs or counts[1] <= -fs \
            or counts[2] >= fs or counts[2] <= -fs

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.bus.name}, 0x{self.address:02X})"


# ============================================================================ FIFO


@dataclass(frozen=True, slots=True)
class FifoLayout:
    """How a part's FIFO is read (from its datasheet).

    depth_frames: frames the FIFO holds (e.g. 32 on the ST parts and the ADXL345, 512 bytes
        / 12 = 42 accelerometer + gyroscope frames on the MPU-9250).
    frame_bytes: bytes of one sample in the FIFO.
    data_register: sub-address a burst reads from (with any auto-increment flag).
    frames_per_transfer: whole frames one transfer may carry (the ADXL345 pops one entry per
        multi-byte read of DATAX0…DATAZ1: 1), or 0 for a plain byte stream that may be split
        anywhere (the MPU-9250's FIFO_R_W: one read of everything on a plain-I2C adapter,
        32-byte SMBus blocks on an SMBus-only one).
    """

    depth_frames: int
    frame_bytes: int
    data_register: int
    frames_per_transfer: int = 0

    def transfers(self, frames: int, max_read_bytes: int = SMBUS_BLOCK_MAX) -> int:
        """How many bus transfers reading ``frames`` frames takes on a bus whose longest read
        is ``max_read_bytes`` (``I2CBus.max_read_bytes``)."""
        if frames <= 0:
            return 0
        if self.frames_per_transfer == 0:
            return -(-frames * self.frame_bytes // max_read_bytes)
        return -(-frames // self.frames_per_transfer)


@dataclass(frozen=True, slots=True)
class FifoStatus:
    """One read of a FIFO's status: ``level`` frames waiting, ``overflow`` (the part has
    overwritten or dropped samples since the last reset), ``level_read_ns``: the host time
    (ns) at which the transfer that read the level began — the part latches its level while
    that transfer runs, so the newest counted sample is at most its address phase younger:
    the sensor clock's anchor."""

    level: int
    overflow: bool
    level_read_ns: int


def watermark_frames(rate_hz: float, wakeup_hz: float, depth_frames: int) -> int:
    """FIFO watermark (frames) for draining at ``wakeup_hz``: rate/wake-up rounded, clipped to
    1 … depth − 1 (a watermark at the full depth would leave no room for a late read)."""
    if not wakeup_hz > 0:
        raise ValueError(f"fifo wake-up rate must be > 0 Hz, got {wakeup_hz}")
    return min(max(1, int(round(rate_hz / wakeup_hz))), depth_frames - 1)


# ============================================================================ simulation


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
