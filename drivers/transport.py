"""Register transports: how a part's driver reaches its registers, over I2C or SPI.

Today's IMUs (ICM-42688-P, ICM-20948, BMI088) speak the same register protocol over either
bus, so their drivers (``drivers/imu/``) talk to a :class:`RegisterTransport` and never to a
bus directly:

* :class:`I2CTransport` — one address on an :class:`~ahrs_service.drivers.i2c.bus.I2CBus`
  (``/dev/i2c-N`` or the simulated I2C bus); a burst is one read on an adapter that speaks
  plain I2C, else split into the SMBus's 32-byte blocks (``I2CBus.max_read_bytes``).
* :class:`SPITransport` — one chip select on an :class:`~ahrs_service.drivers.spi.bus.SPIBus`
  (``/dev/spidevB.C`` or the simulated SPI bus); the first byte is the register address
  with the read bit (0x80 for every part here) set for reads, and ``dummy_bytes`` bytes the
  part clocks out before its data are dropped (one on the BMI088 accelerometer, datasheet
  BST-BMI088-DS001 §6.1.2).

:class:`TransportDevice` is the driver base on top: register access with the same retry and
fault counting as :class:`~ahrs_service.drivers.i2c.device.I2CDevice`, the identity check,
and :meth:`TransportDevice.read_fifo`, which reads a FIFO data register in transfers of at
most ``transport.max_read`` bytes.

``wire_bytes(n)`` is what a burst of ``n`` data bytes costs on the wire (start, address,
register, restart, data on I2C; command + dummy + data on SPI): the board multiplies it by
its reads per second to refuse a rate the bus cannot carry (:func:`check_bus_rate`).
"""

from __future__ import annotations

import abc
import errno
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from ahrs_service.drivers.base import SourceDiagnostics
from ahrs_service.drivers.i2c.bus import SMBUS_BLOCK_MAX
from ahrs_service.drivers.i2c.device import DeviceIdentityError, _hex, run_retried

if TYPE_CHECKING:  # pragma: no cover
    from ahrs_service.drivers.i2c.bus import I2CBus
    from ahrs_service.drivers.spi.bus import SPIBus

class TransportError(OSError):
    """A register transfer failed after the retries: names bus, address or chip select, register."""

    def __init__(self, where: str, part: str, register: int, action: str, cause: OSError):
        self.where, self.part, self.register, self.cause = where, part, register, cause
        super().__init__(cause.errno or errno.EIO,
                         f"{part} at {where}: {action} register 0x{register:02X} failed: "
                         f"{cause.strerror or cause}")


class PartIdentityError(DeviceIdentityError):
    """The part behind a transport is not the expected one (identity register mismatch)."""

    def __init__(self, where: str, part: str, register: int, got: int, expected: Sequence[int],
                 what: str) -> None:
        self.bus, self.address, self.part, self.register = where, None, part, register
        self.read, self.expected = bytes((got,)), [bytes((e,)) for e in expected]
        RuntimeError.__init__(
            self, f"{where}: expected {part}, but {what} (register 0x{register:02X}) reads "
            f"{_hex(self.read)}, expected {' or '.join(_hex(e) for e in self.expected)} — another "
            f"part here, no part at all (0x00/0xFF), or a wrong chip select/address/board setting?")


