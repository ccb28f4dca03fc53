"""Reading a flight log back into NumPy arrays, for replay, analysis and tests.

:func:`read_log` uses the MCAP summary and indexes (``mcap.reader.make_reader``) when the
file is complete, and falls back to record-by-record stream reading
(:class:`~ahrs_service.logs.recover.RecordScanner`) when it is not — a crashed or truncated
log is read up to the damage, and the damage is reported in ``RecordedLog.damage``.
"""

from __future__ import annotations

import os
import struct
from array import array
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message, Metadata
from mcap.stream_reader import breakup_chunk

from ahrs_service.core.paths import regular_file
from ahrs_service.core.samples import SAMPLE_ROW
from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES, check_read_budget
from ahrs_service.logs.fields import (
    BadMessage,
    decoded,
    integer,
    integers,
    numbers,
    obj,
    scalar,
    string,
    vector,
    vectors,
)
from ahrs_service.logs.recover import MAX_CHUNK_BYTES, Damage, RecordScanner
from ahrs_service.logs.schemas import CHANNELS


class MessageSource:
    """Iterates (topic, log_time_ns, publish_time_ns, data bytes) of a log in file order.

    Indexed reading (with chunk CRC checks) when the summary is readable, else stream reading
    up to the damage. After iteration: ``damage`` (None if sound), ``indexed`` and
    ``metadata`` ({name: {key: value}}). Before the first message, a log whose chunks state
    more than ``budget_bytes`` decompressed (or a bomb's expansion) raises
    :class:`~ahrs_service.logs.budget.ReadBudgetExceeded` (``logs/budget.py``).
    """

    def __init__(self, path: str | os.PathLike, *, stream_only: bool = False,
                 budget_bytes: int = DEFAULT_READ_BUDGET_BYTES) -> None:
        self.path = Path(path)
        self.stream_only = stream_only
        self.budget_bytes = budget_bytes
        self.damage: Damage | None = None
        self.indexed = False
        self.metadata: dict[str, dict[str, str]] = {}
        self._scanner: RecordScanner | None = None

    @property
    def offset(self) -> int:
        """Byte offset of the record the message yielded last came from (its chunk's); -1 when
        reading through the index, which does not tell."""
        return -1 if self._scanner is None else self._scanner.record_offset

    def _summary_reader(self, f: Any) -> Any:
        try:
            reader = make_reader(f, validate_crcs=True)
            summary = reader.get_summary()
        except Exception:  # noqa: BLE001 - no readable footer/summary: stream read instead
            return None
        if summary is None or not summary.chunk_indexes:
            return None
        if not all(self._chunk_as_indexed(f, c) for c in summary.chunk_indexes):
            return None  # the library would decompress it whole: the stream read bounds and reports it
        return reader

    @staticmethod
    def _chunk_as_indexed(f: Any, index: Any) -> bool:
        """Whether the Chunk record at ``index.chunk_start_offset`` says what its index says
        (size within :data:`MAX_CHUNK_BYTES`, a known compression): the library decompresses a
        chunk to the size its *record* states, so an index that lies cannot hide a bomb."""
        if index.uncompressed_size > MAX_CHUNK_BYTES or index.compression not in ("zstd", "lz4", ""):
            return False
        f.seek(index.chunk_start_offset)
        head = f.read(9 + 28)  # opcode, length; message start/end time, uncompressed size, CRC
        if len(head) < 37 or head[0] != 0x06:
            return False
        return struct.unpack_from("<Q", head, 9 + 16)[0] == index.uncompressed_size

    @staticmethod
    def _indexed_messages(f: Any, summary: Any) -> Iterator[tuple[str, int, int, bytes]]:
        """The messages of the indexed chunks, chunk after chunk, each chunk's CRC checked.
        (The library's ``iter_messages(log_time_order=False)`` decompresses every chunk before
        it yields the first message, so a whole log's messages would be objects at once.)"""
        for index in summary.chunk_indexes:
            f.seek(index.chunk_start_offset + 1 + 8)  # past the record's opcode and length
            chunk = Chunk.read(ReadDataStream(f))
            for record in breakup_chunk(chunk, validate_crc=True):
                if isinstance(record, Message):
                    channel = summary.channels[record.channel_id]
                    yield channel.topic, record.log_time, record.publish_time, record.data

    def __iter__(self) -> Iterator[tuple[str, int, int, bytes]]:
        check_read_budget(self.path, self.budget_bytes)
        with open(self.path, "rb") as f:
            reader = None if self.stream_only else self._summary_reader(f)
            if reader is not None:
                self.indexed = True
                try:
                    for m in reader.iter_metadata():
                        self.metadata[m.name] = dict(m.metadata)
                    yield from self._indexed_messages(f, reader.get_summary())
                except Exception as exc:  # noqa: BLE001 - damage inside an indexed file
                    size = self.path.stat().st_size
                    self.damage = Damage(-1, size, f"indexed read failed: {type(exc).__name__}: {exc}")
                return
        scanner = self._scanner = RecordScanner(self.path)
        topics: dict[int, str] = {}
        for rec in scanner:
            if isinstance(rec, Channel):
                topics[rec.id] = rec.topic
            elif isinstance(rec, Message) and rec.channel_id in topics:
                yield topics[rec.channel_id], rec.log_time, rec.publish_time, rec.data
            elif isinstance(rec, Metadata):
                self.metadata[rec.name] = dict(rec.metadata)
        self.damage = scanner.damage if not scanner.complete or scanner.damage else None


