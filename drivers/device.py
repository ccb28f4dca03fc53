"""The one driver base of every register part, over I2C or SPI alike.

:class:`RegisterDevice` is one part behind a
:class:`~ahrs_service.drivers.transport.RegisterTransport`, and every part's driver
(``drivers/parts/``) reaches its registers through it alone: register access with the one
retry policy (a transient ``OSError`` retried, every failure and retry counted in a
:class:`SourceDiagnostics`), block reads, FIFO reads in transfers the part and the bus can
carry, verified writes, identity checks of one or more bytes, counts → SI conversion and the
saturation test. What is particular to a bus (SMBus blocks, plain-I2C reads, SPI's read bit
and dummy bytes) is the transport's.

:class:`I2CDevice` builds the same base for the parts that live on I2C only (the source
papers' boards and the MPU-9250) from a bus and an address: it is the base over an
:class:`~ahrs_service.drivers.transport.I2CTransport`.

Errors (``drivers/errors.py``, importable from here too): a transfer that keeps failing
raises the transport's :class:`TransportError` (:class:`I2CDeviceError` on I2C), a part
that is not the expected one :class:`PartIdentityError` (a :class:`DeviceIdentityError`).

Also here: how a part's FIFO is read (:class:`FifoLayout`, :class:`FifoStatus`,
:func:`watermark_frames`) and the unit constants the parts' scales are built from.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ahrs_service.core.samples import SourceDiagnostics
from ahrs_service.drivers.buses.i2c import SMBUS_BLOCK_MAX, I2CBus

# the errors have their own module (the transports raise them); they import from here as before
from ahrs_service.drivers.errors import (  # noqa: F401
    HINT_ANY_BUS,
    HINT_I2C_ONLY,
    DeviceIdentityError,
    I2CDeviceError,
    PartIdentityError,
    TransportError,
)
from ahrs_service.drivers.transport import I2CTransport, RegisterTransport

#: standard gravity: accelerometer counts are in g
STANDARD_GRAVITY = 9.80665
DEG2RAD = math.pi / 180.0


def run_retried(call: Callable[[], Any], retries: int, diagnostics: SourceDiagnostics,
                error: Callable[[OSError], OSError]) -> Any:
    """The one retry policy of every register transfer: ``call()`` is repeated on a transient
    ``OSError`` up to ``retries`` times; every failure is counted in
    ``diagnostics.bus_errors`` (and each repeat in ``retries``), ``last_error`` holds
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


def _identity_options(expected: int | bytes | Sequence[int] | Sequence[bytes]) -> list[bytes]:
    """The accepted identities as byte strings of one length: one byte string (e.g. b"H43"),
    alternatives as byte strings, or alternatives of one byte as ints."""
    if isinstance(expected, (bytes, bytearray)):
        return [bytes(expected)]
    if isinstance(expected, int):
        return [bytes((expected,))]
    return [bytes((e,)) if isinstance(e, int) else bytes(e) for e in expected]


