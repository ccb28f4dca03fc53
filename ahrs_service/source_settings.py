"""The ``[source]`` section of the configuration: which sensor input the service reads, and its checks.

The sources wiring (:mod:`ahrs_service.sources`) builds the source this section names; the
section's declaration and checks sit beside it. The board and bus checks read the drivers' one
board registry (:mod:`ahrs_service.drivers.boards`): a board that cannot be wired on the
configured bus, an option its parts do not have or a rate its bus cannot carry is refused when
the file is checked, not at start.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Any, Callable

from ahrs_service.core.paths import regular_file
from ahrs_service.core.settings import (
    ConfigError,
    Section,
    boolean,
    choice,
    file_path,
    finite_table,
    number,
    string,
    unreadable,
    vector3,
)
from ahrs_service.drivers.boards import board_names
from ahrs_service.drivers.sim.motion import profile_names
from ahrs_service.evaluation.hdf5_signature import has_hdf5_signature
from ahrs_service.logs.magic import starts_like_mcap
from ahrs_service.protocols.mavlink.imu_source import IMU_MESSAGES, parse_raw_scale
from ahrs_service.protocols.mavlink.settings import endpoint

__all__ = ["BOARDS", "MAVLINK_IMUS", "PROFILES", "SOURCE", "SOURCE_TYPES", "check_source_section"]

SOURCE_TYPES = ("simulated_i2c", "simulated_spi", "simulated_can", "simulated", "i2c", "spi", "can", "recorded",
                "mavlink")
#: source.mavlink_imu: the autopilot's IMU message
MAVLINK_IMUS = tuple(IMU_MESSAGES)
#: the board names source.board accepts: the drivers' one board registry
BOARDS = tuple(board_names())
#: source.profile: the simulator's built-in flights ("waypoints" needs keyframes no key can give)
PROFILES = tuple(name for name in profile_names() if name != "waypoints")

#: ``[source]``: the sensor input (:mod:`ahrs_service.sources` lists what each type reads)
SOURCE: Section = {
    "type": ("simulated_i2c", choice(SOURCE_TYPES)),
    "board": ("gy80", choice(BOARDS)),
    "i2c_bus": (1, number(0, 255, integer=True)),
    # the I2C clock the rate check assumes (FIFO boards): 100 kHz standard, 400 kHz fast mode
    "i2c_speed_hz": (400_000, number(10_000, 3_400_000, integer=True)),
    # SPI boards: /dev/spidev<spi_bus>.<spi_device>, clock mode 0-3, clock in Hz
    "spi_bus": (0, number(0, 255, integer=True)),
    "spi_device": (0, number(0, 255, integer=True)),
    "spi_mode": (3, number(0, 3, integer=True)),
    "spi_speed_hz": (8_000_000, number(10_000, 50_000_000, integer=True)),
    # FIFO watermark interrupt line "<chip>:<line>", e.g. "gpiochip0:17"; "" = timer polling
    "drdy_gpio": ("", string),
    # board options (addresses, ranges, rates), e.g. {gyro_rate_hz = 800}: docs/drivers.md
    "board_options": ({}, finite_table),
    "profile": ("validation", choice(PROFILES)),
    "loop_profile": (True, boolean),
    "sensor_errors": (True, boolean),
    # simulated sources: a sinusoidal vibration of the airframe, m/s² per body axis, at
    # vibration_hz (0: none): what VIBRATION measures (docs/simulator.md)
    "vibration_mss": ([0.0, 0.0, 0.0], vector3(0.0, 1000.0)),
    "vibration_hz": (0.0, number(0.0, 10_000.0)),
    "seed": (0, number(0, None, integer=True)),
    "can_interface": ("virtual", string),
    "can_channel": ("ahrs", string),
    "can_bitrate": (1_000_000, number(10_000, 8_000_000, integer=True)),
    "can_node_id": (0, number(0, 127, integer=True)),
    "recorded_path": ("", file_path(must_exist=True)),
    "recorded_realtime": (True, boolean),
    # source.type = "mavlink": the autopilot's IMU over its link (docs/autopilot.md); the
    # same connection carries TIMESYNC, ODOMETRY and the attitude monitor
    "mavlink_connection": ("udpin:127.0.0.1:14540", endpoint),
    "mavlink_imu": ("highres", choice(MAVLINK_IMUS)),
    "mavlink_imu_hz": (200.0, number(1.0, 2000.0)),
    # RAW_IMU counts -> m/s2, rad/s, uT per count; unset keys: ArduPilot's (mG, mrad/s, mgauss)
    "mavlink_raw_scale": ({}, finite_table),
    # the flight controller the link listens to (0: the first one heard); any other one's
    # HEARTBEATs are counted and reported, never adopted (docs/autopilot.md)
    "mavlink_autopilot_system_id": (0, number(0, 255, integer=True)),
    "mavlink_autopilot_component_id": (0, number(0, 255, integer=True)),
}


def check_source_section(section: dict[str, Any]) -> None:
    """The checked ``[source]`` section as a whole: the board on the bus ``source.type`` names,
    its options and bus rate (by building its drivers on no bus or a simulated one), the
    watermark line, the autopilot's raw scale, the recorded log for ``recorded``, the python-can
    interface for ``can``. Raises :class:`ConfigError` naming the key."""
    from ahrs_service.drivers.boards import BOARDS, buses_of

    bus = section["type"].removeprefix("simulated_")
    if bus in ("i2c", "spi") and bus not in buses_of(section["board"]):
        raise ConfigError(f"source.board: {section['board']!r} cannot be wired on {bus}; "
                          f"it supports {', '.join(buses_of(section['board']))}")
    if section["drdy_gpio"]:
        from ahrs_service.drivers.buses.drdy import parse_line_spec

        if section["board"] not in BOARDS or not BOARDS[section["board"]].on_transport \
                or not BOARDS[section["board"]].cls.HAS_WATERMARK_LINE:
            raise ConfigError(f"source.drdy_gpio: board {section['board']!r} has no FIFO watermark "
                              f"line; leave drdy_gpio empty (timer polling)")
        try:
            parse_line_spec(section["drdy_gpio"])
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    if section["board"] in BOARDS and BOARDS[section["board"]].on_transport and bus in ("i2c", "spi"):
        _check_fifo_board(section, bus)
    elif section["board_options"] and section["type"] in ("i2c", "simulated_i2c"):
        _check_board_options(section["board"], dict(section["board_options"]), section["i2c_speed_hz"])
    if section["mavlink_raw_scale"]:
        try:
            parse_raw_scale(section["mavlink_raw_scale"])
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    if section["type"] == "recorded":
        _check_recorded_path(section["recorded_path"])
    if section["type"] in ("can", "simulated_can"):
        _check_can_interface(section["can_interface"])


_RECORDED_HELP = "accepted: an .mcap flight log or a BROAD .hdf5 file"


def _check_recorded_path(path: str) -> None:
    """``source.recorded_path`` for ``source.type = "recorded"``: a readable regular file that
    starts like the format its suffix names (MCAP magic; HDF5 signature for .hdf5/.h5), so a
    directory or a file that is no log is refused here, not at start or by a run that plays
    nothing and exits 0."""
    key = "source.recorded_path"
    if not path:
        raise ConfigError(f"{key}: required when source.type = 'recorded'; {_RECORDED_HELP}")
    p = Path(path)
    hdf5 = p.suffix.lower() in (".hdf5", ".h5")
    try:
        with regular_file(p).open("rb") as f:
            head = f.read(8)
    except OSError as exc:
        raise ConfigError(f"{key}: {path!r} {unreadable(exc)}; {_RECORDED_HELP}") from None
    if not p.is_file():
        raise ConfigError(f"{key}: {path!r} is not a regular file; {_RECORDED_HELP}")
    if hdf5 and not has_hdf5_signature(p, head):
        raise ConfigError(f"{key}: {path!r} is not an HDF5 file (no HDF5 signature); {_RECORDED_HELP}")
    if not hdf5 and not starts_like_mcap(head):
        raise ConfigError(f"{key}: {path!r} is not an MCAP log (bad magic); {_RECORDED_HELP}")


def _check_can_interface(name: str) -> None:
    """``source.can_interface``: one of python-can's interface names (what ``can.Bus`` opens)."""
    from can.interfaces import VALID_INTERFACES  # python-can's ~0.2 s import: only for a CAN source

    if name not in VALID_INTERFACES:
        raise ConfigError(f"source.can_interface: {name!r} is not a python-can interface; accepted: "
                          f"{', '.join(sorted(VALID_INTERFACES))}")


