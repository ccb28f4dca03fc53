"""The flight-log writer's encoders: each queue record turned into its MCAP messages.

:class:`RecordEncoders` has one method per record kind (:mod:`ahrs_service.logs.records`);
:meth:`RecordEncoders.handlers` is the dispatch table the writer thread looks a record's type
up in. Each method checks that a file takes the record (``LogFiles.ensure_file`` /
``ensure_item``, which count what it carries when none does), builds the messages with
:mod:`ahrs_service.logs.schemas` and writes them through ``LogFiles.write``.
"""

from __future__ import annotations

import collections
import math
from typing import Any, Callable

import numpy as np

from ahrs_service.logs import records
from ahrs_service.logs.log_files import LogFiles
from ahrs_service.logs.schemas import (
    attitude_block_message,
    attitude_message,
    autopilot_attitude_messages,
    jsonable,
    log_message,
    num_or_null,
    raw_block_message,
    raw_message,
    tf_message,
    truth_block_message,
    truth_message,
)

#: rows at most in one joined /imu/raw_block (RecordEncoders._joined_with_queued)
JOINED_BLOCK_MAX_ROWS = 256


def _continues(block: records.Block, nxt: records.Block) -> bool:
    """Whether ``nxt`` can be written in the same block messages as ``block``: the next rows,
    the same estimator and fields, and ``block`` without diagnostics of its own (those go
    with a message's last row)."""
    return (nxt.one_message and nxt.first_index == block.first_index + len(block.t_ns)
            and nxt.estimator == block.estimator and block.diagnostics is None
            and (nxt.t_source_ns is None) == (block.t_source_ns is None)
            and (nxt.temperature is None) == (block.temperature is None)
            and (nxt.truth_q is None) == (block.truth_q is None)
            and (nxt.raw is None) == (block.raw is None)
            and (nxt.raw is None or (nxt.raw.keys() == block.raw.keys()
                                     and all(nxt.raw[k].shape[1:] == block.raw[k].shape[1:] for k in nxt.raw))))


def _join(parts: list[records.Block]) -> records.Block:
    """Consecutive blocks (``_continues``) as one; the last one's bias and diagnostics."""

    def cat(field: str) -> np.ndarray | None:
        arrays = [getattr(p, field) for p in parts]
        return None if arrays[0] is None else np.concatenate(arrays)

    last = parts[-1]
    raw = None if last.raw is None else {k: np.concatenate([p.raw[k] for p in parts]) for k in last.raw}
    return records.Block(t_ns=cat("t_ns"), t_source_ns=cat("t_source_ns"), rows=cat("rows"), flags=cat("flags"),
                         raw=raw, temperature=cat("temperature"), first_index=parts[0].first_index, q=cat("q"),
                         estimator=last.estimator, bias=last.bias, truth_q=cat("truth_q"),
                         diagnostics=last.diagnostics, one_message=True)


