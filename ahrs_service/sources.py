"""Builds the configured sensor source: simulated or real I2C board, DroneCAN, simulator, log.

``source.type`` in the configuration picks one:

* ``simulated_i2c`` (default) — a simulated board (``source.board``) on the simulated I2C
  bus, fed by the motion simulator flying ``source.profile``; the very driver code that runs
  on hardware reads it.
* ``i2c`` — the real board on ``/dev/i2c-<source.i2c_bus>``.
* ``spi`` / ``simulated_spi`` — a FIFO board (``icm42688p``, ``icm20948``, ``bmi088``) on ``/dev/spidev<spi_bus>.<spi_device>``
  or on the simulated SPI bus with its twin; I2C FIFO boards take ``i2c`` / ``simulated_i2c``.
  ``source.drdy_gpio`` ("gpiochip0:17") wakes the loop on the FIFO watermark line (a
  simulated line on the simulated buses).
* ``simulated_can`` — a simulated DroneCAN IMU node on a python-can bus in this process.
* ``can`` — a DroneCAN IMU on ``source.can_interface`` / ``source.can_channel``.
* ``simulated`` — the motion simulator without any bus.
* ``recorded`` — an MCAP log or a BROAD HDF5 recording (``source.recorded_path``).
* ``mavlink`` — the autopilot's IMU (``source.mavlink_imu``) over its link
  (``source.mavlink_connection``), which the service also uses to talk to the autopilot.

The section's keys, defaults and checks are declared in :mod:`ahrs_service.source_settings`.
"""

from __future__ import annotations

from typing import Any

from ahrs_service.core.samples import ImuSource


def simulated_imu(source_cfg: dict[str, Any]):
    """The motion simulator with the error models of the configured board's parts."""
    from ahrs_service.drivers.boards import BOARDS
    from ahrs_service.drivers.sim.imu import MonotonicClock, SimulatedImu
    from ahrs_service.drivers.sim.motion import profile
    from ahrs_service.drivers.sim.sensor_model import PART_MODELS

    trajectory = profile(source_cfg["profile"], looping=source_cfg["loop_profile"])
    if any(source_cfg["vibration_mss"]) and source_cfg["vibration_hz"] > 0:
        from ahrs_service.drivers.sim.motion import Vibrating

        trajectory = Vibrating(trajectory, source_cfg["vibration_mss"], source_cfg["vibration_hz"])
    if source_cfg["sensor_errors"]:
        # analog(): the register devices quantise and saturate at their configured range
        gyr, acc, mag = (PART_MODELS[p].analog() for p in BOARDS[source_cfg["board"]].sensor_models)
    else:
        gyr = acc = mag = PART_MODELS["ideal"]
    models = {"gyr": gyr, "acc": acc, "mag": mag}
    return SimulatedImu(trajectory, models, clock=MonotonicClock(), seed=source_cfg["seed"])


def make_source(source_cfg: dict[str, Any], estimation_hz: float, system_id: int = 1,
                companion: bool = False) -> ImuSource:
    """An unopened source for the ``[source]`` section of the configuration (``system_id``:
    the service's MAVLink system id, its address on an autopilot link)."""
    kind = source_cfg["type"]
    if kind in ("spi", "simulated_spi") or (kind in ("i2c", "simulated_i2c")
                                             and _on_transport(source_cfg["board"])):
        return make_fifo_source(source_cfg)
    if kind == "simulated_i2c":
        from ahrs_service.drivers.boards import make_simulated_board

        return make_simulated_board(source_cfg["board"], simulated_imu(source_cfg),
                                    i2c_speed_hz=source_cfg["i2c_speed_hz"], **source_cfg["board_options"])
    if kind == "i2c":
        from ahrs_service.drivers.boards import make_board

        return make_board(source_cfg["board"], source_cfg["i2c_bus"], i2c_speed_hz=source_cfg["i2c_speed_hz"],
                          **source_cfg["board_options"])
    if kind == "simulated":
        from ahrs_service.drivers.sim.source import SimulatedSource

        return SimulatedSource(simulated_imu(source_cfg), rate_hz=estimation_hz)
    if kind in ("can", "simulated_can"):
        from ahrs_service.protocols.dronecan.imu_source import DroneCanConfig, DroneCanImuSource

        can_cfg = DroneCanConfig(
            interface=source_cfg["can_interface"],
            channel=source_cfg["can_channel"],
            bitrate=source_cfg["can_bitrate"],
            node_id=source_cfg["can_node_id"] or None,
        )
        if kind == "can":
            return DroneCanImuSource(can_cfg)
        return SimulatedCanSource(can_cfg, simulated_imu(source_cfg), estimation_hz)
    if kind == "recorded":
        from ahrs_service.recorded import RecordedSource

        return RecordedSource(source_cfg["recorded_path"], realtime=source_cfg["recorded_realtime"])
    if kind == "mavlink":
        return make_mavlink_source(source_cfg, system_id, companion)
    raise ValueError(f"source.type: unknown source {kind!r}")


