"""COMMAND_LONG handling: a table of command handlers, each answering a MAV_RESULT.

The component answers every COMMAND_LONG addressed to it with one COMMAND_ACK
(https://mavlink.io/en/services/command.html). Handlers are plain functions
``handler(cmd: Command) -> CommandResult``; commands nobody registered are answered
MAV_RESULT_UNSUPPORTED. The component itself registers MAV_CMD_SET_MESSAGE_INTERVAL,
MAV_CMD_GET_MESSAGE_INTERVAL and MAV_CMD_REQUEST_MESSAGE; this module provides
MAV_CMD_PREFLIGHT_CALIBRATION on top of service callbacks.

Handlers run inside ``MavlinkComponent.poll`` on the service's thread and must return
quickly: a long job (a 2 s gyro calibration) is started and answered ACCEPTED or
IN_PROGRESS, and its outcome reported later with a STATUSTEXT.

Which commands change something (:data:`WRITE_COMMANDS`) and who sent them (:class:`Sender`:
ids and whether the signature was verified) is what the component's write rules and its
record of accepted writes go by (docs/mavlink.md, "Security"). :class:`ArmingState` follows
an autopilot's HEARTBEATs, for the rule that no calibration starts while it is armed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

from ahrs_service.protocols.mavlink.dialect import mavlink


#: the commands that change something on this component; the others only read
WRITE_COMMANDS: frozenset[int] = frozenset({
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL,
    mavlink.MAV_CMD_PREFLIGHT_CALIBRATION,
})


@dataclass(frozen=True)
class Sender:
    """Who sent a message: its system and component id, and whether it carried a signature
    this component verified with its key (always False on a link without signing)."""

    system_id: int
    component_id: int
    signed: bool = False

    @classmethod
    def of(cls, msg: Any) -> "Sender":
        """The sender of a received pymavlink message."""
        return cls(int(msg.get_srcSystem()), int(msg.get_srcComponent()), bool(msg.get_signed()))

    def __str__(self) -> str:
        return f"{self.system_id}/{self.component_id} {'signed' if self.signed else 'unsigned'}"


@dataclass(frozen=True)
class Command:
    """A received command: id, its seven parameters, and who sent it (``signed``: with a
    verified signature)."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    source_system: int
    source_component: int
    confirmation: int = 0
    signed: bool = False

    @classmethod
    def from_command_long(cls, msg: "mavlink.MAVLink_command_long_message") -> "Command":
        return cls(
            int(msg.command),
            (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7),
            msg.get_srcSystem(), msg.get_srcComponent(), int(msg.confirmation), bool(msg.get_signed()),
        )

    @property
    def sender(self) -> Sender:
        return Sender(self.source_system, self.source_component, self.signed)


@dataclass(frozen=True)
class CommandResult:
    """MAV_RESULT for the ACK, and an optional text sent as STATUSTEXT with the ACK."""

    result: int
    text: str = ""


Handler = Callable[[Command], CommandResult]
#: calibration callback: gets the command's parameter value (e.g. 1 for gyro) and returns
#: (MAV_RESULT, human-readable text)
CalibrationCallback = Callable[[int], tuple[int, str]]
#: calibration guard: gets the sensor ("gyro", "mag" or "accel") and returns why its
#: calibration may not start now, "" when it may
CalibrationGuard = Callable[[str], str]


class CommandTable:
    """Maps MAV_CMD ids to handlers."""

    def __init__(self) -> None:
        self._handlers: dict[int, Handler] = {}

    def register(self, command: int, handler: Handler) -> None:
        """Sets the handler of MAV_CMD ``command`` (replacing any earlier one)."""
        self._handlers[int(command)] = handler

    def supported(self) -> list[int]:
        return sorted(self._handlers)

    def dispatch(self, cmd: Command) -> CommandResult:
        """Runs the handler of ``cmd``; UNSUPPORTED when there is none. Handler errors propagate."""
        handler = self._handlers.get(cmd.command)
        if handler is None:
            return CommandResult(mavlink.MAV_RESULT_UNSUPPORTED)
        return handler(cmd)