class RegisterTransport(abc.ABC):
    """Register reads and writes to one part, over whatever bus it sits on.

    ``where``: the bus and address/chip select for messages, e.g. "/dev/spidev0.0" or
    "/dev/i2c-1 address 0x68". ``clock_hz``: the bus clock used for rate checks.
    """

    where: str = "?"
    kind: str = "?"  # "i2c" or "spi"
    simulated: bool = False
    clock_hz: float = 0.0
    #: the largest single read transfer, data bytes
    max_read: int = SMBUS_BLOCK_MAX

    @abc.abstractmethod
    def read(self, reg: int, n: int) -> bytes:
        """``n`` bytes from ``reg`` (``n`` ≤ ``max_read``) in one transfer."""

    @abc.abstractmethod
    def write(self, reg: int, value: int) -> None:
        """One byte to ``reg``."""

    @abc.abstractmethod
    def wire_bytes(self, n: int) -> float:
        """Bytes on the wire for one read of ``n`` data bytes (framing included)."""

    @abc.abstractmethod
    def now_ns(self) -> int:
        """Now on the bus clock (host monotonic ns; the simulation clock when simulated)."""

    @abc.abstractmethod
    def sleep(self, seconds: float) -> None:
        """A datasheet delay (a no-op on simulated buses)."""


class I2CTransport(RegisterTransport):
    """A part at ``address`` on an I2C bus; ``clock_hz`` is the bus speed (100/400 kHz)."""

    kind = "i2c"

    def __init__(self, bus: "I2CBus", address: int, clock_hz: float = 400_000.0) -> None:
        if not 0x03 <= int(address) <= 0x77:
            raise ValueError(f"I2C address 0x{int(address):02X} is outside 0x03..0x77")
        self.bus, self.address, self.clock_hz = bus, int(address), float(clock_hz)
        self.where = f"{bus.name} address 0x{self.address:02X}"
        self.simulated = bus.simulated
        # an adapter that speaks plain I2C reads a whole FIFO burst in one transaction
        self.max_read = bus.max_read_bytes

    def read(self, reg: int, n: int) -> bytes:
        if n == 1:
            return bytes((self.bus.read_byte_data(self.address, reg),))
        if n <= SMBUS_BLOCK_MAX:
            return bytes(self.bus.read_i2c_block_data(self.address, reg, n))
        return bytes(self.bus.read_burst(self.address, reg, n))

    def write(self, reg: int, value: int) -> None:
        self.bus.write_byte_data(self.address, reg, value)

    def wire_bytes(self, n: int) -> float:
        # START + addr/W + reg, repeated START + addr/R, n data bytes; 9 clocks a byte with ACK
        return (3 + n) * 9 / 8

    def now_ns(self) -> int:
        return self.bus.now_ns()

    def sleep(self, seconds: float) -> None:
        self.bus.sleep(seconds)


class SPITransport(RegisterTransport):
    """A part on chip select ``cs`` of an SPI bus.

    read_bit: set in the address byte of a read (0x80: bit 7 = R/W on all parts here);
    dummy_bytes: bytes the part sends before the data of a read (BMI088 accelerometer: 1).
    """

    kind = "spi"

    def __init__(self, bus: "SPIBus", cs: int, *, read_bit: int = 0x80, dummy_bytes: int = 0) -> None:
        self.bus, self.cs = bus, int(cs)
        self.read_bit, self.dummy_bytes = int(read_bit), int(dummy_bytes)
        self.where = bus.device_name(self.cs)
        self.simulated = bus.simulated
        self.clock_hz = float(bus.speed_hz(self.cs))
        self.max_read = bus.max_transfer - 1 - self.dummy_bytes

    def read(self, reg: int, n: int) -> bytes:
        # command byte, dummy bytes, then n clocks for data: one chip-select assertion
        got = self.bus.transfer(self.cs, bytes((reg | self.read_bit,)) + bytes(self.dummy_bytes + n))
        return got[1 + self.dummy_bytes:]

    def write(self, reg: int, value: int) -> None:
        self.bus.transfer(self.cs, bytes((reg & ~self.read_bit & 0xFF, value)))

    def wire_bytes(self, n: int) -> float:
        return 1 + self.dummy_bytes + n

    def now_ns(self) -> int:
        return self.bus.now_ns()

    def sleep(self, seconds: float) -> None:
        self.bus.sleep(seconds)


class BusRateError(ValueError):
    """A configured rate the bus cannot carry (names the key, the need and the capacity)."""


