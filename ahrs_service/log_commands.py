"""Command-line subcommands for flight logs: ``log recover|info|import-broad|plot`` and ``replay``."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from ahrs_service import execution
from ahrs_service.cli import add_offline_options, lazy_command


def _param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    try:
        return name.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name}: {value!r} is not a number") from None


def _add_read_budget(p: argparse.ArgumentParser) -> None:
    from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES

    p.add_argument("--read-budget-mb", type=float, default=DEFAULT_READ_BUDGET_BYTES / (1 << 20), metavar="MIB",
                   help="refuse a log whose chunks decompress to more than this, MiB (default %(default)g; "
                        "docs/logs.md, 'Decompression budget')")


def _read_budget(args: argparse.Namespace) -> int:
    """``--read-budget-mb`` in bytes; a bad value is cli.main's one-line error (ValueError)."""
    from ahrs_service.logs.budget import budget_bytes_from_mb

    return budget_bytes_from_mb(args.read_budget_mb)


def add_subcommands(subparsers: Any) -> None:
    """Adds ``log`` (recover, info, import-broad) and ``replay`` to the ``ahrs-service`` parser."""
    log = subparsers.add_parser("log", help="inspect, recover and import flight logs (MCAP)")
    sub = log.add_subparsers(dest="log_command", required=True, metavar="ACTION")

    p = sub.add_parser("recover", help="rewrite a crashed/truncated log as a valid indexed MCAP")
    p.add_argument("input", type=Path)
    p.add_argument("output", type=Path, nargs="?", help="default: INPUT.recovered.mcap")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=_recover)

    p = sub.add_parser("info", help="channels, message counts, duration and damage of a log")
    p.add_argument("log", type=Path)
    p.add_argument("--json", action="store_true")
    _add_read_budget(p)
    p.set_defaults(func=_info)

    p = sub.add_parser("import-broad", help="convert a BROAD HDF5 trial into an MCAP log with truth")
    p.add_argument("input", type=Path)
    p.add_argument("output", type=Path)
    p.add_argument("--start", type=float, default=None, metavar="S", help="first second to import")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="seconds to import")
    p.set_defaults(func=_import_broad)

    p = sub.add_parser("plot", help="quick-look figure of a log: attitude, sensors, loop timing, rejections")
    p.add_argument("log", type=Path)
    p.add_argument("--out", type=Path, required=True, help="figure file: .png, .pdf or .svg")
    p.set_defaults(func=lazy_command("ahrs_service.logs.plot:cmd_plot"))

    p = subparsers.add_parser(
        "replay",
        help="re-run an estimator over a recorded log (or a fleet of logs) and compare",
        description=(
            "One log: replays it and compares (--out FILE writes the new log). Several logs, a "
            "directory or a glob pattern: each log is one task of the execution layer, --out DIR "
            "gets each new log plus fleet.csv / fleet.parquet (one row per log) and a summary."
        ),
    )
    p.add_argument("log", nargs="+", metavar="LOG", help="an MCAP log, a directory of logs, or a glob such as 'logs/*.mcap'")
    p.add_argument("--estimator", default=None, help="estimator name (default: the recorded one)")
    p.add_argument("--param", type=_param, action="append", default=[], metavar="NAME=VALUE")
    p.add_argument("--no-param-changes", action="store_true", help="ignore recorded live parameter changes")
    p.add_argument(
        "--out", type=Path, default=None,
        help="one log: write a new log with the new estimate (FILE); several: the folder for the new logs and the fleet table (DIR)",
    )
    add_offline_options(p, "non-causal estimate: the estimator run forward and backward over the log and fused")
    p.add_argument("--json", action="store_true", help="print the comparison as JSON")
    p.add_argument(
        "--force", action="store_true",
        help="several logs: replay again the logs a previous run into the same --out DIR finished (default: skip them)",
    )
    _add_read_budget(p)
    execution.add_arguments(p, task_floor=False)  # a log is a task's worth
    p.set_defaults(func=_replay)


def _recover(args: argparse.Namespace) -> int:
    from ahrs_service.logs.loss import log_losses
    from ahrs_service.logs.recover import recover

    report = recover(args.input, args.output)
    # what the writer could not log (a full disk), from its counters in the last /loop: a file
    # cut by a disk that stayed full is a clean cut ("0 bytes lost") that misses the rest
    losses = log_losses(report.output)
    if args.json:
        print(json.dumps({**report.as_dict(), "not_logged_samples": losses.not_logged_samples,
                          "not_logged_s": losses.outage_s}, indent=2))
    else:
        d = report.as_dict()
        print(f"recovered {report.total_messages} messages into {report.output}")
        for topic, n in sorted(report.messages.items()):
            print(f"  {topic:20s} {n}")
        if d["duration_s"] is not None:
            print(f"  time range {report.start_ns} .. {report.end_ns} ns ({d['duration_s']:.3f} s)")
        if losses.not_logged_samples:
            print(f"  not logged (disk errors): {losses.not_logged_samples} samples, {losses.outage_s:.1f} s")
        print(f"  damage: {report.damage or 'none'}")
    return 0


