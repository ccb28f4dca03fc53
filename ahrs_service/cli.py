"""The ``ahrs-service`` command line: ``run``, ``evaluate``, ``log``, ``replay`` and friends.

Each part of the project adds its own subcommands through an ``add_subcommands(subparsers)``
function; every subparser sets ``func`` to a callable taking the parsed arguments and
returning the exit code.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
import threading
import types
from pathlib import Path
from typing import Callable

from ahrs_service.execution import RunnerError

# modules that contribute subcommands, in the order they appear in --help
_COMMAND_MODULES = [
    "ahrs_service.service_cli",
    "ahrs_service.evaluation.command",
    "ahrs_service.log_commands",
    "ahrs_service.calibration.command",
]


def add_offline_options(parser: argparse.ArgumentParser, offline_help: str) -> None:
    """``--offline`` and ``--offline-blend``, shared by ``evaluate`` and ``log replay``
    (``ahrs_service.estimators.offline``)."""
    parser.add_argument("--offline", action="store_true", help=offline_help)
    parser.add_argument(
        "--offline-blend",
        type=float,
        default=None,
        metavar="S",
        help="with --offline: time constant of the fusion weights 1 - exp(-t/S), seconds (default 10)",
    )


def lazy_command(target: str) -> Callable[[argparse.Namespace], int]:
    """A subcommand's ``func`` that imports ``"module:function"`` only when it runs, so that
    ``ahrs-service --help`` and the other commands do not import what they do not use."""
    module, _, name = target.partition(":")

    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(module), name)(args)

    return run


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ahrs-service", description="MAVLink AHRS companion service: run, evaluate, log tools, replay, calibration."
    )
    parser.add_argument("--version", action="version", version=f"ahrs-service {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in _COMMAND_MODULES:
        importlib.import_module(name).add_subcommands(sub)
    return parser


def package_version() -> str:
    """The installed distribution's version (pyproject.toml's ``version``), or "unknown" when
    the package runs from a source tree that was never installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("ahrs-service")
    except PackageNotFoundError:
        return "unknown"


#: top-level modules of the optional dependencies -> the extra that installs them (pyproject.toml)
OPTIONAL_MODULES = {
    "h5py": "recordings",
    "matplotlib": "analysis",
    "scikit_posthocs": "analysis",
    "scipy": "analysis",
    "tqdm": "analysis",
    "vqf": "peers",
    "imufusion": "peers",
    "ahrs": "peers",
    "spidev": "hardware",
    "gpiod": "hardware",
    "foxglove": "live",
    "dask": "fleet",
    "distributed": "fleet",
    "optuna": "fleet",
    "pyarrow": "fleet",
}


def missing_extra(exc: ModuleNotFoundError) -> str | None:
    """The extra that would install the module ``exc`` misses, or None if it is none of ours."""
    return OPTIONAL_MODULES.get((exc.name or "").split(".")[0])


def main(argv: list[str] | None = None) -> int:
    """Runs one subcommand (:func:`_main`). Ctrl-C (SIGINT) or SIGTERM ends any command with
    one line, exit status 130 or 143 (``run`` handles both itself once its loop is set up: it
    stops and prints its summary).

    The signal unwinds the command as a KeyboardInterrupt; code that swallows it (a library's
    ``except BaseException``, a C call that clears the error it was raised in) would let the
    command finish as if nothing happened, exit status 0. The signal is therefore also noted
    when it arrives, and a command that returns after one still ends with the same line and
    status."""
    global _received
    _received = None
    handlers = threading.current_thread() is threading.main_thread()  # main thread only
    previous_term = signal.signal(signal.SIGTERM, _interrupt) if handlers else None
    previous_alarm = signal.signal(signal.SIGALRM, _interrupt) if handlers else None  # a deferred one
    # SIGINT is left alone where it is ignored (a shell's background job) or handled by the caller
    own_int = handlers and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    if own_int:
        signal.signal(signal.SIGINT, _interrupt)
    try:
        rc = _main(argv)
    except KeyboardInterrupt as exc:
        return _interrupted("SIGTERM" if isinstance(exc, Terminated) else "SIGINT")
    finally:
        if handlers:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            signal.signal(signal.SIGTERM, previous_term)
            signal.signal(signal.SIGALRM, previous_alarm)
        if own_int:
            signal.signal(signal.SIGINT, signal.default_int_handler)
    if _received is not None:  # the interrupt was swallowed on its way up
        return _interrupted(_received)
    return rc


def _interrupted(name: str) -> int:
    print(f"ahrs-service: interrupted ({name}) before the command finished", file=sys.stderr)
    return 143 if name == "SIGTERM" else 130


