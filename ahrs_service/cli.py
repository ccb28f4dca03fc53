"""The ``ahrs-service`` command line: ``run``, ``evaluate``, ``log``, ``replay`` and friends.

Each part of the project adds its own subcommands through an ``add_subcommands(subparsers)``
function; every subparser sets ``func`` to a callable taking the parsed arguments and
returning the exit code.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# modules that contribute subcommands, in the order they appear in --help
_COMMAND_MODULES = [
    "ahrs_service.service_cli",
    "ahrs_service.evaluation.command",
    "ahrs_service.logs.command",
    "ahrs_service.calibration.command",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ahrs-service", description="MAVLink AHRS companion service: run, evaluate, log tools, replay, calibration."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).add_subcommands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
