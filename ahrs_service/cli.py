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


#: top-level modules of the optional dependencies -> the extra that installs them (pyproject.toml)
OPTIONAL_MODULES = {
    "h5py": "recordings",
    "matplotlib": "analysis",
    "scikit_posthocs": "analysis",
    "tqdm": "analysis",
    "vqf": "peers",
    "imufusion": "peers",
    "ahrs": "peers",
    "spidev": "hardware",
    "gpiod": "hardware",
    "foxglove": "live",
}


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The extra that would install the module ``exc`` misses, or None if it is none of ours."""
    return OPTIONAL_MODULES.get((exc.name or "").split(".")[0])


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ModuleNotFoundError as exc:
        extra = missing_extra(exc)
        if extra is None:
            raise
        print(
            f"ahrs-service {args.command}: needs the optional package {exc.name!r}: "
            f"pip install 'ahrs-service[{extra}]'",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