class RecordEncoders:
    """Writes each queue record's messages to the writer's files (writer thread only).

    files: the writer's :class:`~ahrs_service.logs.log_files.LogFiles`.
    queued: the writer's queue; one-message blocks waiting right behind the one in hand are
        taken from it and joined (see ``_joined_with_queued``).
    tf_period_ns: least time between two /tf (and /attitude previews of block messages), ns;
        0: every attitude.
    rotate_if_due: the writer's rotation check, called at each sample boundary (before a
        sample's or block's messages).
    """

    def __init__(
        self,
        files: LogFiles,
        queued: collections.deque,
        *,
        tf_period_ns: int,
        rotate_if_due: Callable[[], None],
    ) -> None:
        self.tf_period_ns = tf_period_ns
        self._files = files
        self._queued = queued
        self._rotate_if_due = rotate_if_due
        # bound once: they run for every message
        self._write = files.write
        self._ensure_file = files.ensure_file
        self._ensure_item = files.ensure_item

    def handlers(self) -> dict[type, Callable[[Any], None]]:
        """The encoder of each message record kind (the writer adds its control records)."""
        return {
            records.Config: self.config,
            records.ParamChange: self.param_change,
            records.Raw: self.raw,
            records.Sample: self.sample,
            records.Block: self.block,
            records.Attitude: self.attitude,
            records.Truth: self.truth,
            records.Loop: self.loop,
            records.Mavlink: self.mavlink,
            records.AutopilotAttitude: self.autopilot_attitude,
            records.Timesync: self.timesync,
            records.Log: self.log,
        }

    # ---------------------------------------------------------------- configuration and state
    def config(self, item: records.Config) -> None:
        """/config; also the configuration every later file starts with."""
        files = self._files
        files.config = {"t_ns": int(item.t_ns), "config": item.config, "reason": item.reason}
        if files.current is None:
            self._ensure_file(1, item.reason)  # opening writes the configuration as the file's first message
            return
        self._write("/config", item.t_ns, files.config)

    def param_change(self, item: records.ParamChange) -> None:
        """/params; the change is folded into the configuration a new file starts with."""
        self._files.fold_param(item.name, item.new)
        if not self._ensure_file(1):
            return
        msg = {
            "t_ns": int(item.t_ns),
            "sample_index": item.sample_index,
            "name": str(item.name),
            "old": jsonable(item.old),
            "new": jsonable(item.new),
            "source": str(item.source),
        }
        self._write("/params", item.t_ns, msg)

    def state_snapshot(self, item: records.StateSnapshot) -> None:
        """/estimator/state: the first message of a file the writer has just rotated to."""
        if not self._ensure_file(1):
            return
        msg = {
            "t_ns": int(item.t_ns),
            "sample_index": int(item.next_index),
            "estimator": str(item.estimator),
            "state": item.state,
        }
        self._write("/estimator/state", item.t_ns, msg)

    # ---------------------------------------------------------------- samples
    def raw(self, item: records.Raw) -> None:
        self._rotate_if_due()
        if self._ensure_item(item):
            self._write("/imu/raw", item.t_ns, raw_message(item.t_ns, item.row, item.flags, item.raw, item.temperature, item.index))

    def sample(self, item: records.Sample) -> None:
        self._rotate_if_due()
        if not self._ensure_item(item):
            return
        t_ns = item.t_ns
        self._write("/imu/raw", t_ns, raw_message(t_ns, item.row, item.flags, item.raw, item.temperature, item.index))
        self._write_attitude(t_ns, item.q, item.estimator, item.bias, item.diagnostics)
        if item.truth_q is not None:
            self._write("/attitude/truth", t_ns, truth_message(t_ns, item.truth_q))

    def block(self, item: records.Block) -> None:
        self._rotate_if_due()  # at the block's start: a rotation's snapshot is a block's end state
        if item.one_message:
            item = self._joined_with_queued(item)
        if not self._ensure_item(item):
            return
        if item.one_message:
            self._write_block_messages(item)
            return
        files = self._files
        n = len(item.t_ns)
        truth = None if item.truth_q is None else item.truth_q.tolist()
        per_row = 2 + (truth is not None)
        sources = None if item.t_source_ns is None else item.t_source_ns.tolist()
        temps = None if item.temperature is None else item.temperature.tolist()
        raw = None if item.raw is None else {k: v.tolist() for k, v in item.raw.items()}
        rows, flags, qs = item.rows.tolist(), item.flags.tolist(), item.q.tolist()
        last = n - 1
        for i, t_ns in enumerate(item.t_ns.tolist()):
            if files.current is None:  # a write before failed: the files counted what the file held
                files.lose((n - i) * per_row, n - i)
                return
            self._write("/imu/raw", t_ns, raw_message(
                t_ns, rows[i], flags[i], None if raw is None else {k: v[i] for k, v in raw.items()},
                None if temps is None else temps[i], item.first_index + i,
                t_source_ns=None if sources is None else sources[i]))
            if i == last:
                self._write_attitude(t_ns, qs[i], item.estimator, item.bias, item.diagnostics)
            else:  # no bias of its own: the key is left out (not zeros a plot would show)
                self._write_attitude(t_ns, qs[i], item.estimator, None, None, with_bias=False)
            if truth is not None:
                self._write("/attitude/truth", t_ns, truth_message(t_ns, truth[i]))

    def _joined_with_queued(self, item: records.Block) -> records.Block:
        """``item`` and the one-message blocks queued right behind it that continue it, as one
        block: one /imu/raw_block and /attitude_block for all of them, up to the block whose
        last row makes the next /attitude preview due (``tf_period_ns``: each message then ends
        with one, at that rate) and at most :data:`JOINED_BLOCK_MAX_ROWS` rows. A fast part's
        bursts of a few samples each cost a message per channel each, and the ``mcap``
        library's ``add_message`` is pure Python: joined, the writer pays it once per /tf
        period. Nothing else is queued between them (a rotation's snapshot, a config, the
        close stop the join where they stand)."""
        last_tf_ns = self._files.last_tf_ns
        if last_tf_ns is None:
            return item
        q, parts = self._queued, [item]
        rows = len(item.t_ns)
        preview_due_ns = last_tf_ns + self.tf_period_ns
        while q and int(parts[-1].t_ns[-1]) < preview_due_ns:
            nxt = q[0]
            if (type(nxt) is not records.Block or not _continues(parts[-1], nxt)
                    or rows + len(nxt.t_ns) > JOINED_BLOCK_MAX_ROWS):
                break
            parts.append(q.popleft())
            rows += len(nxt.t_ns)
        return item if len(parts) == 1 else _join(parts)

    def _write_block_messages(self, item: records.Block) -> None:
        """One /imu/raw_block, /attitude_block (and /attitude/truth_block) for the whole block;
        /attitude and /tf of its last row at the /tf rate (and whenever the block carries
        diagnostics), so Foxglove's plots and 3-D panel have the attitude."""
        t_ns = item.t_ns.tolist()
        t_last = t_ns[-1]
        n = len(t_ns)
        self._write("/imu/raw_block", t_last, raw_block_message(
            t_ns, item.rows, item.flags.tolist(), item.first_index, item.raw, item.temperature,
            None if item.t_source_ns is None else item.t_source_ns.tolist()), samples=n)
        self._write("/attitude_block", t_last,
                    attitude_block_message(t_ns, item.q, item.estimator, item.bias, item.diagnostics))
        if item.truth_q is not None:
            self._write("/attitude/truth_block", t_last, truth_block_message(t_ns, item.truth_q))
        files = self._files
        if files.current is None:
            return
        q_last = item.q[-1].tolist()
        last_tf_ns = files.last_tf_ns
        tf_due = last_tf_ns is None or t_last - last_tf_ns >= self.tf_period_ns
        if tf_due or item.diagnostics:  # not counted as carried: a preview of /attitude_block
            self._write_attitude(t_last, q_last, item.estimator, item.bias, item.diagnostics,
                                 with_bias=item.bias is not None)

    def _write_attitude(self, t_ns: int, q: list[float], estimator: str, bias: Any, diagnostics: Any,
                        with_bias: bool = True) -> None:
        """/attitude, and /tf when one is due (``tf_period_ns``) and the attitude is finite."""
        message = attitude_message(t_ns, q, estimator, bias, diagnostics)
        if not with_bias:
            del message["gyro_bias"]
        self._write("/attitude", t_ns, message)
        files = self._files
        if (
            files.current is not None  # /tf is not counted as carried: not written, not lost
            and (files.last_tf_ns is None or t_ns - files.last_tf_ns >= self.tf_period_ns)
            and all(map(math.isfinite, q))  # a transform with null rotation would break the 3-D panel
        ):
            files.last_tf_ns = t_ns
            self._write("/tf", t_ns, tf_message(t_ns, q))

    # ---------------------------------------------------------------- other channels
    def attitude(self, item: records.Attitude) -> None:
        if self._ensure_file(1):
            self._write_attitude(item.t_ns, item.q, item.estimator, item.bias, item.diagnostics)

    def truth(self, item: records.Truth) -> None:
        if self._ensure_file(1):
            self._write("/attitude/truth", item.t_ns, truth_message(item.t_ns, item.q, item.movement, item.source))

    def loop(self, item: records.Loop) -> None:
        self._files.last_loop = dict(item.stats)
        if self._ensure_file(1):
            self._write("/loop", item.t_ns, {"t_ns": int(item.t_ns), **jsonable(item.stats)})

    def mavlink(self, item: records.Mavlink) -> None:
        if self._ensure_file(1):
            self._write("/mavlink", item.t_ns, {"t_ns": int(item.t_ns), "counters": jsonable(item.counters)})

    def autopilot_attitude(self, item: records.AutopilotAttitude) -> None:
        if self._ensure_item(item):
            d = item.d
            t = int(d.t_ns)
            for topic, message in autopilot_attitude_messages(t, list(d.q_autopilot), list(d.q_estimate), float(d.total_deg),
                                                              float(d.inclination_deg), float(d.heading_deg)).items():
                self._write(topic, t, message)

    def timesync(self, item: records.Timesync) -> None:
        if self._ensure_file(1):
            s = item.status
            t = int(s.local_ns)
            self._write("/timesync", t, {
                "t_ns": t, "offset_ns": int(s.offset_ns), "observed_offset_ns": int(s.observed_offset_ns),
                "drift_ppm": num_or_null(float(s.drift_ppm)), "rtt_ns": int(s.rtt_ns), "synced": bool(s.synced),
                "samples": int(s.samples),
            })

    def log(self, item: records.Log) -> None:
        if self._ensure_file(1):
            self._write("/log", item.t_ns, log_message(item.t_ns, item.severity, item.text))