def check_bus_rate(transport: RegisterTransport, key: str, rate_hz: float, bytes_per_sample: float,
                   reads_per_s: float, overhead_bytes: float, part: str, margin: float = 0.75) -> None:
    """Refuses ``rate_hz`` when its FIFO traffic needs more than ``margin`` of the bus.

    bytes_per_sample: FIFO bytes a sample takes; reads_per_s: FIFO bursts per second (the
    watermark rate); overhead_bytes: the other registers read per burst (status, count).
    The need is computed in wire bits: each burst costs ``wire_bytes`` for its data plus
    one short read per ``overhead_bytes``, and bursts longer than ``max_read`` are split.
    """
    per_burst = rate_hz / reads_per_s * bytes_per_sample
    chunks = max(1.0, -(-per_burst // transport.max_read))
    bits_per_s = 8 * reads_per_s * (chunks * transport.wire_bytes(per_burst / chunks)
                                    + transport.wire_bytes(overhead_bytes))
    capacity = margin * transport.clock_hz
    if bits_per_s > capacity:
        raise BusRateError(
            f"{key} = {rate_hz:g} Hz: the {part} on {transport.where} needs "
            f"{bits_per_s / 1000:.0f} kbit/s of FIFO traffic ({bytes_per_sample:g} bytes a sample), "
            f"more than {margin:.0%} of the {transport.kind.upper()} bus's {transport.clock_hz / 1000:g} kHz "
            f"clock; lower {key}" + (" or wire it on SPI" if transport.kind == "i2c" else
                                     " or raise source.spi_speed_hz"))


class TransportDevice:
    """Driver base: one part behind a :class:`RegisterTransport`, with retries and counters.

    Subclasses set ``PART``; registers are read with :meth:`read_u8` / :meth:`read_regs`,
    written with :meth:`write_u8`. Each failed transfer is counted in
    ``diagnostics.bus_errors`` and retried ``retries`` times before :class:`TransportError`.
    """

    PART = "device"

    def __init__(self, transport: RegisterTransport, *, diagnostics: SourceDiagnostics | None = None,
                 retries: int = 2) -> None:
        if retries < 0:
            raise ValueError(f"{self.PART}: retries must be >= 0, got {retries}")
        self.transport = transport
        self.diagnostics = diagnostics if diagnostics is not None else SourceDiagnostics()
        self.retries = int(retries)

    def _transfer(self, fn: Callable[..., Any], reg: int, action: str, *args: Any) -> Any:
        return run_retried(lambda: fn(reg, *args), self.retries, self.diagnostics,
                           lambda exc: TransportError(self.transport.where, self.PART, reg, action, exc))

    def read_u8(self, reg: int) -> int:
        return self._transfer(self.transport.read, reg, "reading", 1)[0]

    def read_regs(self, reg: int, n: int) -> bytes:
        """``n`` consecutive registers from ``reg`` in one transfer (``n`` ≤ max_read)."""
        return self._transfer(self.transport.read, reg, "reading", n)

    def write_u8(self, reg: int, value: int) -> None:
        self._transfer(self.transport.write, reg, "writing", value)

    def read_fifo(self, reg: int, n: int, granule: int = 1) -> bytes:
        """``n`` bytes from the FIFO data register ``reg``, in transfers of at most
        ``max_read`` bytes rounded down to whole ``granule``-byte frames."""
        step = max(granule, self.transport.max_read // granule * granule)
        if n <= step:
            return self.read_regs(reg, n)
        parts = []
        for start in range(0, n, step):
            parts.append(self.read_regs(reg, min(step, n - start)))
        return b"".join(parts)

    def check_identity(self, reg: int, expected: Sequence[int], what: str) -> int:
        """Reads ``reg`` and compares with the accepted ``expected`` values."""
        got = self.read_u8(reg)
        if got not in expected:
            raise PartIdentityError(self.transport.where, self.PART, reg, got, expected, what)
        return got

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.transport.where})"


