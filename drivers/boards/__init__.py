"""The board registry: every board name the configuration accepts, its class, the buses it
can be wired on and its default address — the one list config validation, the sources
wiring, the docs and the command line read (:func:`board_names`, :data:`BOARDS`).

Two kinds of board, one registry:

* boards whose parts sit on one I2C bus (:mod:`.i2c`: ``gy80``, ``minimu9v2``, ``mpu9250``),
  built by :func:`make_board` / :func:`make_simulated_board`;
* boards of one part behind a :class:`~ahrs_service.drivers.transport.RegisterTransport`
  (:mod:`.transport`: ``icm42688p`` on SPI or I2C, ``icm20948`` on SPI or I2C, ``bmi088`` on
  SPI: its accelerometer on ``spi_device``, its gyroscope on
  ``board_options.gyro_spi_device``, default ``spi_device + 1``), built by
  :func:`make_transport_board` on a real bus (``spi``: ``/dev/spidevB.C``; ``i2c``:
  ``/dev/i2c-N``) or on the simulated bus of that kind with the part's twin attached.

The parts themselves are in ``drivers/parts/``, their twins in ``drivers/sim/``. A board's
module is imported when its class is first asked for (:attr:`BoardSpec.cls`), so reading the
names (config validation at start-up) does not import every part and twin.
"""

from __future__ import annotations

import importlib
import inspect
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from ahrs_service.drivers.boards.i2c import I2CBoard
    from ahrs_service.drivers.boards.transport import FifoBoard

_I2C = "ahrs_service.drivers.boards.i2c"
_TRANSPORT = "ahrs_service.drivers.boards.transport"


@dataclass(frozen=True)
class BoardSpec:
    """One board name: where its class is (``module``, ``class_name``), the buses it can be
    wired on ("i2c", "spi"), the simulator's error models of its gyroscope, accelerometer and
    magnetometer (names in :data:`~ahrs_service.drivers.sim.sensor_model.PART_MODELS`;
    "ideal" where the board has none), and the I2C address of its part when it is wired on a
    transport (the I2C boards take their parts' addresses as options)."""

    module: str
    class_name: str
    buses: tuple[str, ...]
    sensor_models: tuple[str, str, str]
    default_address: int | None = None

    @property
    def on_transport(self) -> bool:
        """True for a board of one part behind a register transport (SPI or I2C)."""
        return self.module == _TRANSPORT

    @property
    def cls(self) -> type[I2CBoard] | type[FifoBoard]:
        """The board's class (its module imported on first use)."""
        return getattr(importlib.import_module(self.module), self.class_name)


#: every board name → its :class:`BoardSpec`, in the order the documentation lists them
BOARDS: dict[str, BoardSpec] = {
    "gy80": BoardSpec(_I2C, "GY80", ("i2c",), ("L3G4200D", "ADXL345", "HMC5883L")),
    "minimu9v2": BoardSpec(_I2C, "MinIMU9v2", ("i2c",), ("L3GD20", "LSM303DLHC_ACC", "LSM303DLHC_MAG")),
    "mpu9250": BoardSpec(_I2C, "MPU9250Board", ("i2c",), ("MPU9250_GYRO", "MPU9250_ACC", "AK8963")),
    "icm42688p": BoardSpec(_TRANSPORT, "ICM42688PBoard", ("spi", "i2c"), ("ICM42688P_GYRO", "ICM42688P_ACC", "ideal"),
                           default_address=0x68),
    "icm20948": BoardSpec(_TRANSPORT, "ICM20948Board", ("spi", "i2c"), ("ICM20948_GYRO", "ICM20948_ACC", "AK09916"),
                          default_address=0x68),
    "bmi088": BoardSpec(_TRANSPORT, "BMI088Board", ("spi",), ("BMI088_GYRO", "BMI088_ACC", "ideal"),
                        default_address=0x00),
}


def transport_boards() -> dict[str, tuple[type[FifoBoard], tuple[str, ...], int]]:
    """The boards of one part behind a register transport: name → (class, buses, default I2C address)."""
    return {name: (spec.cls, spec.buses, spec.default_address)  # type: ignore[misc]
            for name, spec in BOARDS.items() if spec.on_transport}


def __getattr__(name: str) -> Any:
    # TRANSPORT_BOARDS names the classes, so it is built on first use, not at import
    if name == "TRANSPORT_BOARDS":
        return transport_boards()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def board_names() -> list[str]:
    """Every board name the configuration accepts (``source.board``)."""
    return list(BOARDS)


def i2c_board_names() -> list[str]:
    """The boards whose parts sit on one I2C bus (:func:`make_board`, :func:`make_simulated_board`)."""
    return [name for name, spec in BOARDS.items() if not spec.on_transport]


#: the name this list had before the registry held every board
all_board_names = board_names


def buses_of(name: str) -> tuple[str, ...]:
    """The buses board ``name`` can be wired on ("i2c", "spi")."""
    return BOARDS[name].buses if name in BOARDS else ("i2c",)


def board_class(name: str, options: dict[str, Any]) -> type[I2CBoard]:
    """The I2C board class for ``name``; ValueError naming unknown boards or options."""
    names = i2c_board_names()
    if name not in names:
        raise ValueError(f"unknown I2C board {name!r}; available: {', '.join(names)}")
    from ahrs_service.drivers.boards.i2c import I2CBoard

    cls = BOARDS[name].cls
    allowed = {p for c in (cls, I2CBoard) for p in inspect.signature(c.__init__).parameters
               if p not in ("self", "bus", "kw", "own_bus", "i2c_speed_hz")}
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"board {name!r}: unknown option(s) {', '.join(unknown)}; "
                         f"valid: {', '.join(sorted(allowed))}")
    return cls  # type: ignore[return-value]