@dataclass
class RecordedLog:
    """A flight log as arrays. Rows are the /imu/raw samples (and the rows of /imu/raw_block
    bursts), in file order; the /attitude of a block log (written at the /tf rate for
    Foxglove) repeats rows of its /attitude_block.

    t_ns (N,) int64 sample times; rows (N, 10) float64 [gx, gy, gz, ax, ay, az, mx, my, mz, dt]
    exactly as fed to the estimator (rad/s, m/s², µT, s; NaN where null); flags (N,) int64;
    index (N,) int64 the writer's sample counter (what /params sample_index refers to);
    attitudes (N, 4) the recorded /attitude q_earth←body [w, x, y, z] (NaN where none) or None;
    original (N, 4) /attitude/original (a replayed log's source estimate) or None;
    truth (N, 4) /attitude/truth in NED or None; movement (N,) bool or None;
    estimator / params: the recorded estimator name and its parameters at the start of the
    file (from /config: config["estimator"] = {"name", "params"}); param_changes: the /params
    messages; configs: every /config message; counts: messages per topic; damage: None for a
    sound file; initial_state: the /estimator/state snapshot a rotated file starts from
    ({"estimator", "sample_index", "state" (ndarray)}) or None.
    """

    path: Path
    t_ns: np.ndarray
    rows: np.ndarray
    flags: np.ndarray
    index: np.ndarray
    attitudes: np.ndarray | None
    original: np.ndarray | None
    truth: np.ndarray | None
    movement: np.ndarray | None
    estimator: str | None
    params: dict[str, Any]
    param_changes: list[dict[str, Any]]
    config: dict[str, Any]
    configs: list[dict[str, Any]] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    damage: Damage | None = None
    indexed: bool = False
    initial_state: dict[str, Any] | None = None
    #: (N,) int64 the source's own stamps (host read times of a polling source) beside
    #: ``t_ns``, the recovered sample times ``dt`` came from; ``t_ns`` where not recorded
    t_source_ns: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def duration_s(self) -> float:
        return float(self.t_ns[-1] - self.t_ns[0]) / 1e9 if len(self) > 1 else 0.0

    def local_index(self, sample_index: int) -> int:
        """Row of this file at which writer sample number ``sample_index`` sits (may be < 0)."""
        first = int(self.index[0]) if len(self) else 0
        return int(sample_index) - first


def _align(t_ns: np.ndarray, times: array, values: array, width: int) -> np.ndarray | None:
    """``values`` (``width`` floats per time, flat) on the rows of ``t_ns`` whose time they
    carry (NaN where none does; the last of equal times wins); None without any."""
    if not times:
        return None
    out = np.full((t_ns.shape[0], width), np.nan)
    rows = np.frombuffer(values, dtype=np.float64).reshape(-1, width)
    row_of = {int(t): i for i, t in enumerate(t_ns.tolist())}
    for k, t in enumerate(times):
        i = row_of.get(t)
        if i is not None:
            out[i] = rows[k]
    return out


