"""One SPI bus abstraction with two backends: Linux spidev and a simulation.

A transfer is full duplex: the host clocks out ``data`` with one chip select asserted and
gets as many bytes back. Drivers never call a bus directly; they go through
:class:`~ahrs_service.drivers.transport.SPITransport` (address byte, read bit, dummy bytes).

* :class:`SpidevSPI` — ``/dev/spidev<bus>.<cs>`` through the ``spidev`` module (one
  ``SpiDev`` per chip select, mode 0–3, clock in Hz). Install with
  ``pip install 'ahrs-service[hardware]'``.
* :class:`SimulatedSPIBus` — simulated register devices on chip selects, on a simulation
  clock, with fault injection (transfer errors, a device that vanishes: its MISO then
  floats high and every byte reads 0xFF, as on a real board — SPI has no ACK).

Simulated devices answer SPI like the parts: the first byte is the register with bit 7 set
for a read; the part clocks out ``SPI_DUMMY_BYTES`` undefined bytes before the data (one on
the BMI088 accelerometer); a write sends the register with bit 7 clear, then the data.
"""

from __future__ import annotations

import abc
import errno
import os
import time
from typing import TYPE_CHECKING, Any

from ahrs_service.drivers.sim_bus import SimulatedBusBase, SimulatedSlot, simulating

if TYPE_CHECKING:  # pragma: no cover
    from ahrs_service.drivers.i2c.device import SimulatedRegisterDevice

#: spidev's default transfer buffer (module parameter spidev.bufsiz), bytes
SPIDEV_BUFSIZ = 4096


class SPIBus(abc.ABC):
    """Full-duplex transfers to the chip selects of one SPI controller."""

    name: str = "spi"
    simulated: bool = False
    #: the longest transfer in bytes (command + dummy + data)
    max_transfer: int = SPIDEV_BUFSIZ

    @abc.abstractmethod
    def transfer(self, cs: int, data: bytes) -> bytes:
        """Clocks ``data`` out with chip select ``cs`` asserted; returns the bytes clocked in."""

    @abc.abstractmethod
    def speed_hz(self, cs: int) -> float:
        """The clock used for chip select ``cs``, Hz."""

    def device_name(self, cs: int) -> str:
        """What messages call chip select ``cs``, e.g. "/dev/spidev0.1"."""
        return f"{self.name}.{cs}"

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def close(self) -> None:
        """Releases the device nodes."""


class SpidevSPI(SPIBus):
    """``/dev/spidev<bus>.<cs>`` for each chip select used, all at ``mode`` and ``speed_hz``.

    Raises :class:`FileNotFoundError` (SPI not enabled, wrong bus/chip select) and
    :class:`PermissionError` (user not in the ``spi`` group), each with the fix.
    """

    def __init__(self, bus: int, chip_selects: tuple[int, ...] = (0,), *, mode: int = 3,
                 speed_hz: int = 8_000_000) -> None:
        import spidev  # imported here: the simulated path never needs the hardware module

        if not isinstance(bus, int) or bus < 0:
            raise ValueError(f"SPI bus number must be an integer >= 0, got {bus!r}")
        if mode not in (0, 1, 2, 3):
            raise ValueError(f"SPI mode must be 0, 1, 2 or 3, got {mode!r}")
        if not 10_000 <= speed_hz <= 50_000_000:
            raise ValueError(f"SPI speed must be 10 kHz … 50 MHz, got {speed_hz} Hz")
        self.bus, self.mode, self._speed = bus, mode, int(speed_hz)
        self.name = f"/dev/spidev{bus}"
        self._dev: dict[int, Any] = {}
        try:
            for cs in chip_selects:
                node = self.device_name(cs)
                if not os.path.exists(node):
                    raise FileNotFoundError(
                        errno.ENOENT,
                        f"SPI device {node} does not exist: enable SPI (Raspberry Pi: "
                        f"`sudo raspi-config nonint do_spi 0` or dtparam=spi=on in "
                        f"/boot/firmware/config.txt, then reboot; a second chip select or bus "
                        f"needs its overlay, e.g. dtoverlay=spi1-2cs) and check source.spi_bus / "
                        f"source.spi_device (`ls /dev/spidev*`)", node)
                dev = spidev.SpiDev()
                try:
                    dev.open(bus, cs)
                except PermissionError as exc:
                    raise PermissionError(
                        errno.EACCES,
                        f"no permission to open {node}: add the service user to the 'spi' group "
                        f"(`sudo usermod -aG spi $USER`, then log in again)", node) from exc
                dev.mode = mode
                dev.max_speed_hz = self._speed
                dev.bits_per_word = 8
                self._dev[cs] = dev
        except BaseException:
            self.close()
            raise

    def device_name(self, cs: int) -> str:
        return f"/dev/spidev{self.bus}.{cs}"

    def speed_hz(self, cs: int) -> float:
        return float(self._speed)

    def transfer(self, cs: int, data: bytes) -> bytes:
        # xfer2 keeps chip select asserted for the whole list (xfer toggles it between bytes)
        return bytes(self._dev[cs].xfer2(list(data)))

    def close(self) -> None:
        for dev in self._dev.values():
            dev.close()
        self._dev.clear()


class SimulatedSPIBus(SimulatedBusBase, SPIBus):
    """Simulated register devices on chip selects, on ``clock`` (``now()`` in s, ``to_ns``).

    ``transfers`` counts transfers, ``bytes_moved`` the bytes clocked. The devices make the
    samples due before each transfer and when the host reads the bus clock
    (:meth:`~ahrs_service.drivers.sim_bus.SimulatedBusBase.catch_up`), not inside a transfer.
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