def _main(argv: list[str] | None) -> int:
    """Runs one subcommand. A path that cannot be opened (missing, a directory where a file is
    expected, no permission), a missing extra, an execution layer that cannot start (a
    Dask scheduler out of reach, a bad ``--workers``) or no folder numba can cache the kernels
    in ends any command with one line, exit status 2."""
    try:
        parser = build_parser()  # imports the command modules, whose numba kernels set up their cache
    except RuntimeError as exc:
        if not str(exc).startswith("cannot cache function"):
            raise
        print(f"ahrs-service: {numba_cache_error(exc)}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
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
    except OSError as exc:
        print(f"ahrs-service: {path_error(exc)}", file=sys.stderr)
        return 2
    except RunnerError as exc:
        print(f"ahrs-service {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except RuntimeError as exc:  # a kernel module imported only by this command (lazy_command)
        if not str(exc).startswith("cannot cache function"):
            raise
        print(f"ahrs-service: {numba_cache_error(exc)}", file=sys.stderr)
        return 2
    except ValueError as exc:  # bad input a command found (an unknown estimator, a bad value)
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"ahrs-service {args.command}: error: {text}", file=sys.stderr)
        return 2


class Terminated(KeyboardInterrupt):
    """SIGTERM (until ``run`` installs its own handler): unwinds like Ctrl-C, so that files being
    written are closed or removed (``log recover``) and the command ends with one line."""


#: the signal that interrupted the running command, noted by its handler (None: none yet)
_received: str | None = None


#: functions Python calls from C through ctypes while numba compiles (llvmlite's object-cache
#: hooks): an exception cannot leave them, Python prints it as "ignored" with its traceback
_NATIVE_CALLBACKS = frozenset({"_raw_object_cache_notify", "_raw_object_cache_getbuffer"})
#: how soon an interrupt that came inside one of them is raised again, s
_CALLBACK_RETRY_S = 0.02


def _interrupt(signum: int, frame: types.FrameType | None) -> None:
    """SIGINT, SIGTERM (and SIGALRM, their deferred delivery): notes the signal and raises it
    as KeyboardInterrupt (Terminated for SIGTERM), unless Python code called from C is running,
    where it is raised again a moment later."""
    global _received
    if signum == signal.SIGTERM:
        _received = "SIGTERM"
    elif signum == signal.SIGINT:
        _received = "SIGINT"
    if _received is None:
        return  # a SIGALRM of someone else's
    if _in_native_callback(frame):
        signal.setitimer(signal.ITIMER_REAL, _CALLBACK_RETRY_S)
        return
    raise Terminated() if _received == "SIGTERM" else KeyboardInterrupt


def _in_native_callback(frame: types.FrameType | None) -> bool:
    while frame is not None:
        if frame.f_code.co_name in _NATIVE_CALLBACKS and "llvmlite" in frame.f_code.co_filename:
            return True
        frame = frame.f_back
    return False


def numba_cache_error(exc: RuntimeError) -> str:
    """One line for numba's "cannot cache function ...: no locator available": no folder numba
    may cache the estimator kernels in is writable for this user (``__pycache__`` beside the
    installed sources, ``$NUMBA_CACHE_DIR``, numba's per-user cache folder)."""
    import os

    where = os.environ.get("NUMBA_CACHE_DIR")
    tried = f"NUMBA_CACHE_DIR={where}" if where else "NUMBA_CACHE_DIR is not set"
    return (f"cannot cache the estimator kernels: no writable cache folder for this user "
            f"({tried}; __pycache__ beside the installed package is not writable); set "
            f"NUMBA_CACHE_DIR to a folder this user can write (docs/systemd.md)")


def path_error(exc: OSError) -> str:
    """One line for an OSError about a path: ``PATH: what is wrong``."""
    what = {FileNotFoundError: "does not exist", IsADirectoryError: "is a directory, not a file",
            NotADirectoryError: "is not a directory", PermissionError: "permission denied"}
    reason = next((text for cls, text in what.items() if isinstance(exc, cls)), None)
    if isinstance(exc, FileNotFoundError) and exc.filename is not None:
        parent = Path(exc.filename).parent
        if not parent.is_dir():  # a file to be written: its folder is what is missing
            reason = f"its folder {parent} does not exist"
    reason = reason or exc.strerror or str(exc)
    reason = reason.splitlines()[0] if reason else type(exc).__name__
    return f"{exc.filename}: {reason}" if exc.filename is not None else reason


if __name__ == "__main__":
    sys.exit(main())
