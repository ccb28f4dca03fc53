"""One I2C bus abstraction with two backends: real hardware (smbus2) and a simulation.

Every part on I2C (``drivers/parts/``) reaches its registers through an
:class:`~ahrs_service.drivers.transport.I2CTransport` on an :class:`I2CBus` and nothing else,
so the simulated devices sit behind exactly the code that runs on hardware:

* :class:`SMBusI2C` — a Linux ``/dev/i2c-N`` adapter through smbus2 (Raspberry Pi & co.).
* :class:`~ahrs_service.drivers.sim.bus.SimulatedI2CBus` — simulated register devices attached by address, driven by a
  simulation clock, with fault injection for tests (transient errors, a device that
  disappears and comes back).

Reads longer than an SMBus block: an adapter that speaks plain I2C (``I2C_FUNC_I2C``: the
Raspberry Pi's, i.MX, Tegra and most SoC controllers) takes a register write followed by a
read of any length in one combined transaction (``I2C_RDWR``, smbus2's ``i2c_rdwr``), so a
FIFO is emptied in one transfer; :attr:`I2CBus.max_read_bytes` says how long a read may be
(32 on an SMBus-only adapter, where :meth:`I2CBus.read_burst` is refused above that).

Errors follow Linux: a failed transfer raises :class:`OSError`; an address nobody answers
raises ``OSError(ENXIO)`` (what most adapters return for an address NACK; some return
``EREMOTEIO``). Bus timestamps are nanoseconds on the host monotonic clock
(``time.monotonic_ns``), or the simulation clock mapped to nanoseconds.
"""

from __future__ import annotations

import abc
import errno
import os
import time
from collections.abc import Sequence

#: SMBus block transfers carry at most 32 data bytes
SMBUS_BLOCK_MAX = 32
#: Linux i2c-dev's longest message in one I2C_RDWR transaction (bytes)
I2C_RDWR_MAX = 8192