def _option_kind(param: inspect.Parameter) -> str | None:
    """"an integer" or "a number" for a board option whose signature says so (its annotation,
    ``int | None`` included, else the type of its default); None for any other option."""
    annotation = param.annotation
    if isinstance(annotation, str):
        annotation = annotation.replace(" ", "").removesuffix("|None").removeprefix("None|")
    if annotation in (int, "int"):
        return "an integer"
    if annotation in (float, "float"):
        return "a number"
    default = param.default
    if isinstance(default, (int, float)) and not isinstance(default, bool):
        return "an integer" if isinstance(default, int) else "a number"
    return None


def _check_option_types(board: str, options: dict[str, Any], inits: tuple[Callable, ...]) -> None:
    """Each option's type against the board constructors' signatures (``inits``, later ones
    first): ``source.board_options.NAME: VALUE is not a number`` before any driver divides by it.
    Unknown names are left to the board's own check, which lists the valid ones."""
    params: dict[str, inspect.Parameter] = {}
    for init in inits:
        params.update(inspect.signature(init).parameters)
    for name, value in options.items():
        kind = _option_kind(params[name]) if name in params else None
        if kind is None:
            continue
        integer = kind == "an integer"
        if isinstance(value, bool) or not isinstance(value, int if integer else (int, float)):
            raise ConfigError(f"source.board_options.{name}: {value!r} is not {kind} (board {board!r})")


