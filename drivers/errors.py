"""The errors of register access, one hierarchy for every part on every bus.

* :class:`TransportError` (an ``OSError``): a register transfer failed after the retries; it
  names the part, where it sits (bus and address, or chip select) and the register.
  :class:`I2CDeviceError` is the one an :class:`~ahrs_service.drivers.transport.I2CTransport`
  raises: it also carries ``bus`` and ``address``.
* :class:`DeviceIdentityError` (a ``RuntimeError``): something answers, but it is not the
  expected part (an identity register, or a configuration byte read back, differs).
  :class:`PartIdentityError` is the one every driver raises.

A board tells the two apart: a transfer error means a part lost (retried later), an
identity error a wrong wiring or setting (refused at start).
"""

from __future__ import annotations

import errno
from collections.abc import Sequence

#: what a wrong identity may mean, for a part that may sit on SPI or I2C
HINT_ANY_BUS = "another part here, no part at all (0x00/0xFF), or a wrong chip select/address/board setting?"
#: the same for a part that lives on I2C only: a missing part does not answer there (ENXIO)
#: instead of reading 0x00/0xFF, and there is no chip select to get wrong
HINT_I2C_ONLY = "another part at this address, or a wrong address/board setting?"


def _hex(b: bytes) -> str:
    return " ".join(f"0x{x:02X}" for x in b)


class TransportError(OSError):
    """A register transfer failed after the retries: names bus, address or chip select, register.

    ``errno`` is the cause's (EIO when it had none); ``register`` is the datasheet's, without
    any auto-increment flag.
    """

    def __init__(self, where: str, part: str, register: int, action: str, cause: OSError):
        self.where, self.part, self.register, self.cause = where, part, register, cause
        super().__init__(cause.errno or errno.EIO,
                         f"{part} at {where}: {action} register 0x{register:02X} failed: "
                         f"{cause.strerror or cause}")


class I2CDeviceError(TransportError):
    """A transfer to a part on I2C failed after the retries: names bus, address, register."""

    def __init__(self, bus: str, address: int, part: str, register: int, action: str,
                 cause: OSError):
        self.bus, self.address = bus, address
        super().__init__(f"{bus} address 0x{address:02X}", part, register, action, cause)


class DeviceIdentityError(RuntimeError):
    """The device at an address is not the expected part (identity register mismatch)."""

    def __init__(self, bus: str, address: int, part: str, register: int, read: bytes,
                 expected: Sequence[bytes], what: str):
        self.bus, self.address, self.part, self.register = bus, address, part, register
        self.read, self.expected = read, list(expected)
        exp = " or ".join(_hex(e) for e in expected)
        super().__init__(
            f"{bus} address 0x{address:02X}: expected {part}, but {what} (register "
            f"0x{register:02X}) reads {_hex(read)}, expected {exp} — {HINT_I2C_ONLY}"
        )


def _as_bytes(value: int | bytes) -> bytes:
    return bytes((value,)) if isinstance(value, int) else bytes(value)


class PartIdentityError(DeviceIdentityError):
    """The part behind a transport is not the expected one (identity register mismatch).

    got: the byte (int) or bytes read; expected: the accepted values, bytes or single-byte
    ints; hint: what the mismatch may mean (:data:`HINT_ANY_BUS` unless the part lives on
    I2C only).
    """

    def __init__(self, where: str, part: str, register: int, got: int | bytes,
                 expected: Sequence[int] | Sequence[bytes], what: str, hint: str = HINT_ANY_BUS) -> None:
        self.bus, self.address, self.part, self.register = where, None, part, register
        self.read, self.expected = _as_bytes(got), [_as_bytes(e) for e in expected]
        RuntimeError.__init__(
            self, f"{where}: expected {part}, but {what} (register 0x{register:02X}) reads "
            f"{_hex(self.read)}, expected {' or '.join(_hex(e) for e in self.expected)} — {hint}")