def encode_command_ack(cmd: Command, result: CommandResult) -> "mavlink.MAVLink_command_ack_message":
    """COMMAND_ACK for ``cmd``, addressed to its sender (progress 0, result_param2 0)."""
    return mavlink.MAVLink_command_ack_message(
        cmd.command, result.result, 0, 0, cmd.source_system, cmd.source_component
    )


def preflight_calibration_handler(gyro: CalibrationCallback | None, mag: CalibrationCallback | None = None,
                                  accel: CalibrationCallback | None = None, *,
                                  guard: CalibrationGuard | None = None) -> Handler:
    """Handler of MAV_CMD_PREFLIGHT_CALIBRATION.

    param1 = 1 → ``gyro(1)``; param2 ≠ 0 → ``mag(param2)``; param5 ≠ 0 → ``accel(param5)``.
    A sensor without callback, gyro temperature calibration (param1 = 3) and the
    baro/RC/ESC/airspeed calibrations (param3, 4, 6, 7) are UNSUPPORTED. More than one sensor in
    one command is DENIED (MAVLink: one sensor per message), as is a command selecting none.
    ``guard(sensor)`` runs before the callback: a reason it returns (the vehicle moves, an
    autopilot is armed) answers TEMPORARILY_REJECTED with that reason, and the callback is not
    called. The callback decides everything else.
    """

    def handle(cmd: Command) -> CommandResult:
        p = cmd.params
        if not all(math.isfinite(v) for v in p):
            return CommandResult(mavlink.MAV_RESULT_DENIED, "calibration: parameters not finite")
        selected = [(i, int(round(p[i]))) for i in (0, 1, 2, 3, 4, 5, 6) if round(p[i]) != 0]
        if not selected:
            return CommandResult(mavlink.MAV_RESULT_DENIED, "calibration: no sensor selected")
        if len(selected) > 1:
            return CommandResult(mavlink.MAV_RESULT_DENIED, "calibration: one sensor per command")
        index, action = selected[0]
        callback = {0: gyro if action == 1 else None, 1: mag, 4: accel}.get(index)
        if callback is None:
            return CommandResult(mavlink.MAV_RESULT_UNSUPPORTED)
        sensor = _CALIBRATED_SENSOR[index]
        refusal = guard(sensor) if guard is not None else ""
        if refusal:
            return CommandResult(mavlink.MAV_RESULT_TEMPORARILY_REJECTED, f"{sensor} calibration refused: {refusal}")
        result, text = callback(action)
        return CommandResult(int(result), str(text))

    return handle


#: PREFLIGHT_CALIBRATION parameter index → the sensor it calibrates (the supported ones)
_CALIBRATED_SENSOR = {0: "gyro", 1: "mag", 4: "accel"}


def calibrated_sensor(cmd: Command) -> str:
    """The sensor a MAV_CMD_PREFLIGHT_CALIBRATION selects ("gyro", "mag" or "accel"), "" when
    it selects none of them, several, or another calibration (what the handler refuses)."""
    p = cmd.params
    if cmd.command != mavlink.MAV_CMD_PREFLIGHT_CALIBRATION or not all(math.isfinite(v) for v in p):
        return ""
    selected = [(i, int(round(p[i]))) for i in range(7) if round(p[i]) != 0]
    if len(selected) != 1:
        return ""
    index, action = selected[0]
    if index == 0 and action != 1:
        return ""
    return _CALIBRATED_SENSOR.get(index, "")


class ArmingState:
    """Whether an autopilot says it is armed, from its HEARTBEATs (base_mode
    MAV_MODE_FLAG_SAFETY_ARMED), as PX4 and ArduPilot refuse calibrations while armed.

    :meth:`on_heartbeat` is an ``AutopilotLink.subscribe`` sink (the link's reader thread);
    :attr:`armed` is read on the loop thread: None before the autopilot's first HEARTBEAT.
    The last word stands while the link is silent: an autopilot that went quiet while armed
    may still be flying.
    """

    def __init__(self) -> None:
        self.armed: bool | None = None
        self.heartbeats = 0

    def on_heartbeat(self, msg: Any, rx_ns: int = 0) -> None:
        """One HEARTBEAT of the autopilot (``rx_ns``, its arrival, is not needed)."""
        # one attribute store: the loop thread reads a whole value, never a torn one
        self.armed = bool(int(msg.base_mode) & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        self.heartbeats += 1