def read_log(path: str | os.PathLike, budget_bytes: int = DEFAULT_READ_BUDGET_BYTES) -> RecordedLog:
    """Reads a flight log (MCAP) into a :class:`RecordedLog`; damaged files up to the damage.
    OSError naming the path when it is no regular file (missing, a directory, a FIFO …);
    :class:`~ahrs_service.logs.budget.ReadBudgetExceeded` (a ValueError), before anything is
    decompressed, when its chunks state more than ``budget_bytes`` or a bomb's expansion."""
    regular_file(path)  # a FIFO would block open() until some process writes to it
    log = _read(MessageSource(path, budget_bytes=budget_bytes))
    if log.damage is not None and log.indexed:
        # a complete file with a damaged chunk: read it again in file order, up to the damage
        log = _read(MessageSource(path, stream_only=True, budget_bytes=budget_bytes))
    return log


def _read(source: MessageSource) -> RecordedLog:
    path = source.path
    # flat typed arrays, 8 bytes a number: lists of Python floats and ints take about ten
    # times as much, which bounds the longest log a worker can replay
    t_ns, t_src, flags, index = array("q"), array("q"), array("q"), array("q")
    rows = array("d")  # SAMPLE_ROW.size floats a sample: gyr, acc, mag, dt
    att_t, orig_t, tru_t = array("q"), array("q"), array("q")
    att_q, orig_q, tru_q = array("d"), array("d"), array("d")  # 4 floats a quaternion
    tru_m = array("d")
    configs: list[dict[str, Any]] = []
    changes: list[dict[str, Any]] = []
    counts: dict[str, int] = {}
    att_estimator: str | None = None
    first_state: dict[str, Any] | None = None
    damage: Damage | None = None
    for topic, log_time, _, data in source:
        counts[topic] = counts.get(topic, 0) + 1
        try:
            if topic == "/imu/raw":
                m = decoded(data)
                t = integer(m, "t_ns")
                ts = integer(m, "t_source_ns", optional=True)  # absent in logs before it was recorded
                row = vector(m, "gyr", 3) + vector(m, "acc", 3) + vector(m, "mag", 3, nullable=True)
                row.append(scalar(m, "dt"))
                flag = integer(m, "flags")
                i = integer(m, "index", optional=True)  # null or absent (schema allows both): the row number in this file
                t_ns.append(t)
                t_src.append(t if ts is None else ts)
                rows.extend(row)
                flags.append(flag)
                index.append(len(index) if i is None else i)
            elif topic == "/imu/raw_block":  # one FIFO burst: its rows as that many /imu/raw
                m = decoded(data)
                times = integers(m, "t_ns")
                n = len(times)
                sources = integers(m, "t_source_ns", n, optional=True)
                dt = numbers(m, "dt", n)
                gyr, acc = vectors(m, "gyr", n, 3), vectors(m, "acc", n, 3)
                mag = vectors(m, "mag", n, 3, nullable=True)
                block_flags = integers(m, "flags", n)
                first = integer(m, "first_index")
                t_ns.extend(times)
                t_src.extend(times if sources is None else sources)
                for g, a, b, d in zip(gyr, acc, mag, dt):
                    rows.extend(g)
                    rows.extend(a)
                    rows.extend(b)
                    rows.append(d)
                flags.extend(block_flags)
                index.extend(range(first, first + n))
            elif topic in ("/attitude_block", "/attitude/original_block"):
                m = decoded(data)
                times = integers(m, "t_ns")
                qs = vectors(m, "q", len(times), 4)
                name = string(m, "estimator", optional=True)
                (att_t if topic == "/attitude_block" else orig_t).extend(times)
                for q in qs:
                    (att_q if topic == "/attitude_block" else orig_q).extend(q)
                if topic == "/attitude_block" and att_estimator is None:
                    att_estimator = name
            elif topic == "/attitude/truth_block":
                m = decoded(data)
                times = integers(m, "t_ns")
                for q in vectors(m, "q", len(times), 4):
                    tru_q.extend(q)
                tru_t.extend(times)
                tru_m.extend([np.nan] * len(times))
            elif topic in ("/attitude", "/attitude/original"):
                m = decoded(data)
                t, q = integer(m, "t_ns"), vector(m, "q", 4)
                name = string(m, "estimator", optional=True)
                (att_t if topic == "/attitude" else orig_t).append(t)
                (att_q if topic == "/attitude" else orig_q).extend(q)
                if topic == "/attitude" and att_estimator is None:
                    att_estimator = name
            elif topic == "/attitude/truth":
                m = decoded(data)
                t, q = integer(m, "t_ns"), vector(m, "q", 4)
                mv = m.get("movement")
                if mv is not None and not isinstance(mv, bool):
                    raise BadMessage("$.movement", "expected a boolean or null")
                tru_t.append(t)
                tru_q.extend(q)
                tru_m.append(np.nan if mv is None else float(mv))
            elif topic == "/config":
                m = decoded(data)
                est = obj(m, "config").get("estimator")
                if isinstance(est, dict):  # what replay takes from it: a name and a parameter table
                    string(est, "name", optional=True)
                    obj(est, "params", optional=True)
                configs.append(m)
            elif topic == "/params":
                m = decoded(data)
                integer(m, "sample_index"), integer(m, "t_ns"), string(m, "name")
                if "new" not in m:
                    raise BadMessage("$.new", "missing")
                changes.append(m)
            elif topic == "/estimator/state":
                m = decoded(data)
                integer(m, "sample_index"), string(m, "estimator"), numbers(m, "state")
                if first_state is None:  # replay starts from it; the others are only checked
                    first_state = m
        except BadMessage as exc:
            # a message its topic's schema does not describe: the file is read up to it, as up
            # to a damaged chunk, and the damage names the message and the field
            schema = CHANNELS.get(topic, ("",))[0]
            size = path.stat().st_size
            damage = Damage(source.offset, size, f"{topic} message {counts[topic]} (log time {log_time} ns) "
                            f"is not a valid {schema}: {exc}")
            counts[topic] -= 1
            if not counts[topic]:
                del counts[topic]
            break
    t = np.frombuffer(t_ns, dtype=np.int64).copy()
    config = configs[0]["config"] if configs else {}
    est_cfg = config.get("estimator") if isinstance(config.get("estimator"), dict) else {}
    estimator = est_cfg.get("name") or att_estimator
    params = dict(est_cfg.get("params") or {})
    movement = None
    if tru_t and not np.all(np.isnan(np.frombuffer(tru_m, dtype=np.float64))):
        mv = _align(t, tru_t, tru_m, 1)
        movement = None if mv is None else (mv[:, 0] == 1.0)
    changes.sort(key=lambda c: (int(c["sample_index"]), int(c["t_ns"])))
    initial_state = None
    if first_state is not None and index and first_state["sample_index"] == index[0]:
        st = first_state
        initial_state = {
            "estimator": st["estimator"],
            "sample_index": st["sample_index"],
            "state": np.asarray(numbers(st, "state"), dtype=np.float64),
        }
    return RecordedLog(
        path=Path(path),
        t_ns=t,
        rows=np.frombuffer(rows, dtype=np.float64).reshape(-1, SAMPLE_ROW.size).copy(),
        flags=np.frombuffer(flags, dtype=np.int64).copy(),
        index=np.frombuffer(index, dtype=np.int64).copy(),
        attitudes=_align(t, att_t, att_q, 4),
        original=_align(t, orig_t, orig_q, 4),
        truth=_align(t, tru_t, tru_q, 4),
        movement=movement,
        estimator=estimator,
        params=params,
        param_changes=changes,
        config=config,
        configs=configs,
        counts=counts,
        metadata=source.metadata,
        damage=damage or source.damage,
        indexed=source.indexed,
        initial_state=initial_state,
        t_source_ns=np.frombuffer(t_src, dtype=np.int64).copy(),
    )
