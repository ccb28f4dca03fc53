"""Fleet re-estimation: ``ahrs-service replay`` over many logs, one Dask task per log.

Each log is replayed as the single-log ``replay`` does (``replay.replay`` / ``replay_offline``,
``replay.compare``, ``replay.write_replay`` into ``--out DIR``, at the log's path relative to
the folder all the logs share: :func:`output_paths`), on whatever worker
the execution layer (``ahrs_service.execution``) gives it; the log is read on that worker from
its path. A log that cannot be read or replayed becomes a row naming its error, and a damaged
(corrupt or truncated) log is replayed up to its damage and its row says what the damage is;
neither stops the others.

:func:`run_fleet` streams the rows as the logs finish (``Runner.stream``): each is appended
at once to the journal ``fleet.jsonl`` in the output folder, so neither the client nor the
cluster holds the fleet's results, and a run that is killed keeps every row it finished. A
re-run in the same folder skips the logs whose journal row has no error, was made with the
same estimator settings, and whose output reads back complete (:func:`output_complete`);
``force=True`` redoes them. At the end the table (:data:`COLUMNS`) is written as ``fleet.csv``
and ``fleet.parquet``, rows in the order of the logs given, with a summary of what failed and
why (:class:`FleetTally`).
"""

from __future__ import annotations

import csv
import glob
import json
import math
import os
from collections import Counter
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Iterator

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
    #: the kind of damage or failure, for the summary (:func:`problem_of`); None when intact
    problem: str | None = None


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
            return _with_problem(FleetRow(**empty | {"log": job.path, "damage": damage, "samples": len(log),
                                                     "error": "the log names no estimator; give --estimator NAME"}))
        if not len(log):
            return _with_problem(FleetRow(**empty | {"log": job.path, "damage": damage, "samples": 0,
                                                     "error": "no sample to replay"}))
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
        return _with_problem(FleetRow(
            log=job.path, estimator=name, samples=int(cmp["samples"]), lost_samples=_lost_samples(log.index),
            damage=damage, rms_diff_vs_recorded_deg=_num(rec.get("rms_deg")),
            truth_samples=truth.get("samples"), truth_total_rmse_deg=_num(truth.get("total")),
            truth_heading_rmse_deg=_num(truth.get("heading")),
            truth_inclination_rmse_deg=_num(truth.get("inclination")), output=output, error=None,
        ))
    except ReadBudgetExceeded as exc:  # a bomb, or a log longer than the budget: nothing was read
        return FleetRow(**empty | {"log": job.path, "error": str(exc), "problem": BUDGET_REFUSED})
    except Exception as exc:  # noqa: BLE001 - one bad log is a row, not the end of the fleet
        return _with_problem(FleetRow(**empty | {"log": job.path, "error": f"{type(exc).__name__}: {exc}"}))


#: the problem of a log the read budget refused (a decompression bomb, or longer than the budget)
BUDGET_REFUSED = "refused by the read budget"


def problem_of(row: FleetRow) -> str | None:
    """What went wrong with a log, in a few words the summary counts by: "truncated" or
    "corrupt" for a damaged log (replayed up to its damage), else why it failed: "refused by
    the read budget", "not an MCAP file", "missing", "no estimator", "no samples" or
    "unreadable". None for an intact log replayed whole."""
    error, damage = row.error or "", row.damage or ""
    if error:
        if "refused, nothing read" in error:
            return BUDGET_REFUSED
        if "not an MCAP file" in error + damage or "BadMagic" in error:
            return "not an MCAP file"
        if error.startswith("FileNotFoundError"):
            return "missing"
        if "names no estimator" in error:
            return "no estimator"
        if error == "no sample to replay":
            return "no samples"
        return "unreadable"
    if damage:
        if "without footer" in damage or "cut short" in damage:
            return "truncated"
        return "corrupt"
    return None


def _with_problem(row: FleetRow) -> FleetRow:
    row.problem = problem_of(row)
    return row


def _row_from(d: dict[str, Any]) -> FleetRow:
    return FleetRow(**{k: d.get(k) for k in COLUMNS})