class RegisterDevice:
    """Driver base: one part behind a :class:`RegisterTransport` (I2C or SPI), with retries
    and counters.

    retries: how many times a failed transfer is repeated before the transport's
    :class:`TransportError`.
    diagnostics: counters shared with the board (``bus_errors``, ``retries``, ``last_error``).

    Subclasses set ``PART`` (name for messages); registers are read with :meth:`read_u8` /
    :meth:`read_regs` (FIFOs with :meth:`read_fifo` or :meth:`read_fifo_frames`), written with
    :meth:`write_u8` (:meth:`write_verified` for a part without an identity register). A part
    that converts counts sets, in :meth:`configure`, ``scale`` (SI units per count, sensor
    axes) and ``full_scale`` (counts at or beyond which an axis is saturated).
    """

    PART = "device"
    #: sub-address bit that requests auto-increment (0x80 on ST parts on I2C, none elsewhere):
    #: errors name the register as the datasheet does, without it
    AUTO_INCREMENT_FLAG = 0x00
    #: what a wrong identity may mean, the end of :class:`PartIdentityError`'s message
    IDENTITY_HINT = HINT_ANY_BUS

    def __init__(self, transport: RegisterTransport, *, diagnostics: SourceDiagnostics | None = None,
                 retries: int = 2) -> None:
        if retries < 0:
            raise ValueError(f"{self.PART}: retries must be >= 0, got {retries}")
        self.transport = transport
        self.diagnostics = diagnostics if diagnostics is not None else SourceDiagnostics()
        self.retries = int(retries)
        self.scale = np.ones(3)
        self.full_scale = 32767

    # ---------------------------------------------------------------- transfers
    def _transfer(self, fn: Callable[..., Any], reg: int, action: str, *args: Any) -> Any:
        """``fn(reg, *args)``, a transport call, under the retry policy (:func:`run_retried`)."""
        try:
            return fn(reg, *args)
        except OSError as first:  # the retry machinery is built only once a transfer failed
            return self._retry(first, fn, reg, action, args)

    def _retry(self, first: OSError, fn: Callable[..., Any], reg: int, action: str,
               args: tuple[Any, ...]) -> Any:
        """Counts the failed first attempt, then repeats the transfer as :func:`run_retried`
        does with the retries left."""
        d = self.diagnostics

        def error(exc: OSError) -> OSError:
            return self.transport.transfer_error(self.PART, reg & ~self.AUTO_INCREMENT_FLAG, action, exc)

        d.bus_errors += 1
        err = error(first)
        d.last_error = str(err)
        if self.retries == 0:
            raise err from first
        d.retries += 1
        return run_retried(lambda: fn(reg, *args), self.retries - 1, d, error)

    def read_u8(self, reg: int) -> int:
        """One register byte (retried)."""
        return self._transfer(self.transport.read_u8, reg, "reading")

    def read_regs(self, reg: int, n: int) -> bytes:
        """``n`` consecutive registers from ``reg`` (with any auto-increment flag) in one
        transfer, ``n`` ≤ ``transport.max_read`` (retried)."""
        return self._transfer(self.transport.read, reg, "reading", n)

    #: the name the I2C-only parts knew :meth:`read_regs` by (it gives bytes)
    read_block = read_regs

    def write_u8(self, reg: int, value: int) -> None:
        """Writes one register byte (retried)."""
        self._transfer(self.transport.write, reg, "writing", value)

    def write_verified(self, reg: int, value: int, what: str) -> None:
        """Writes a configuration byte and reads it back: a mismatch means a wrong part
        (:class:`PartIdentityError`), the check of a part without an identity register."""
        self.write_u8(reg, value)
        got = self.read_u8(reg)
        if got != value:
            raise PartIdentityError(self.transport.where, self.PART, reg, got, (value,),
                                    f"{what} read back after writing", self.IDENTITY_HINT)

    def check_identity(self, reg: int, expected: int | bytes | Sequence[int] | Sequence[bytes],
                       what: str) -> bytes:
        """Reads the identity register(s) from ``reg`` and compares; returns what was read.

        expected: one identity as bytes (several registers, e.g. b"H43"), or the accepted
        alternatives (bytes of one length, or ints for one register).
        Raises :class:`PartIdentityError` (wrong part) or the transport's
        :class:`TransportError` (nothing answers), both naming where the part is and the register.
        """
        options = _identity_options(expected)
        n = len(options[0])
        got = self.read_regs(reg, n) if n > 1 else bytes((self.read_u8(reg),))
        if got not in options:
            raise PartIdentityError(self.transport.where, self.PART, reg, got, options, what,
                                    self.IDENTITY_HINT)
        return got

    def _read_chunked(self, reg: int, total: int, step: int) -> bytes:
        """``total`` bytes from ``reg`` in transfers of at most ``step`` bytes."""
        return b"".join([self.read_regs(reg, min(step, total - start))
                         for start in range(0, total, step)])

    def read_fifo(self, reg: int, n: int, granule: int = 1) -> bytes:
        """``n`` bytes from the FIFO data register ``reg``, in transfers of at most
        ``max_read`` bytes rounded down to whole ``granule``-byte frames."""
        step = max(granule, self.transport.max_read // granule * granule)
        if n <= step:
            return self.read_regs(reg, n)
        return self._read_chunked(reg, n, step)

    def read_fifo_frames(self, fifo: "FifoLayout", frames: int) -> bytes:
        """``frames`` whole FIFO frames popped from ``fifo.data_register``, oldest first, in as
        few transfers as the part and the bus allow (see :class:`FifoLayout`); each transfer
        retried."""
        if fifo.frames_per_transfer == 0:  # a byte stream: any split, the bus's longest reads
            step = self.transport.max_read
        else:
            step = fifo.frames_per_transfer * fifo.frame_bytes
        return self._read_chunked(fifo.data_register, frames * fifo.frame_bytes, step)

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
        return f"{type(self).__name__}({self.transport.where})"


#: the name this base had while only today's IMUs used it
TransportDevice = RegisterDevice


class I2CDevice(RegisterDevice):
    """A register part that lives on I2C only, built from a bus and an address: the base over
    an :class:`I2CTransport` (``transport``), which raises :class:`I2CDeviceError`.

    Subclasses set ``PART`` (name for messages), ``DEFAULT_ADDRESS``, any
    ``AUTO_INCREMENT_FLAG``, and after :meth:`configure` the conversion ``scale`` and
    ``full_scale``. ``bus`` and ``address`` stay readable (a board finds a part's twin by them).
    """

    PART = "I2C device"
    DEFAULT_ADDRESS = 0x00
    IDENTITY_HINT = HINT_I2C_ONLY

    def __init__(self, bus: I2CBus, address: int | None = None, *,
                 diagnostics: SourceDiagnostics | None = None, retries: int = 2) -> None:
        address = self.DEFAULT_ADDRESS if address is None else int(address)
        if not 0x03 <= address <= 0x77:
            raise ValueError(f"{self.PART}: I2C address 0x{address:02X} is outside 0x03..0x77")
        # the configuration check builds parts on no bus: their constructors only check and store
        transport = I2CTransport(bus, address) if bus is not None else None
        super().__init__(transport, diagnostics=diagnostics, retries=retries)  # type: ignore[arg-type]
        self.bus, self.address = bus, address

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