def make_mavlink_source(source_cfg: dict[str, Any], system_id: int = 1, companion: bool = False) -> ImuSource:
    """The autopilot's IMU over a new autopilot link (opened with the source). The link listens
    to ``source.mavlink_autopilot_system_id``; when that is 0 and the service speaks as the
    autopilot's companion (``mavlink.identity``), to the system id they share, ``system_id``."""
    from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink
    from ahrs_service.protocols.mavlink.imu_source import MavlinkImuSource, parse_raw_scale

    link = AutopilotLink(source_cfg["mavlink_connection"], system_id=system_id,
                         autopilot_system_id=source_cfg.get("mavlink_autopilot_system_id", 0) or (system_id if companion else 0),
                         autopilot_component_id=source_cfg.get("mavlink_autopilot_component_id", 0))
    return MavlinkImuSource(link, message=source_cfg["mavlink_imu"], rate_hz=source_cfg["mavlink_imu_hz"],
                            raw_scale=parse_raw_scale(source_cfg["mavlink_raw_scale"]))


def _on_transport(board: str) -> bool:
    """True for a board of one part behind a register transport (SPI or I2C): a FIFO source."""
    from ahrs_service.drivers.boards import BOARDS

    return board in BOARDS and BOARDS[board].on_transport


def make_fifo_source(source_cfg: dict[str, Any]) -> ImuSource:
    """A FIFO board on SPI or I2C, real or simulated, with its data-ready line if configured."""
    from ahrs_service.drivers.boards import make_transport_board

    kind = source_cfg["type"]
    simulated = kind.startswith("simulated")
    imu = simulated_imu(source_cfg) if simulated else None
    board = make_transport_board(
        source_cfg["board"], kind.removeprefix("simulated_"), simulated_imu=imu,
        spi_bus=source_cfg["spi_bus"], spi_device=source_cfg["spi_device"],
        spi_mode=source_cfg["spi_mode"], spi_speed_hz=source_cfg["spi_speed_hz"],
        i2c_bus=source_cfg["i2c_bus"], i2c_speed_hz=source_cfg["i2c_speed_hz"],
        **source_cfg["board_options"])
    spec = source_cfg["drdy_gpio"]
    if spec:
        if simulated:
            from ahrs_service.drivers.sim.bus import twin_behind
            from ahrs_service.drivers.sim.drdy import SimulatedDataReadyLine

            # the line carries the watermark of the part that drives the rows (BMI088: the gyro's INT3)
            board.data_ready_line = SimulatedDataReadyLine(twin_behind(board.transport), imu.clock, name=spec)
        else:
            from ahrs_service.drivers.buses.drdy import GpiodLine

            board.data_ready_line = GpiodLine(spec)
    return board


class SimulatedCanSource(ImuSource):
    """A DroneCAN source plus, in this process, a simulated IMU node publishing on the same bus."""

    def __init__(self, can_cfg, imu, rate_hz: float) -> None:
        from ahrs_service.protocols.dronecan.imu_source import DroneCanImuSource

        super().__init__()
        self.can_cfg, self.imu, self.rate_hz = can_cfg, imu, rate_hz
        self.inner = DroneCanImuSource(can_cfg)
        self.diagnostics = self.inner.diagnostics
        self.may_have_backlog = self.inner.may_have_backlog
        self.node = None

    def open(self) -> None:
        from ahrs_service.protocols.dronecan.sim_node import SimulatedDroneCanImuNode

        self.inner.open()
        self.node = SimulatedDroneCanImuNode(self.can_cfg.open_bus(), self.imu, rate_hz=self.rate_hz)
        self.node.start()

    def read(self):
        return self.inner.read()

    def close(self) -> None:
        if self.node is not None:
            self.node.stop()
            self.node.bus.shutdown()
        self.inner.close()