class FleetTally:
    """The fleet summary, counted row by row (memory independent of the fleet's size: at most
    :attr:`examples` logs named per kind of problem)."""

    examples = 5

    def __init__(self) -> None:
        self.logs = self.replayed = self.damaged = self.failed = self.resumed = 0
        self.samples = self.lost = 0
        self.problems: Counter[str] = Counter()
        self.named: dict[str, list[str]] = {}
        self._sums: dict[str, list[float]] = {"rms_diff_vs_recorded_deg": [0.0, 0], "truth_total_rmse_deg": [0.0, 0]}

    def add(self, row: FleetRow, resumed: bool = False) -> None:
        self.logs += 1
        self.resumed += resumed
        if row.damage:
            self.damaged += 1
        if row.error:
            self.failed += 1
        else:
            self.replayed += 1
            self.samples += row.samples or 0
            self.lost += row.lost_samples or 0
            for key, acc in self._sums.items():
                value = getattr(row, key)
                if value is not None:
                    acc[0] += value
                    acc[1] += 1
        problem = row.problem or problem_of(row)
        if problem:
            self.problems[problem] += 1
            named = self.named.setdefault(problem, [])
            if len(named) < self.examples:
                named.append(f"{row.log}: {row.error or row.damage}")

    def _mean(self, key: str) -> str:
        total, n = self._sums[key]
        return f"{total / n:.3f}° over {n}" if n else "n/a"

    def text(self) -> str:
        """A few lines: logs replayed, damaged, failed; mean differences; each kind of problem
        with its count and the first few logs that had it, and why."""
        resumed = f", {self.resumed} of them done by a previous run" if self.resumed else ""
        lines = [
            f"{self.logs} log(s): {self.replayed} replayed ({self.samples} samples, {self.lost} lost), "
            f"{self.damaged} damaged, {self.failed} failed{resumed}",
            f"  RMS difference from the recorded estimate: mean {self._mean('rms_diff_vs_recorded_deg')}",
            f"  total RMSE against truth: mean {self._mean('truth_total_rmse_deg')}",
        ]
        for problem, count in sorted(self.problems.items(), key=lambda kv: (-kv[1], kv[0])):
            replayed = problem in ("truncated", "corrupt")
            lines.append(f"  {problem}: {count} log(s)" + (", replayed up to the damage" if replayed else ", not replayed"))
            lines += [f"    {example}" for example in self.named[problem]]
            if count > len(self.named[problem]):
                lines.append(f"    ... and {count - len(self.named[problem])} more (the 'problem' column of the table)")
        return "\n".join(lines)


def summary(rows: list[FleetRow]) -> str:
    """A few lines: how many logs replayed, damaged, failed; mean differences; the problems."""
    tally = FleetTally()
    for row in rows:
        tally.add(row)
    return tally.text()


class _TableWriter:
    """``fleet.csv`` and (with pyarrow) ``fleet.parquet``, written a row at a time (Parquet in
    row groups of ``batch`` rows)."""

    def __init__(self, out_dir: Path, batch: int = 1000) -> None:
        self.csv_path = out_dir / "fleet.csv"
        self.parquet_path: Path | None = None
        self._csv_file = self.csv_path.open("w", newline="", encoding="utf-8")
        self._csv = csv.DictWriter(self._csv_file, fieldnames=COLUMNS)
        self._csv.writeheader()
        self._batch: list[dict[str, Any]] = []
        self._batch_size = batch
        self._pq_writer: Any = None
        try:
            import pyarrow as pa
            import pyarrow.parquet as pq
        except ImportError:
            self._pa = None
            return
        self._pa, self._pq = pa, pq
        self.parquet_path = out_dir / "fleet.parquet"
        # the schema fixed from the dataclass: a first batch of all-None columns must not make them null-typed
        types = {int: pa.int64(), float: pa.float64(), str: pa.string()}
        self._schema = pa.schema([(f.name, types[_base_type(f.type)]) for f in fields(FleetRow)])

    def add(self, row: FleetRow) -> None:
        d = asdict(row)
        self._csv.writerow({k: ("" if v is None else v) for k, v in d.items()})
        if self._pa is not None:
            self._batch.append(d)
            if len(self._batch) >= self._batch_size:
                self._flush()

    def _flush(self) -> None:
        if self._pq_writer is None:
            self._pq_writer = self._pq.ParquetWriter(self.parquet_path, self._schema)
        self._pq_writer.write_table(self._pa.Table.from_pylist(self._batch, schema=self._schema))
        self._batch = []

    def close(self) -> None:
        self._csv_file.close()
        if self._pa is not None:
            if self._batch or self._pq_writer is None:
                self._flush()
            self._pq_writer.close()


