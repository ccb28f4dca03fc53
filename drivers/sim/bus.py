"""The simulated buses: :class:`SimulatedI2CBus` (devices at addresses) and
:class:`SimulatedSPIBus` (devices on chip selects) behind the same bus interfaces as the
hardware (:mod:`ahrs_service.drivers.buses`), so the twins sit behind exactly the driver code
that runs on hardware.

What they share (:class:`SimulatedBusBase`): simulated register devices in slots, the
simulation clock, and fault injection — transfer errors and a device that vanishes and comes
back power-cycled.
"""

from __future__ import annotations

import errno
import functools
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from ahrs_service.drivers.buses.i2c import I2C_RDWR_MAX, SMBUS_BLOCK_MAX, I2CBus, check_transfer
from ahrs_service.drivers.buses.spi import SPIBus

if TYPE_CHECKING:  # pragma: no cover
    from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice


class SimulatedSlot:
    """A device on a simulated bus, with its fault-injection state."""

    __slots__ = ("device", "present", "visible_if", "pending_errors", "error_errno")

    def __init__(self, device: "SimulatedRegisterDevice",
                 visible_if: Callable[[], bool] | None = None) -> None:
        self.device = device
        self.present = True
        self.visible_if = visible_if
        self.pending_errors = 0
        self.error_errno = errno.EIO

    def injected_error(self, where: str) -> OSError | None:
        """The error of the next transfer when one was injected (counted down), else None."""
        if self.pending_errors <= 0:
            return None
        self.pending_errors -= 1
        return OSError(self.error_errno, f"{where}: injected transfer error")


def simulating(method: Callable[..., Any]) -> Callable[..., Any]:
    """Marks a simulated bus's method whose work is the simulated hardware's (a transfer, the
    catch-up of the parts' due samples): its thread CPU time is added to the bus's
    ``simulation_cpu_ns`` — what a real bus's parts would have done for nothing. Counted at
    the outermost such call only (one may call another)."""

    @functools.wraps(method)
    def counted(self: "SimulatedBusBase", *args: Any, **kwargs: Any) -> Any:
        if self._inside_simulation:
            return method(self, *args, **kwargs)
        self._inside_simulation = True
        start = time.thread_time_ns()
        try:
            return method(self, *args, **kwargs)
        finally:
            self.simulation_cpu_ns += time.thread_time_ns() - start
            self._inside_simulation = False

    return counted


class SimulatedBusBase:
    """The slots, clock and fault injection of a simulated bus (``clock.now()`` in s).

    ``simulation_cpu_ns``: thread CPU time (ns) spent inside the bus's transfers and in its
    parts' making of samples (:func:`simulating`): the simulated hardware's share of the
    process's CPU, which benchmarks take off to state the service's own work (/loop
    ``simulation_cpu_s``).
    """

    clock: Any
    name: str
    _slots: dict[int, SimulatedSlot]
    simulation_cpu_ns: int = 0
    _inside_simulation: bool = False

    def _init_clock(self, clock: Any, bus_kind: str) -> None:
        if not callable(getattr(clock, "now", None)):
            raise TypeError(f"{bus_kind} needs a clock with now() -> seconds, got {clock!r}")
        self.clock = clock
        self._slots = {}

    def inject_errors(self, key: int, count: int = 1, err: int = errno.EIO) -> None:
        """The next ``count`` transfers to the device at ``key`` (address or chip select)
        raise ``OSError(err)`` (a glitch on the wires)."""
        slot = self._slots[key]
        slot.pending_errors += int(count)
        slot.error_errno = err

    def set_present(self, key: int, present: bool, power_cycle: bool = True) -> None:
        """Makes the device at ``key`` vanish or come back; coming back with ``power_cycle``
        resets its registers to power-on values (it lost power): the driver must configure
        it again."""
        slot = self._slots[key]
        if present and not slot.present and power_cycle:
            slot.device.power_on_reset(self.clock.now())
        slot.present = bool(present)

    #: passes of :meth:`catch_up` at most: each makes the samples that came due during the last
    CATCH_UP_PASSES = 4

    def catch_up(self, device: "SimulatedRegisterDevice") -> None:
        """Lets ``device`` make the samples due by now before a transfer reaches it, then
        those that came due while it did (until a pass makes at most one, at most
        :attr:`CATCH_UP_PASSES` passes). Making a FIFO's worth of samples costs the simulation
        tens of ms on a busy host; a real part's samples cost the host nothing. Done inside
        the transfer, that cost fell between the FIFO level the transfer latched and the
        data read that follows it — where a real part leaves microseconds — and the FIFO
        overflowed in between. Done first, it falls before the transfer, as a
        host delayed before its read would: the level then counts every sample made.
        Buses call it at each transfer and when the host reads their clock (it times a
        transfer next): the transfer's own time is then its own, as on a real bus, and the
        sensor clock's bounds stay tight (a transfer that took the simulation's 30 ms
        allowed its latch anywhere in them)."""
        for _ in range(self.CATCH_UP_PASSES):
            before = device.samples_due
            device.update(self.clock.now())
            if device.samples_due - before <= 1:
                return

    def now_ns(self) -> int:
        """The simulation clock's now, mapped to ns (``clock.to_ns`` when the clock has it)."""
        t = self.clock.now()
        to_ns = getattr(self.clock, "to_ns", None)
        return to_ns(t) if to_ns is not None else int(round(t * 1e9))

    def sleep(self, seconds: float) -> None:
        # simulated parts settle at once; tests move the clock themselves
        return None