def make_board(name: str, bus_number: int = 1, i2c_speed_hz: float = 400_000, **options: Any) -> I2CBoard:
    """An I2C board on the hardware bus ``/dev/i2c-<bus_number>`` (not opened yet: call ``open()``).

    options: the board's addresses, ranges and rates (e.g. ``gyro_rate_hz=400``); an unknown
    option raises ValueError listing the valid ones.
    """
    from ahrs_service.drivers.buses.i2c import SMBusI2C

    cls = board_class(name, options)
    return cls(SMBusI2C(bus_number), own_bus=True, i2c_speed_hz=i2c_speed_hz, **options)


def make_simulated_board(name: str, simulated_imu: Any, i2c_speed_hz: float = 400_000,
                         **options: Any) -> I2CBoard:
    """An I2C board whose parts are simulated register devices fed by ``simulated_imu``.

    simulated_imu: an object with ``physics(t) -> dict`` and ``clock`` (``now()`` in s), such
    as ``ahrs_service.drivers.sim.SimulatedImu``. The board (not opened yet) has its
    :class:`~ahrs_service.drivers.sim.bus.SimulatedI2CBus` as ``board.bus``, for fault injection.
    """
    from ahrs_service.drivers.sim.bus import SimulatedI2CBus

    cls = board_class(name, options)
    bus = SimulatedI2CBus(simulated_imu.clock, name=f"sim-i2c[{name}]")
    cls.attach_simulated(bus, simulated_imu, **options)
    return cls(bus, i2c_speed_hz=i2c_speed_hz, **options)


def transport_board_class(name: str, options: dict[str, Any]) -> type[FifoBoard]:
    """The FIFO board class for ``name``; ValueError naming unknown options."""
    from ahrs_service.drivers.boards.transport import FifoBoard

    cls = BOARDS[name].cls
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
    kinds = BOARDS[name].buses
    if bus_kind not in kinds:
        raise ValueError(f"board {name!r} cannot be wired on {bus_kind}; it supports {', '.join(kinds)}")
    addr = BOARDS[name].default_address if address is None else int(address)
    if bus_kind == "spi":
        if simulated_imu is not None:
            from ahrs_service.drivers.sim.bus import SimulatedSPIBus

            bus = SimulatedSPIBus(simulated_imu.clock, name=sim_bus_name or f"sim-spi{spi_bus}",
                                  speed_hz=spi_speed_hz)
            bus.attach(_twin_for(name, simulated_imu), spi_device)
        else:
            from ahrs_service.drivers.buses.spi import SpidevSPI

            bus = SpidevSPI(spi_bus, (spi_device,), mode=spi_mode, speed_hz=spi_speed_hz)
        transport = SPITransport(bus, spi_device)
    else:
        if simulated_imu is not None:
            from ahrs_service.drivers.sim.bus import SimulatedI2CBus

            bus = SimulatedI2CBus(simulated_imu.clock, name=sim_bus_name or f"sim-i2c[{name}]")
            bus.attach(_twin_for(name, simulated_imu, addr))
        else:
            from ahrs_service.drivers.buses.i2c import SMBusI2C

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
    from ahrs_service.drivers.boards.transport import BMI088Board
    from ahrs_service.drivers.transport import SPITransport

    gyro_cs = int(options.pop("gyro_spi_device", spi_device + 1))
    if gyro_cs == spi_device:
        raise ValueError(f"bmi088: gyro_spi_device must differ from source.spi_device ({spi_device}): "
                         f"each die has its own chip select")
    if simulated_imu is not None:
        from ahrs_service.drivers.sim.bmi088 import SimulatedBMI088Accel, SimulatedBMI088Gyro
        from ahrs_service.drivers.sim.bus import SimulatedSPIBus

        bus = SimulatedSPIBus(simulated_imu.clock, name=sim_bus_name or f"sim-spi{spi_bus}",
                              speed_hz=spi_speed_hz)
        bus.attach(SimulatedBMI088Accel(simulated_imu), spi_device)
        bus.attach(SimulatedBMI088Gyro(simulated_imu), gyro_cs)
    else:
        from ahrs_service.drivers.buses.spi import SpidevSPI

        bus = SpidevSPI(spi_bus, (spi_device, gyro_cs), mode=spi_mode, speed_hz=spi_speed_hz)
    try:
        return BMI088Board(SPITransport(bus, gyro_cs), acc_transport=SPITransport(bus, spi_device, dummy_bytes=1),
                           own_bus=None if simulated_imu is not None else bus, **options)
    except BaseException:
        if simulated_imu is None:
            bus.close()
        raise


def _twin_for(name: str, simulated_imu: Any, address: int | None = None) -> Any:
    from ahrs_service.drivers.sim.icm20948 import SimulatedICM20948
    from ahrs_service.drivers.sim.icm42688p import SimulatedICM42688P

    if name == "icm20948":  # its aux I2C bus runs on the same clock
        return SimulatedICM20948(simulated_imu, address, clock=simulated_imu.clock)
    return SimulatedICM42688P(simulated_imu, address)
