"""One SPI bus abstraction with two backends: Linux spidev and a simulation.

A transfer is full duplex: the host clocks out ``data`` with one chip select asserted and
gets as many bytes back. Drivers never call a bus directly; they go through
:class:`~ahrs_service.drivers.transport.SPITransport` (address byte, read bit, dummy bytes).

* :class:`SpidevSPI` — ``/dev/spidev<bus>.<cs>`` through the ``spidev`` module (one
  ``SpiDev`` per chip select, mode 0–3, clock in Hz). Install with
  ``pip install 'ahrs-service[hardware]'``.
* :class:`~ahrs_service.drivers.sim.bus.SimulatedSPIBus` — simulated register devices on chip selects, on a simulation
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
from typing import Any

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
