"""Register transports: how a part's driver reaches its registers, over I2C or SPI.

A register part speaks the same register protocol over either bus (today's IMUs: ICM-42688-P,
ICM-20948, BMI088 wire on both), so every part's driver (``drivers/parts/``, on the one base
:class:`~ahrs_service.drivers.device.RegisterDevice`) holds a :class:`RegisterTransport`:

* :class:`I2CTransport` — one address on an :class:`~ahrs_service.drivers.buses.i2c.I2CBus`
  (``/dev/i2c-N`` or the simulated I2C bus): a byte is an SMBus byte read, a burst an SMBus
  block up to 32 bytes and one plain-I2C read beyond (``I2C_RDWR``) on an adapter that
  speaks it (``I2CBus.max_read_bytes``). The bus's methods are looked up at each transfer,
  so a test may wrap them on a bus whose parts are built already.
* :class:`SPITransport` — one chip select on an :class:`~ahrs_service.drivers.buses.spi.SPIBus`
  (``/dev/spidevB.C`` or the simulated SPI bus); the first byte is the register address
  with the read bit (0x80 for every part here) set for reads, and ``dummy_bytes`` bytes the
  part clocks out before its data are dropped (one on the BMI088 accelerometer, datasheet
  BST-BMI088-DS001 §6.1.2).

The driver base on top, :class:`~ahrs_service.drivers.device.RegisterDevice`, retries and
counts each transfer and reads a FIFO data register in transfers of at most
``transport.max_read`` bytes. A transfer that keeps failing becomes the transport's
:meth:`~RegisterTransport.transfer_error` (``drivers/errors.py``), which names the part's place.

``wire_bytes(n)`` is what a burst of ``n`` data bytes costs on the wire (start, address,
register, restart, data on I2C; command + dummy + data on SPI): the board multiplies it by
its reads per second to refuse a rate the bus cannot carry (:func:`check_bus_rate`).
"""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING

from ahrs_service import _moved
from ahrs_service.drivers import errors
from ahrs_service.drivers.buses.i2c import SMBUS_BLOCK_MAX

if TYPE_CHECKING:  # pragma: no cover
    from ahrs_service.drivers.buses.i2c import I2CBus
    from ahrs_service.drivers.buses.spi import SPIBus


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

    def read_u8(self, reg: int) -> int:
        """One register byte (the common case: status and identity registers)."""
        return self.read(reg, 1)[0]

    @abc.abstractmethod
    def write(self, reg: int, value: int) -> None:
        """One byte to ``reg``."""

    def transfer_error(self, part: str, register: int, action: str, cause: OSError) -> OSError:
        """The error raised when a transfer to ``register`` (datasheet number) of ``part``
        failed after the retries: ``action`` "reading" or "writing", ``cause`` the last error."""
        return errors.TransportError(self.where, part, register, action, cause)

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
        self._max_read: int | None = None

    @property
    def max_read(self) -> int:
        """The adapter's longest read (an SMBus block, or a whole FIFO burst on an adapter
        that speaks plain I2C), asked at each burst: a bus may be narrowed after its parts are
        built; setting it narrows this transport alone."""
        return self.bus.max_read_bytes if self._max_read is None else self._max_read

    @max_read.setter
    def max_read(self, n: int) -> None:
        self._max_read = int(n)

    def read(self, reg: int, n: int) -> bytes:
        if n == 1:
            return bytes((self.bus.read_byte_data(self.address, reg),))
        if n <= SMBUS_BLOCK_MAX:
            return bytes(self.bus.read_i2c_block_data(self.address, reg, n))
        return bytes(self.bus.read_burst(self.address, reg, n))

    def read_u8(self, reg: int) -> int:
        return self.bus.read_byte_data(self.address, reg)

    def write(self, reg: int, value: int) -> None:
        self.bus.write_byte_data(self.address, reg, value)

    def transfer_error(self, part: str, register: int, action: str, cause: OSError) -> OSError:
        return errors.I2CDeviceError(self.bus.name, self.address, part, register, action, cause)

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


def __getattr__(name: str):  # names that moved out of this module keep working for one release
    return _moved.moved_name(__name__, name)