def _base_type(annotation: str) -> type:
    name = annotation.split("|")[0].strip()
    return {"int": int, "float": float, "str": str}[name]


def write_table(rows: list[FleetRow], out_dir: str | os.PathLike) -> tuple[Path, Path | None]:
    """``fleet.csv`` and (with pyarrow) ``fleet.parquet`` in ``out_dir``; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = _TableWriter(out)
    for row in rows:
        table.add(row)
    table.close()
    return table.csv_path, table.parquet_path


# ---------------------------------------------------------------- streaming, resuming

JOURNAL_NAME = "fleet.jsonl"


def settings_of(job: ReplayJob) -> str:
    """What makes two replays of one log the same replay (not the read budget, which only
    decides whether a log is read): a short text kept in the journal."""
    return json.dumps([job.estimator, job.params, job.follow_param_changes, job.blend_time_s], sort_keys=True, default=str)


def output_complete(path: str | os.PathLike, samples: int | None) -> bool:
    """Whether a replay's output reads back whole: an MCAP file with its footer and summary
    (a write cut short, as by a killed worker, has neither) whose statistics count ``samples``
    messages on /imu/raw. Reads only the file's end."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary_section = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - whatever the reason, the output cannot be trusted
        return False
    if summary_section is None or summary_section.statistics is None:
        return False
    raw = [c.id for c in summary_section.channels.values() if c.topic in ("/imu/raw", "/imu/raw_block")]
    counts = summary_section.statistics.channel_message_counts
    if samples is None or not raw:
        return False
    if any(summary_section.channels[i].topic == "/imu/raw_block" for i in raw):
        return sum(counts.get(i, 0) for i in raw) > 0  # rows per block message are not counted here
    return sum(counts.get(i, 0) for i in raw) == samples


class _Journal:
    """The append-only ``fleet.jsonl``: one JSON line per finished log (its row, and the
    settings it was replayed with), flushed at once. The last line of a log wins. A line a
    killed run left unfinished is ended with a newline and then ignored as unreadable."""

    def __init__(self, out_dir: Path) -> None:
        self.path = out_dir / JOURNAL_NAME
        self.offset_of: dict[str, int] = {}  # log -> byte offset of its last line
        self.unreadable_lines = 0
        if self.path.exists():
            self._index()
        self._file = self.path.open("ab")
        if self._file.tell() and not self._ends_with_newline():
            self._file.write(b"\n")
            self._file.flush()

    def _ends_with_newline(self) -> bool:
        with self.path.open("rb") as f:
            f.seek(-1, os.SEEK_END)
            return f.read(1) == b"\n"

    def _index(self) -> None:
        with self.path.open("rb") as f:
            offset = 0
            for line in f:
                try:
                    self.offset_of[json.loads(line)["log"]] = offset
                except (ValueError, KeyError, TypeError):
                    self.unreadable_lines += 1
                offset += len(line)

    def read(self, log: str) -> dict[str, Any] | None:
        offset = self.offset_of.get(log)
        if offset is None:
            return None
        with self.path.open("rb") as f:
            f.seek(offset)
            return json.loads(f.readline())

    def append(self, row: FleetRow, settings: str) -> None:
        line = json.dumps({**asdict(row), "settings": settings}, default=str).encode() + b"\n"
        self.offset_of[row.log] = self._file.tell()
        self._file.write(line)
        self._file.flush()

    def close(self) -> None:
        self._file.close()