def _info(args: argparse.Namespace) -> int:
    from ahrs_service.logs.loss import log_losses
    from ahrs_service.logs.reader import read_log

    budget = _read_budget(args)
    log = read_log(args.log, budget)
    losses = log_losses(args.log, budget)
    info = {
        "path": str(log.path),
        "indexed": log.indexed,
        "channels": log.counts,
        "samples": len(log),
        "duration_s": log.duration_s,
        "estimator": log.estimator,
        "params": log.params,
        "param_changes": len(log.param_changes),
        "truth": log.truth is not None,
        "metadata": log.metadata,
        "damage": log.damage.as_dict() if log.damage else None,
        "loop_damage": losses.damage,  # a /loop message whose counters could not be read
        # IMU samples that never reached the host, by cause (the source's running totals at
        # the last /loop), and samples that reached it but not the disk (the writer's)
        "lost_samples": None if losses.last is None else losses.last.as_dict(),
        "lost_samples_in_file": None if losses.in_file is None else losses.in_file.as_dict(),
        "not_logged_samples": losses.not_logged_samples,
        "not_logged_s": losses.outage_s,
    }
    if args.json:
        print(json.dumps(info, indent=2, default=str))
        return 1 if log.damage or losses.damage else 0  # as without --json (docs/logs.md)
    print(f"{log.path}  ({'indexed' if log.indexed else 'stream-read'})")
    print(f"  samples {len(log)}, duration {log.duration_s:.3f} s, estimator {log.estimator} {log.params}")
    for topic, n in sorted(log.counts.items()):
        print(f"  {topic:20s} {n}")
    print(f"  live parameter changes: {len(log.param_changes)}")
    if losses.last is None:
        print("  lost samples: not recorded (no /loop source counters)")
    else:
        print(f"  lost samples (source, since the service started): {losses.last.summary()}")
        if losses.in_file.total != losses.last.total:
            print(f"  lost samples in this file (first to last /loop): {losses.in_file.summary()}")
    if losses.not_logged_samples:
        print(f"  not logged (disk errors): {losses.not_logged_samples} samples, {losses.outage_s:.1f} s")
    print(f"  damage: {log.damage or losses.damage or 'none'}")
    return 1 if log.damage or losses.damage else 0


def _import_broad(args: argparse.Namespace) -> int:
    from ahrs_service.evaluation.broad_import import import_broad

    if not args.input.is_file():  # h5py's own error names no path
        raise (IsADirectoryError if args.input.is_dir() else FileNotFoundError)(2, "cannot open", str(args.input))
    try:
        summary = import_broad(args.input, args.output, args.start, args.duration)
    except OSError as exc:
        if exc.filename is not None:
            raise
        # h5py's errors name no file ("Unable to synchronously open file (file signature not found)")
        raise OSError(exc.errno, f"not a readable HDF5 recording ({exc})", str(args.input)) from None
    print(json.dumps(summary))
    return 0


def _blend_time(args: argparse.Namespace) -> float | None:
    """--offline's fusion time constant (s), None without --offline. A bad --offline-blend
    raises ValueError: cli.main prints it as the command's one error line (exit status 2)."""
    if not args.offline:
        return None
    from ahrs_service.estimators.offline import blend_time

    return blend_time(args.offline_blend)


def _is_fleet(specs: list[str]) -> bool:
    return len(specs) > 1 or Path(specs[0]).is_dir() or any(c in specs[0] for c in "*?[")


def _replay_fleet(args: argparse.Namespace) -> int:
    from ahrs_service import fleet
    from ahrs_service.execution import open_runner

    try:
        paths = fleet.expand_logs(args.log)
    except FileNotFoundError as exc:
        print(f"ahrs-service replay: error: {exc}", file=sys.stderr)
        return 2
    if args.out is None:
        print("ahrs-service replay: error: several logs need --out DIR (the new logs and the fleet table)", file=sys.stderr)
        return 2
    if args.out.exists() and not args.out.is_dir():
        print(f"ahrs-service replay: error: --out {str(args.out)!r} is a file; several logs need a folder", file=sys.stderr)
        return 2
    blend = _blend_time(args)  # checked before any log is replayed
    if args.estimator and args.param:  # else each log's own estimator: checked in its replay
        from ahrs_service.estimators.settings import check_estimator_params

        check_estimator_params(args.estimator, dict(args.param))
    budget = _read_budget(args)
    args.out.mkdir(parents=True, exist_ok=True)
    outputs = fleet.output_paths(paths, args.out)  # the logs' own relative paths: no two alike
    for out_path in outputs:
        out_path.parent.mkdir(parents=True, exist_ok=True)
    jobs = [
        fleet.ReplayJob(
            path=str(p.resolve()), estimator=args.estimator, params=dict(args.param),
            follow_param_changes=not args.no_param_changes, blend_time_s=blend,
            out_path=str(out_path), budget_bytes=budget,
        )
        for p, out_path in zip(paths, outputs)
    ]
    with open_runner(args.workers, args.scheduler) as runner:  # RunnerError: cli.main's one line
        run = fleet.run_fleet(runner, jobs, args.out, force=args.force, progress=sys.stderr.isatty() and not args.json)
    if args.json:
        from dataclasses import asdict

        # one row at a time: the fleet's rows are never all in memory
        print("[", end="")
        for k, row in enumerate(fleet.journal_rows(args.out)):
            print(("," if k else "") + "\n  " + json.dumps(asdict(row)), end="")
        print("\n]")
    else:
        print(run.summary)
        if run.skipped:
            print(f"  {run.skipped} log(s) already replayed into {args.out} by a previous run were skipped (--force redoes them)")
        print(f"  wrote {run.csv_path}" + (f" and {run.parquet_path}" if run.parquet_path else "")
              + f" and {run.logs - run.failed} log(s) in {args.out}")
    return 1 if run.failed else 0


