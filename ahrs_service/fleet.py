"""Fleet re-estimation: ``ahrs-service replay`` over many logs, one Dask task per log.

Each log is replayed as the single-log ``replay`` does (``replay.replay`` / ``replay_offline``,
``replay.compare``, ``replay.write_replay`` into ``--out DIR``, at the log's path relative to
the folder all the logs share: :func:`output_paths`), on whatever worker
the execution layer (``ahrs_service.execution``) gives it; the log is read on that worker from
its path. A log that cannot be read or replayed becomes a row naming its error, and a damaged
(corrupt or truncated) log is replayed up to its damage and its row says what the damage is;
neither stops the others. The table (:data:`COLUMNS`) is written as ``fleet.csv`` and
``fleet.parquet`` in the output folder, rows in the order of the logs given.
"""

from __future__ import annotations

import csv
import glob
import math
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES, ReadBudgetExceeded


@dataclass(frozen=True)
class ReplayJob:
    """One log to re-estimate (read on the worker from ``path``)."""

    path: str
    estimator: str | None  # None: the log's own estimator
    params: dict[str, Any]
    follow_param_changes: bool
    blend_time_s: float | None  # offline (forward-backward) when set
    out_path: str | None  # new log to write, or None
    #: bytes reading the log may decompress (``logs/budget.py``); a log over it is a failed row
    budget_bytes: int = DEFAULT_READ_BUDGET_BYTES


@dataclass
class FleetRow:
    """One log's line of the fleet table. Angles in degrees; None where it does not apply."""

    log: str
    estimator: str | None
    samples: int | None
    lost_samples: int | None  # whole sample periods missing from the log's sample counter
    damage: str | None  # what the reader found wrong with the file, None when intact
    rms_diff_vs_recorded_deg: float | None
    truth_samples: int | None
    truth_total_rmse_deg: float | None
    truth_heading_rmse_deg: float | None
    truth_inclination_rmse_deg: float | None
    output: str | None
    error: str | None  # why the log could not be replayed at all


COLUMNS = [f.name for f in fields(FleetRow)]


def expand_logs(specs: list[str]) -> list[Path]:
    """Log paths from files, directories (their ``*.mcap``, sorted) and glob patterns, in order.

    Raises FileNotFoundError naming a spec that matches no log.
    """
    out: list[Path] = []
    for spec in specs:
        p = Path(spec)
        if p.is_dir():
            found = sorted(p.glob("*.mcap"))
        elif any(c in spec for c in "*?["):
            found = [Path(x) for x in sorted(glob.glob(spec))]
        else:
            found = [p] if p.exists() else []
        if not found:
            raise FileNotFoundError(f"no MCAP log at {spec!r}")
        out += [f for f in found if f not in out]
    return out


def output_paths(logs: list[Path], out_dir: str | os.PathLike) -> list[Path]:
    """Where each log's replay goes: its path relative to the folder all ``logs`` share, under
    ``out_dir``. Distinct logs get distinct outputs (``x/f.mcap`` and ``y/x/f.mcap`` become
    ``OUT/x/f.mcap`` and ``OUT/y/x/f.mcap``), logs of one folder ``OUT/<name>.mcap``."""
    resolved = [Path(os.path.abspath(p)) for p in logs]  # not realpath: two links keep two names
    if not resolved:
        return []
    common = Path(os.path.commonpath([str(p.parent) for p in resolved]))
    return [Path(out_dir) / p.relative_to(common) for p in resolved]


def _lost_samples(index: np.ndarray) -> int:
    if index.size < 2:
        return 0
    steps = np.diff(index.astype(np.int64))
    return int(np.sum(steps[steps > 1] - 1))


def _num(x: Any) -> float | None:
    return None if x is None or (isinstance(x, float) and not math.isfinite(x)) else float(x)


def replay_one(job: ReplayJob) -> FleetRow:
    """Replays one log (the same code serial or as a Dask task); never raises for a bad log."""
    from ahrs_service.logs.reader import read_log
    from ahrs_service.replay import compare, replay, replay_offline, write_replay

    empty = dict.fromkeys(COLUMNS)
    try:
        log = read_log(job.path, job.budget_bytes)
        name = job.estimator or log.estimator
        damage = str(log.damage) if log.damage else None
        if not name:
            return FleetRow(**empty | {"log": job.path, "damage": damage, "samples": len(log),
                                       "error": "the log names no estimator; give --estimator NAME"})
        if not len(log):
            return FleetRow(**empty | {"log": job.path, "damage": damage, "samples": 0, "error": "no sample to replay"})
        if job.blend_time_s is not None:
            q = replay_offline(log, name, job.params, job.follow_param_changes, blend_time_s=job.blend_time_s).q
        else:
            q = replay(log, name, job.params, follow_param_changes=job.follow_param_changes)
        cmp = compare(log, q)
        output = None
        if job.out_path:
            output = str(write_replay(log, q, job.out_path, name, job.params, job.follow_param_changes,
                                      offline_blend_s=job.blend_time_s, budget_bytes=job.budget_bytes))
        rec = cmp.get("vs_recorded") or {}
        truth = cmp.get("vs_truth") or {}
        return FleetRow(
            log=job.path, estimator=name, samples=int(cmp["samples"]), lost_samples=_lost_samples(log.index),
            damage=damage, rms_diff_vs_recorded_deg=_num(rec.get("rms_deg")),
            truth_samples=truth.get("samples"), truth_total_rmse_deg=_num(truth.get("total")),
            truth_heading_rmse_deg=_num(truth.get("heading")),
            truth_inclination_rmse_deg=_num(truth.get("inclination")), output=output, error=None,
        )
    except ReadBudgetExceeded as exc:  # a bomb, or a log longer than the budget: nothing was read
        return FleetRow(**empty | {"log": job.path, "error": str(exc)})
    except Exception as exc:  # noqa: BLE001 - one bad log is a row, not the end of the fleet
        return FleetRow(**empty | {"log": job.path, "error": f"{type(exc).__name__}: {exc}"})


def write_table(rows: list[FleetRow], out_dir: str | os.PathLike) -> tuple[Path, Path | None]:
    """``fleet.csv`` and (with pyarrow) ``fleet.parquet`` in ``out_dir``; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "fleet.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in asdict(r).items()})
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:
        return csv_path, None
    pq_path = out / "fleet.parquet"
    pq.write_table(pa.Table.from_pylist([asdict(r) for r in rows]), pq_path)
    return csv_path, pq_path


def summary(rows: list[FleetRow]) -> str:
    """A few lines: how many logs replayed, damaged, failed; mean differences and errors."""
    ok = [r for r in rows if r.error is None]
    damaged = [r for r in rows if r.damage]
    failed = [r for r in rows if r.error]

    def mean(key: str) -> str:
        vals = [getattr(r, key) for r in ok if getattr(r, key) is not None]
        return f"{np.mean(vals):.3f}° over {len(vals)}" if vals else "n/a"

    lines = [
        f"{len(rows)} log(s): {len(ok)} replayed ({sum(r.samples or 0 for r in ok)} samples, "
        f"{sum(r.lost_samples or 0 for r in ok)} lost), {len(damaged)} damaged, {len(failed)} failed",
        f"  RMS difference from the recorded estimate: mean {mean('rms_diff_vs_recorded_deg')}",
        f"  total RMSE against truth: mean {mean('truth_total_rmse_deg')}",
    ]
    lines += [f"  damaged: {r.log}: {r.damage}" for r in damaged]
    lines += [f"  failed: {r.log}: {r.error}" for r in failed]
    return "\n".join(lines)