@dataclass
class FleetRun:
    """What :func:`run_fleet` did: logs in the fleet, replayed now, skipped as done before."""

    logs: int
    ran: int
    skipped: int
    failed: int
    summary: str
    csv_path: Path
    parquet_path: Path | None
    journal_path: Path
    counts: Counter = field(default_factory=Counter)


def _already_done(journal: _Journal, job: ReplayJob) -> bool:
    entry = journal.read(job.path)
    return (
        entry is not None
        and entry.get("error") is None
        and entry.get("settings") == settings_of(job)
        and entry.get("output") is not None
        and os.path.abspath(entry["output"]) == os.path.abspath(job.out_path or "")
        and output_complete(entry["output"], entry.get("samples"))
    )


def _file_size(path: str) -> int:
    """The log's size in bytes (0 when it cannot be read: its replay reports why)."""
    try:
        return os.stat(path).st_size
    except OSError:
        return 0


def run_fleet(
    runner: Any,
    jobs: list[ReplayJob],
    out_dir: str | os.PathLike,
    *,
    force: bool = False,
    progress: bool = False,
    max_in_flight: int | None = None,
) -> FleetRun:
    """Replays ``jobs`` on ``runner`` (an ``execution.Runner``), streaming each row into the
    journal as its log finishes, then writes the table and the summary (``summary.txt``) in
    ``out_dir``. Logs a previous run in ``out_dir`` replayed completely with the same settings
    are skipped unless ``force``. On a cluster the largest logs go first (so the run does not
    end waiting for a long one); the table is in the jobs' order whatever the order they
    finished in. Memory: one row at a time, plus an offset and a size per log."""
    from ahrs_service.execution import progress_bar

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    journal = _Journal(out)
    try:
        todo = [i for i, job in enumerate(jobs) if force or not _already_done(journal, job)]
        skipped = len(jobs) - len(todo)
        if runner.client is not None:  # largest first: the logs that finish last are short ones
            todo.sort(key=lambda i: -_file_size(jobs[i].path))
        bar = progress_bar(len(todo), "replay", unit="log") if progress and todo else None
        try:
            for k, row in runner.stream(replay_one, (jobs[i] for i in todo), max_in_flight=max_in_flight):
                journal.append(row, settings_of(jobs[todo[k]]))
                if bar is not None:
                    bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        tally = FleetTally()
        table = _TableWriter(out)
        redone = set(todo) if skipped else None  # None: every log ran now
        compact = journal.path.with_suffix(".jsonl.tmp")
        with compact.open("wb") as kept:
            for i, job in enumerate(jobs):
                entry = journal.read(job.path)
                row = _row_from(entry)
                tally.add(row, resumed=redone is not None and i not in redone)
                table.add(row)
                kept.write(json.dumps(entry, default=str).encode() + b"\n")
        table.close()
    finally:
        journal.close()
    # the journal rewritten in the logs' order, one line per log (atomic: a kill here keeps the old one)
    os.replace(compact, journal.path)
    text = tally.text()
    (out / "summary.txt").write_text(text + "\n", encoding="utf-8")
    return FleetRun(len(jobs), len(todo), skipped, tally.failed, text, table.csv_path, table.parquet_path,
                    journal.path, tally.problems)


def journal_logs(out_dir: str | os.PathLike) -> list[str]:
    """The logs the journal in ``out_dir`` has a complete line for so far (a run still going,
    or killed, may have left half a line at its end); [] before the first."""
    path = Path(out_dir) / JOURNAL_NAME
    if not path.exists():
        return []
    done = []
    for line in path.read_bytes().split(b"\n")[:-1]:
        try:
            done.append(json.loads(line)["log"])
        except ValueError:
            pass
    return done


def journal_rows(out_dir: str | os.PathLike) -> Iterator[FleetRow]:
    """The rows of the last completed run in ``out_dir``, in the logs' order, one at a time."""
    with (Path(out_dir) / JOURNAL_NAME).open("rb") as f:
        for line in f:
            yield _row_from(json.loads(line))