def _say_if_compiling(name: str) -> None:
    """One line on stderr before a first use compiles for seconds or minutes in silence."""
    from ahrs_service import estimators

    if name in estimators.names() and not estimators.kernels_cached(name):
        print(f"ahrs-service: compiling the {name} kernels (first use on this machine: seconds for a paper "
              f"filter, minutes for robust; later runs load them from the cache)", file=sys.stderr, flush=True)


def _replay(args: argparse.Namespace) -> int:
    if _is_fleet(args.log):
        return _replay_fleet(args)
    from ahrs_service.logs.reader import read_log
    from ahrs_service.replay import compare, replay, replay_offline, write_replay

    budget = _read_budget(args)
    log = read_log(args.log[0], budget)
    params = dict(args.param)
    name = args.estimator or log.estimator
    if not name:
        if log.damage is not None:
            print(f"ahrs-service replay: error: the log names no estimator: its /config was lost to the damage "
                  f"({log.damage}); give --estimator NAME", file=sys.stderr)
        else:
            print("ahrs-service replay: error: the log names no estimator (no /config or /attitude); give --estimator NAME",
                  file=sys.stderr)
        return 2
    if not len(log):  # nothing to run an estimator over: say so rather than "replayed 0 samples"
        why = f" ({log.damage})" if log.damage is not None else ""
        print(f"ahrs-service replay: error: {log.path}: no sample to replay{why}", file=sys.stderr)
        return 2
    if params:  # the configuration file's checks and ranges, before any sample is replayed
        from ahrs_service.estimators.settings import check_estimator_params

        check_estimator_params(name, params)  # ConfigError (ValueError): cli.main's one line, exit 2
    follow = not args.no_param_changes
    blend = _blend_time(args)
    _say_if_compiling(name)
    if blend is not None:
        q = replay_offline(log, name, params, follow, blend_time_s=blend).q
    else:
        q = replay(log, name, params, follow_param_changes=follow)
    result = {"log": str(log.path), "estimator": name, "params": params, **compare(log, q)}
    if blend is not None:
        result["offline"] = {"blend_time_s": blend}
    if log.damage:
        result["damage"] = log.damage.as_dict()
    if args.out:
        result["output"] = str(write_replay(log, q, args.out, name, params, follow, offline_blend_s=blend,
                                            budget_bytes=budget))
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    mode = " (offline, forward-backward)" if blend is not None else ""
    print(f"replayed {result['samples']} samples of {log.path.name} with {name} {params or ''}{mode}")
    rec = result["vs_recorded"]
    if rec and not rec["samples"]:  # a recorded estimate, but none finite at a sample's time
        print("  vs recorded estimate: no sample has both a finite recorded and a finite new estimate")
    elif rec:
        same = "bit-exact" if rec["identical"] else f"max component difference {rec['max_abs_diff']:.3g}"
        print(
            f"  vs recorded estimate ({rec['samples']} samples): RMS {rec['rms_deg']:.3g}°, "
            f"max {rec['max_deg']:.3g}° ({same})"
        )
    for key, label in (("vs_truth", "new estimate"), ("recorded_vs_truth", "recorded estimate")):
        t = result.get(key)
        if t and t["samples"]:
            print(
                f"  {label} vs truth (RMSE, {t['samples']} samples): total {t['total']:.3f}°, "
                f"heading {t['heading']:.3f}°, inclination {t['inclination']:.3f}°"
            )
    for key, label in (("divergence", "new estimate"), ("recorded_divergence", "recorded estimate")):
        d = result.get(key)
        if d:
            first = next((e["t_s"] for e in d["events"] if e["diverged"]), None)
            at = f", first at {first:.2f} s" if first is not None else ""
            print(f"  divergence monitor, {label}: {d['summary'].removeprefix('attitude: ')}{at}")
    if log.damage:
        print(f"  damage: {log.damage}")
    if args.out:
        print(f"  wrote {result['output']}")
    return 0