class SimulatedI2CBus(SimulatedBusBase, I2CBus):
    """A bus of simulated register devices on a simulation clock.

    clock: any object with ``now() -> float`` seconds (``ManualClock`` in tests, a
    monotonic clock in real-time runs); ``to_ns(t)`` is used for timestamps when it exists.
    Each transfer first lets the addressed device latch the samples due by ``clock.now()``.

    Fault injection (tests): :meth:`inject_errors` makes the next transfers to an address
    fail like a glitch on the wires; :meth:`set_present` removes a device (it NACKs) and puts
    it back, power-cycled by default. ``transfers`` counts bus transactions.

    max_read_bytes: the adapter's longest read (default: a plain-I2C adapter's; 32 models an
    SMBus-only one).
    """

    simulated = True

    def __init__(self, clock: Any, name: str = "sim-i2c", nack_errno: int = errno.ENXIO,
                 max_read_bytes: int = I2C_RDWR_MAX) -> None:
        self._init_clock(clock, "SimulatedI2CBus")
        self.name = name
        self.nack_errno = nack_errno
        self.transfers = 0
        if not SMBUS_BLOCK_MAX <= max_read_bytes <= I2C_RDWR_MAX:
            raise ValueError(f"{name}: max_read_bytes must be {SMBUS_BLOCK_MAX}..{I2C_RDWR_MAX}, "
                             f"got {max_read_bytes}")
        self.max_read_bytes = int(max_read_bytes)

    # ----------------------------------------------------------------- devices
    def attach(self, device: "SimulatedRegisterDevice",
               visible_if: Callable[[], bool] | None = None) -> "SimulatedRegisterDevice":
        """Puts ``device`` on the bus at ``device.address``.

        visible_if: the device answers only while this returns True (e.g. an AK8963 behind
        an MPU-9250 that is reachable only in I2C bypass mode).
        """
        if device.address in self._slots:
            other = self._slots[device.address].device
            raise ValueError(f"{self.name}: address 0x{device.address:02X} is already taken "
                             f"by {type(other).__name__}")
        self._slots[device.address] = SimulatedSlot(device, visible_if)
        device.power_on_reset(self.clock.now())
        return device

    def detach(self, address: int) -> None:
        """Removes the device at ``address`` for good."""
        del self._slots[address]

    def device(self, address: int) -> "SimulatedRegisterDevice":
        """The simulated device attached at ``address`` (KeyError naming the bus if none)."""
        try:
            return self._slots[address].device
        except KeyError:
            raise KeyError(f"{self.name}: no simulated device attached at 0x{address:02X}") from None

    def addresses(self) -> list[int]:
        """Addresses that currently answer (like ``i2cdetect``)."""
        return sorted(a for a, s in self._slots.items() if self._answers(s))

    # faults: inject_errors(address, …) and set_present(address, …) (SimulatedBusBase)

    # ----------------------------------------------------------------- transfers
    @staticmethod
    def _answers(slot: SimulatedSlot) -> bool:
        return slot.present and (slot.visible_if is None or slot.visible_if())

    def _target(self, addr: int) -> "SimulatedRegisterDevice":
        self.transfers += 1
        slot = self._slots.get(addr)
        if slot is None or not self._answers(slot):
            raise OSError(self.nack_errno, f"{self.name}: no ACK from address 0x{addr:02X}")
        err = slot.injected_error(f"{self.name} at 0x{addr:02X}")
        if err is not None:
            raise err
        return slot.device

    @simulating
    def read_byte_data(self, addr: int, reg: int) -> int:
        check_transfer(addr, reg)
        return self._target(addr).bus_read(reg, 1, self.clock.now())[0]

    @simulating
    def write_byte_data(self, addr: int, reg: int, value: int) -> None:
        check_transfer(addr, reg)
        if not 0 <= value <= 0xFF:
            raise ValueError(f"{self.name}: byte 0x{value:X} for 0x{addr:02X} reg 0x{reg:02X}")
        self._target(addr).bus_write(reg, [value], self.clock.now())

    @simulating
    def read_i2c_block_data(self, addr: int, reg: int, n: int) -> list[int]:
        check_transfer(addr, reg, n)
        return self._target(addr).bus_read(reg, n, self.clock.now())

    @simulating
    def write_i2c_block_data(self, addr: int, reg: int, data: Sequence[int]) -> None:
        check_transfer(addr, reg, len(data))
        self._target(addr).bus_write(reg, list(data), self.clock.now())

    @simulating
    def read_burst(self, addr: int, reg: int, n: int) -> list[int]:
        check_transfer(addr, reg, n, self.max_read_bytes)
        return self._target(addr).bus_read(reg, n, self.clock.now())


