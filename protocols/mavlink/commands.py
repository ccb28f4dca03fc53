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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from ahrs_service.protocols.mavlink.dialect import mavlink


@dataclass(frozen=True)
class Command:
    """A received command: id, its seven parameters, and who sent it."""

    command: int
    params: tuple[float, float, float, float, float, float, float]
    source_system: int
    source_component: int
    confirmation: int = 0

    @classmethod
    def from_command_long(cls, msg: "mavlink.MAVLink_command_long_message") -> "Command":
        return cls(
            int(msg.command),
            (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7),
            msg.get_srcSystem(), msg.get_srcComponent(), int(msg.confirmation),
        )


@dataclass(frozen=True)
class CommandResult:
    """MAV_RESULT for the ACK, and an optional text sent as STATUSTEXT with the ACK."""

    result: int
    text: str = ""


Handler = Callable[[Command], CommandResult]
#: calibration callback: gets the command's parameter value (e.g. 1 for gyro) and returns
#: (MAV_RESULT, human-readable text)
CalibrationCallback = Callable[[int], tuple[int, str]]


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
                                  accel: CalibrationCallback | None = None) -> Handler:
    """Handler of MAV_CMD_PREFLIGHT_CALIBRATION.

    param1 = 1 → ``gyro(1)``; param2 ≠ 0 → ``mag(param2)``; param5 ≠ 0 → ``accel(param5)``.
    A sensor without callback, gyro temperature calibration (param1 = 3) and the
    baro/RC/ESC/airspeed calibrations (param3, 4, 6, 7) are UNSUPPORTED. More than one sensor in
    one command is DENIED (MAVLink: one sensor per message), as is a command selecting none.
    The callback decides everything else — e.g. TEMPORARILY_REJECTED when not at rest.
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
        result, text = callback(action)
        return CommandResult(int(result), str(text))

    return handle
