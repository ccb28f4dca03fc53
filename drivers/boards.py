"""The board registry: every board name the configuration accepts, and on which buses.

* I2C boards of the source papers and the MPU-9250: :mod:`ahrs_service.drivers.i2c.boards`
  (``gy80``, ``minimu9v2``, ``mpu9250``) — I2C only.
* Today's FIFO boards: :mod:`ahrs_service.drivers.imu.boards` (``icm42688p`` on SPI or I2C,
  ``icm20948`` on SPI or I2C, ``bmi088`` on SPI: its accelerometer on ``spi_device``, its gyroscope on
  ``board_options.gyro_spi_device``, default ``spi_device + 1``) through a
  :class:`~ahrs_service.drivers.transport.RegisterTransport`.

:func:`make_transport_board` builds a FIFO board on a real bus (``spi``: ``/dev/spidevB.C``;
``i2c``: ``/dev/i2c-N``) or on the simulated bus of that kind with its twin attached.
"""

from __future__ import annotations

import inspect
from typing import Any

from ahrs_service.drivers.imu.bmi088 import SimulatedBMI088Accel, SimulatedBMI088Gyro
from ahrs_service.drivers.imu.boards import BMI088Board, FifoBoard, ICM20948Board, ICM42688PBoard
from ahrs_service.drivers.imu.icm20948 import SimulatedICM20948
from ahrs_service.drivers.imu.icm42688p import SimulatedICM42688P

#: FIFO boards: name → (class, buses it can be wired on, default I2C address)
TRANSPORT_BOARDS: dict[str, tuple[type[FifoBoard], tuple[str, ...], int]] = {
    "icm42688p": (ICM42688PBoard, ("spi", "i2c"), 0x68),
    "icm20948": (ICM20948Board, ("spi", "i2c"), 0x68),
    "bmi088": (BMI088Board, ("spi",), 0x00),
}
#: the twin of each FIFO board's part
_TWINS = {"icm42688p": SimulatedICM42688P, "icm20948": SimulatedICM20948}


def all_board_names() -> list[str]:
    from ahrs_service.drivers.i2c.boards import board_names

    return board_names() + list(TRANSPORT_BOARDS)


def buses_of(name: str) -> tuple[str, ...]:
    """The buses board ``name`` can be wired on ("i2c", "spi")."""
    return TRANSPORT_BOARDS[name][1] if name in TRANSPORT_BOARDS else ("i2c",)


def transport_board_class(name: str, options: dict[str, Any]) -> type[FifoBoard]:
    """The FIFO board class for ``name``; ValueError naming unknown options."""
    cls = TRANSPORT_BOARDS[name][0]
    allowed = {p for c in (cls, FifoBoard) for p in inspect.signature(c.__init__).parameters
               if p not in ("self", "transport", "kw", "own_bus", "acc_transport")}
    if name == "bmi088":
        allowed.add("gyro_spi_device")
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"board {name!r}: unknown option(s) {', '.join(unknown)}; "
                         f"valid: {', '.join(sorted(allowed))}")
    return cls


def make_transport_board(name: str, bus_kind: str, *, simulated_imu: Any = None, spi_bus: int = 0,
                         spi_device: int = 0, spi_mode: int = 3, spi_speed_hz: int = 8_000_000,
                         i2c_bus: int = 1, i2c_speed_hz: int = 400_000, address: int | None = None,
                         sim_bus_name: str | None = None, **options: Any) -> FifoBoard:
    """A FIFO board (not opened) on a real or, with ``simulated_imu``, a simulated bus.

    bus_kind: "spi" or "i2c". The simulated bus carries the board's twin fed by
    ``simulated_imu`` (``physics(t)``, ``clock``) at ``spi_device`` / ``address``;
    ``sim_bus_name`` names it in messages (the configuration check simulates the real bus).
    """
    from ahrs_service.drivers.transport import I2CTransport, SPITransport

    cls = transport_board_class(name, options)
    if name == "bmi088":
        return _make_bmi088(simulated_imu, spi_bus, spi_device, spi_mode, spi_speed_hz, options, sim_bus_name)
    kinds = TRANSPORT_BOARDS[name][1]
    if bus_kind not in kinds:
        raise ValueError(f"board {name!r} cannot be wired on {bus_kind}; it supports {', '.join(kinds)}")
    addr = TRANSPORT_BOARDS[name][2] if address is None else int(address)
    if bus_kind == "spi":
        if simulated_imu is not None:
            from ahrs_service.drivers.spi.bus import SimulatedSPIBus

            bus = SimulatedSPIBus(simulated_imu.clock, name=sim_bus_name or f"sim-spi{spi_bus}",
                                  speed_hz=spi_speed_hz)
            bus.attach(_twin_for(name, simulated_imu), spi_device)
        else:
            from ahrs_service.drivers.spi.bus import SpidevSPI

            bus = SpidevSPI(spi_bus, (spi_device,), mode=spi_mode, speed_hz=spi_speed_hz)
        transport = SPITransport(bus, spi_device)
    else:
        if simulated_imu is not None:
            from ahrs_service.drivers.i2c.bus import SimulatedI2CBus

            bus = SimulatedI2CBus(simulated_imu.clock, name=sim_bus_name or f"sim-i2c[{name}]")
            bus.attach(_twin_for(name, simulated_imu, addr))
        else:
            from ahrs_service.drivers.i2c.bus import SMBusI2C

            bus = SMBusI2C(i2c_bus)
        transport = I2CTransport(bus, addr, clock_hz=i2c_speed_hz)
    try:
        return cls(transport, own_bus=None if simulated_imu is not None else bus, **options)
    except BaseException:
        if simulated_imu is None:
            bus.close()
        raise


def _make_bmi088(simulated_imu: Any, spi_bus: int, spi_device: int, spi_mode: int, spi_speed_hz: int,
                 options: dict[str, Any], sim_bus_name: str | None = None) -> FifoBoard:
    """The BMI088's two dies on two chip selects: accelerometer (dummy byte) and gyroscope."""
    from ahrs_service.drivers.transport import SPITransport

    gyro_cs = int(options.pop("gyro_spi_device", spi_device + 1))
    if gyro_cs == spi_device:
        raise ValueError(f"bmi088: gyro_spi_device must differ from source.spi_device ({spi_device}): "
                         f"each die has its own chip select")
    if simulated_imu is not None:
        from ahrs_service.drivers.spi.bus import SimulatedSPIBus

        bus = SimulatedSPIBus(simulated_imu.clock, name=sim_bus_name or f"sim-spi{spi_bus}",
                              speed_hz=spi_speed_hz)
        bus.attach(SimulatedBMI088Accel(simulated_imu), spi_device)
        bus.attach(SimulatedBMI088Gyro(simulated_imu), gyro_cs)
    else:
        from ahrs_service.drivers.spi.bus import SpidevSPI

        bus = SpidevSPI(spi_bus, (spi_device, gyro_cs), mode=spi_mode, speed_hz=spi_speed_hz)
    try:
        return BMI088Board(SPITransport(bus, gyro_cs), acc_transport=SPITransport(bus, spi_device, dummy_bytes=1),
                           own_bus=None if simulated_imu is not None else bus, **options)
    except BaseException:
        if simulated_imu is None:
            bus.close()
        raise


def _twin_for(name: str, simulated_imu: Any, address: int | None = None) -> Any:
    if name == "icm20948":  # its aux I2C bus runs on the same clock
        return SimulatedICM20948(simulated_imu, address, clock=simulated_imu.clock)
    return _TWINS[name](simulated_imu, address)
