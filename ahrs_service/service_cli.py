"""``ahrs-service run``, ``ahrs-service config`` and ``ahrs-service compile``."""

from __future__ import annotations

import argparse
import logging
import os
import sys

from ahrs_service import config as config_mod


#: the longest ``run --duration``, s (ten years): beyond it the deadline in ns overflows
MAX_DURATION_S = 10 * 365 * 86400.0


def duration_s(text: str) -> float:
    """``run --duration``: a finite number of seconds in (0, MAX_DURATION_S]. NaN started the
    service and then failed ("cannot convert float NaN to integer"), inf and 1e308 ended in an
    OverflowError traceback, 0 and negative values ran for no time and exited 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (0.0 < value <= MAX_DURATION_S):  # False for NaN too
        raise argparse.ArgumentTypeError(
            f"{text!r}: accepted: a number of seconds above 0 and at most {MAX_DURATION_S:g} (ten years); "
            f"leave --duration out to run until SIGTERM/SIGINT")
    return value


def add_subcommands(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run the service (embedded default: simulated GY-80, MAVLink UDP 127.0.0.1:14550)")
    run.add_argument("-c", "--config", help="TOML configuration file (default: the embedded default)")
    run.add_argument("--duration", type=duration_s, default=None,
                     help="stop after this many seconds, > 0 (default: run until SIGTERM/SIGINT)")
    run.add_argument("--log-dir", help="override log.directory")
    run.add_argument("--no-log", action="store_true", help="do not write an MCAP log")
    run.add_argument("--live", action="store_true", help="serve the Foxglove live view (sets live.enabled; extra 'live')")
    run.add_argument("--realtime-priority", type=int, default=None, metavar="N",
                     help="real-time priority 1-99 of the estimation loop's thread (sets service.realtime_priority; "
                          "0 off; docs/systemd.md)")
    run.add_argument("--lock-memory", action="store_true", help="lock the process's memory (sets service.lock_memory)")
    run.add_argument("-v", "--verbose", action="store_true")
    run.set_defaults(func=cmd_run)

    cfg = sub.add_parser("config", help="check a configuration file or print the default one")
    group = cfg.add_mutually_exclusive_group(required=True)
    group.add_argument("--check", metavar="FILE", help="validate FILE and print the effective configuration")
    group.add_argument("--print-default", action="store_true", help="print the embedded default configuration")
    cfg.set_defaults(func=cmd_config)

    comp = sub.add_parser(
        "compile",
        help="compile the estimator kernels into numba's cache (before a first start: ExecStartPre)",
        description=(
            "Compiles, or loads from numba's on-disk cache, the kernels the service runs with the "
            "given estimators (default: the configured one), so that a start or a reload does not "
            "compile. The cache is $NUMBA_CACHE_DIR when set (the systemd unit sets it), else "
            "__pycache__ beside the installed sources; run it as the user the service runs as."
        ),
    )
    comp.add_argument("estimators", nargs="*", metavar="NAME", help="estimators to compile (default: the configured one)")
    comp.add_argument("-c", "--config", help="TOML configuration whose estimator is compiled (default: the embedded default)")
    comp.add_argument("--all", action="store_true", help="every estimator (a later reload to any of them then compiles nothing)")
    comp.add_argument("--nice", type=int, default=0, metavar="N",
                      help="lower this process's CPU priority by N (the service's reload child uses 5)")
    comp.set_defaults(func=cmd_compile)

    lay = sub.add_parser("foxglove-layout", help="print the Foxglove layout for the live view and the logs (JSON)")
    lay.set_defaults(func=cmd_foxglove_layout)


def cmd_foxglove_layout(args: argparse.Namespace) -> int:
    from ahrs_service.foxglove_layout import shipped_layout_json

    sys.stdout.write(shipped_layout_json())
    return 0


def cmd_compile(args: argparse.Namespace) -> int:
    from ahrs_service import estimators, kernels

    try:
        names = estimators.names() if args.all else list(args.estimators)
        if not names:
            names = [config_mod.load(args.config).estimator["name"]]
        for name in names:
            estimators.get(name)  # an unknown name is refused before anything compiles
    except (config_mod.ConfigError, ValueError) as exc:
        print(f"ahrs-service compile: error: {exc}", file=sys.stderr)
        return 2
    if args.nice:
        os.nice(args.nice)
    for name in names:
        print(f"{name}: ready in {kernels.warm_up(name):.1f} s (compiled, or loaded from the cache)", flush=True)
    return 0


def cmd_config(args: argparse.Namespace) -> int:
    try:
        cfg = config_mod.load(args.check) if args.check else config_mod.load(None)
        warnings = config_mod.check_endpoint_hosts(cfg) if args.check else []
    except config_mod.ConfigError as exc:
        print(f"ahrs-service: configuration error: {exc}", file=sys.stderr)
        return 2
    for text in warnings:  # valid, but not reachable now: the file is fine, exit 0
        print(f"ahrs-service: warning: {text}", file=sys.stderr)
    print(config_mod.to_toml(cfg.raw))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        log_overrides: dict[str, object] = {}
        if args.log_dir is not None:  # "" too: log.directory's check refuses it rather than ignoring it
            log_overrides["directory"] = args.log_dir
        if args.no_log:
            log_overrides["enabled"] = False
        overrides: dict[str, dict[str, object]] = {}
        if log_overrides:
            overrides["log"] = log_overrides
        if args.live:
            overrides["live"] = {"enabled": True}
        service_overrides: dict[str, object] = {}
        if args.realtime_priority is not None:
            service_overrides["realtime_priority"] = args.realtime_priority
        if args.lock_memory:
            service_overrides["lock_memory"] = True
        if service_overrides:
            overrides["service"] = service_overrides
        cfg = config_mod.load(args.config, overrides or None)
    except config_mod.ConfigError as exc:
        print(f"ahrs-service: configuration error: {exc}", file=sys.stderr)
        return 2
    from ahrs_service.service import Service

    service = Service(cfg, duration_s=args.duration)
    service.install_signal_handlers()
    try:
        service.start()
    except (OSError, ValueError, RuntimeError) as exc:
        print(f"ahrs-service: cannot start: {exc}", file=sys.stderr)
        service.close()
        return 1
    logger = logging.getLogger("ahrs_service")
    logger.info("running: %s; MAVLink to %s", service.status_line(), ", ".join(cfg.mavlink["endpoints"]))
    if service.log_writer is not None:
        logger.info("logging to %s", getattr(service.log_writer, "path", cfg.log["directory"]))
    try:
        service.run()
    finally:
        service.close()
    parts = [service.status_line(), service.divergence_summary(), service.odometry_summary(),
             service.source_set_summary(), service.log_summary()]
    logger.info("stopped: %s", "; ".join(p for p in parts if p))
    return 0