def _check_board_options(board: str, options: dict[str, Any], i2c_speed_hz: float = 400_000) -> None:
    """Each option's type against the board's signature, then its value by building the board's
    drivers (on no bus: their constructors only check and store), so that a range or rate the
    part does not have is refused here rather than at start."""
    from ahrs_service.drivers.boards import board_class
    from ahrs_service.drivers.boards.i2c import I2CBoard

    try:
        cls = board_class(board, options)
    except ValueError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None
    _check_option_types(board, options, (I2CBoard.__init__, cls.__init__))
    try:
        cls(None, i2c_speed_hz=i2c_speed_hz, **options)  # type: ignore[arg-type]
    except (ValueError, TypeError, OverflowError) as exc:
        msg = str(exc)  # the rate checks name their key already (odr_hz, acc_rate_hz …)
        raise ConfigError(msg if msg.startswith("source.") else f"source.board_options = {options!r}: {msg}") from None


def _check_fifo_board(section: dict[str, Any], bus: str) -> None:
    """Options and the bus-rate check of a FIFO board, on a simulated bus of the configured clock."""
    from ahrs_service.drivers.boards import make_transport_board
    from ahrs_service.drivers.sim.clock import ManualClock

    class _Quiet:  # a simulated part that only has to exist for the checks
        clock = ManualClock()

        @staticmethod
        def physics(t: float) -> dict:
            return {"gyr": (0.0, 0.0, 0.0), "acc": (0.0, 0.0, 0.0), "mag": (0.0, 0.0, 0.0)}

    from ahrs_service.drivers.boards import transport_board_class
    from ahrs_service.drivers.boards.transport import FifoBoard

    options = dict(section["board_options"])
    try:
        cls = transport_board_class(section["board"], options)
    except ValueError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None
    _check_option_types(section["board"], options, (FifoBoard.__init__, cls.__init__))
    cs = options.get("gyro_spi_device")  # bmi088's second chip select: an integer, like spi_device
    if cs is not None and (isinstance(cs, bool) or not isinstance(cs, int)):
        raise ConfigError(f"source.board_options.gyro_spi_device: {cs!r} is not an integer (board {section['board']!r})")
    try:
        real = not section["type"].startswith("simulated")
        name = (f"/dev/spidev{section['spi_bus']}" if bus == "spi" else f"/dev/i2c-{section['i2c_bus']}")
        make_transport_board(section["board"], bus, simulated_imu=_Quiet(), sim_bus_name=name if real else None,
                             spi_bus=section["spi_bus"], spi_device=section["spi_device"],
                             spi_speed_hz=section["spi_speed_hz"],
                             i2c_speed_hz=section["i2c_speed_hz"], **dict(section["board_options"]))
    except ValueError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith("source.") else f"source.board_options: {msg}") from None
    except TypeError as exc:
        raise ConfigError(f"source.board_options: {exc}") from None