class SimulatedSPIBus(SimulatedBusBase, SPIBus):
    """Simulated register devices on chip selects, on ``clock`` (``now()`` in s, ``to_ns``).

    ``transfers`` counts transfers, ``bytes_moved`` the bytes clocked. The devices make the
    samples due before each transfer and when the host reads the bus clock
    (:meth:`~SimulatedBusBase.catch_up`), not inside a transfer.
    """

    simulated = True

    def __init__(self, clock: Any, name: str = "sim-spi0", speed_hz: float = 8_000_000) -> None:
        self._init_clock(clock, "SimulatedSPIBus")
        self.name, self._speed = name, float(speed_hz)
        self.transfers = 0
        self.bytes_moved = 0

    def attach(self, device: "SimulatedRegisterDevice", cs: int) -> "SimulatedRegisterDevice":
        """Wires ``device`` to chip select ``cs`` (powered on now)."""
        if cs in self._slots:
            raise ValueError(f"{self.name}: chip select {cs} is already wired to "
                             f"{type(self._slots[cs].device).__name__}")
        self._slots[cs] = SimulatedSlot(device)
        device.power_on_reset(self.clock.now())
        return device

    def device(self, cs: int) -> "SimulatedRegisterDevice":
        try:
            return self._slots[cs].device
        except KeyError:
            raise KeyError(f"{self.name}: nothing wired to chip select {cs}") from None

    def speed_hz(self, cs: int) -> float:
        return self._speed

    # faults: inject_errors(cs, …) and set_present(cs, …) (SimulatedBusBase; a vanished
    # device leaves MISO floating: reads 0xFF)

    @simulating
    def now_ns(self) -> int:
        # the host times a transfer next: its parts make their due samples first (catch_up)
        for slot in self._slots.values():
            if slot.present:
                self.catch_up(slot.device)
        return super().now_ns()

    @simulating
    def transfer(self, cs: int, data: bytes) -> bytes:
        self.transfers += 1
        self.bytes_moved += len(data)
        slot = self._slots.get(cs)
        err = None if slot is None else slot.injected_error(self.device_name(cs))
        if err is not None:
            raise err
        if slot is None or not slot.present or not data:
            return b"\xff" * len(data)
        self.catch_up(slot.device)  # the simulation's cost before the transfer, not inside it
        return spi_answer(slot.device, data, self.clock.now())


def spi_answer(device: "SimulatedRegisterDevice", data: bytes, now: float) -> bytes:
    """What a simulated part clocks out for one transfer (its SPI register protocol).

    The device may define ``spi_select(now)`` (called at chip-select assertion, e.g. the
    BMI088 accelerometer switching to SPI mode) and ``SPI_DUMMY_BYTES``.
    """
    select = getattr(device, "spi_select", None)
    if select is not None and not select(now):
        return b"\xff" * len(data)  # the part was not listening on SPI yet
    cmd = data[0]
    reg = cmd & 0x7F
    if cmd & 0x80:
        dummy = getattr(device, "SPI_DUMMY_BYTES", 0)
        n = len(data) - 1 - dummy
        head = b"\xff" * (1 + min(dummy, len(data) - 1))
        return head + (bytes(device.bus_read(reg, n, now)) if n > 0 else b"")
    device.bus_write(reg, list(data[1:]), now)
    return b"\xff" * len(data)


def twin_behind(transport: Any) -> "SimulatedRegisterDevice":
    """The simulated part a :class:`~ahrs_service.drivers.transport.RegisterTransport` on a
    simulated bus reaches (at its chip select on SPI, its address on I2C): where a board or a
    test reads the twin's truth and FIFO."""
    bus = transport.bus
    return bus.device(transport.cs if transport.kind == "spi" else transport.address)