class I2CBus(abc.ABC):
    """Register-level access to devices on one I2C bus (the SMBus subset the drivers use).

    ``reg`` is the 8-bit register (sub-)address sent before the data; for ST parts the
    driver sets its MSB itself to request auto-increment.
    """

    #: human-readable bus name used in every error message, e.g. "/dev/i2c-1"
    name: str = "i2c"
    #: True when the devices on this bus are simulated (samples then carry truth)
    simulated: bool = False
    #: the longest read one transaction may carry: an SMBus block (32) unless the adapter
    #: speaks plain I2C (then :data:`I2C_RDWR_MAX`, Linux i2c-dev's limit for one message)
    max_read_bytes: int = SMBUS_BLOCK_MAX

    @abc.abstractmethod
    def read_byte_data(self, addr: int, reg: int) -> int:
        """One byte read from register ``reg`` of the device at 7-bit address ``addr``."""

    @abc.abstractmethod
    def write_byte_data(self, addr: int, reg: int, value: int) -> None:
        """Writes one byte ``value`` to register ``reg``."""

    @abc.abstractmethod
    def read_i2c_block_data(self, addr: int, reg: int, n: int) -> list[int]:
        """Burst read of ``n`` bytes (1…32) starting at ``reg`` in one bus transaction."""

    @abc.abstractmethod
    def write_i2c_block_data(self, addr: int, reg: int, data: Sequence[int]) -> None:
        """Burst write of ``data`` (≤ 32 bytes) starting at ``reg``."""

    def read_burst(self, addr: int, reg: int, n: int) -> list[int]:
        """``n`` bytes (1 … :attr:`max_read_bytes`) from ``reg`` in one transaction: the
        register written, then read with a repeated start. Here: SMBus blocks only."""
        check_transfer(addr, reg, n, self.max_read_bytes)
        return self.read_i2c_block_data(addr, reg, n)

    def now_ns(self) -> int:
        """Timestamp (ns) for a reading taken now: host monotonic clock on hardware."""
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        """Waits for a device's settling time (a datasheet delay). No-op in simulation."""
        time.sleep(seconds)

    def close(self) -> None:
        """Releases the adapter."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


def check_transfer(addr: int, reg: int, n: int | None = None, longest: int = SMBUS_BLOCK_MAX) -> None:
    # Bad arguments are programming errors, not bus faults: ValueError, never retried.
    if not 0x03 <= addr <= 0x77:
        raise ValueError(f"I2C address 0x{addr:02X} is outside the 7-bit range 0x03..0x77")
    if not 0 <= reg <= 0xFF:
        raise ValueError(f"register 0x{reg:X} is not an 8-bit sub-address (device 0x{addr:02X})")
    if n is not None and not 1 <= n <= longest:
        kind = "SMBus blocks are" if longest == SMBUS_BLOCK_MAX else "one read on this bus is"
        raise ValueError(f"block transfer of {n} bytes at device 0x{addr:02X} register "
                         f"0x{reg:02X}: {kind} 1..{longest} bytes")


class SMBusI2C(I2CBus):
    """A Linux I2C adapter ``/dev/i2c-<bus_number>`` through smbus2.

    Raises :class:`FileNotFoundError` when the device node does not exist (I2C not enabled,
    wrong bus number) and :class:`PermissionError` when the user may not open it, each with
    the fix in the message.
    """

    def __init__(self, bus_number: int) -> None:
        import smbus2  # imported here so the simulated path never needs the hardware module

        if not isinstance(bus_number, int) or bus_number < 0:
            raise ValueError(f"I2C bus number must be an integer >= 0, got {bus_number!r}")
        self.bus_number = bus_number
        self.name = f"/dev/i2c-{bus_number}"
        if not os.path.exists(self.name):
            raise FileNotFoundError(
                errno.ENOENT,
                f"I2C bus {self.name} does not exist: enable I2C (Raspberry Pi: "
                f"`sudo raspi-config nonint do_i2c 0` or dtparam=i2c_arm=on in "
                f"/boot/firmware/config.txt, then reboot; elsewhere `modprobe i2c-dev`) "
                f"and check the bus number (`ls /dev/i2c-*`, `i2cdetect -l`)",
                self.name,
            )
        try:
            self._smbus = smbus2.SMBus(bus_number)
        except PermissionError as exc:
            raise PermissionError(
                errno.EACCES,
                f"no permission to open I2C bus {self.name}: add the service user to the "
                f"'i2c' group (`sudo usermod -aG i2c $USER`, then log in again) or install "
                f"a udev rule giving it access",
                self.name,
            ) from exc
        self._i2c_msg = smbus2.i2c_msg
        try:
            plain_i2c = bool(self._smbus.funcs & smbus2.I2cFunc.I2C)
        except (AttributeError, TypeError):  # an smbus2 without funcs: SMBus blocks only
            plain_i2c = False
        self.max_read_bytes = I2C_RDWR_MAX if plain_i2c else SMBUS_BLOCK_MAX

    def read_byte_data(self, addr: int, reg: int) -> int:
        return self._smbus.read_byte_data(addr, reg)

    def write_byte_data(self, addr: int, reg: int, value: int) -> None:
        self._smbus.write_byte_data(addr, reg, value)

    def read_i2c_block_data(self, addr: int, reg: int, n: int) -> list[int]:
        return self._smbus.read_i2c_block_data(addr, reg, n)

    def write_i2c_block_data(self, addr: int, reg: int, data: Sequence[int]) -> None:
        self._smbus.write_i2c_block_data(addr, reg, list(data))

    def read_burst(self, addr: int, reg: int, n: int) -> list[int]:
        check_transfer(addr, reg, n, self.max_read_bytes)
        if n <= SMBUS_BLOCK_MAX:
            return self._smbus.read_i2c_block_data(addr, reg, n)
        write, read = self._i2c_msg.write(addr, [reg]), self._i2c_msg.read(addr, n)
        self._smbus.i2c_rdwr(write, read)  # one combined transaction: repeated start, no stop
        return list(read)

    def close(self) -> None:
        self._smbus.close()
