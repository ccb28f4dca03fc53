"""What a flight log says was lost: IMU samples by cause, and what the writer could not log.

Both are running totals the service writes in every ``/loop`` message (once a second):
``source.lost`` — the source's :class:`~ahrs_service.core.samples.LossCounts` (samples that
never reached the host: ``fifo_overflow``, ``bus_error``, ``gap``, ``host_stall``) — and ``log``
(the writer's ``stats()``: ``samples_not_logged``, ``outage_s`` …, samples that reached the host
but not the disk). :func:`log_losses` reads them back for ``ahrs-service log info``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

from ahrs_service.core.samples import LossCounts
from ahrs_service.logs.fields import BadMessage, decoded, integer, number, obj
from ahrs_service.logs.budget import DEFAULT_READ_BUDGET_BYTES
from ahrs_service.logs.reader import MessageSource

CAUSES = ("fifo_overflow", "bus_error", "gap", "host_stall")


def _counts(lost: Any) -> LossCounts | None:
    if not isinstance(lost, dict):
        return None
    counts = {c: integer(lost, c, optional=True) or 0 for c in CAUSES}
    if any(v < 0 for v in counts.values()):
        raise BadMessage("$.source.lost", f"negative count in {counts}")
    return LossCounts(**counts)


@dataclass
class LogLosses:
    """Loss as the log's ``/loop`` messages report it.

    loops: /loop messages read. first, last: ``source.lost`` of the first and the last of them
    (running totals since the service started; None when the log has no such counters).
    not_logged_samples, outage_s: the writer's running totals at the last /loop (None when not
    recorded); a file that follows an outage carries the samples it could not hold.
    damage: the first /loop message whose counters are not numbers of the right kind (the
    totals are those before it), or None.
    """

    loops: int = 0
    first: LossCounts | None = None
    last: LossCounts | None = None
    not_logged_samples: int | None = None
    outage_s: float | None = None
    #: the /loop message the counters could not be read from (reading stopped there), or None
    damage: str | None = None

    @property
    def in_file(self) -> LossCounts | None:
        """Lost between the file's first and last /loop (what a rotated file adds)."""
        if self.first is None or self.last is None:
            return None
        return self.last.since(self.first)


def log_losses(path: str | os.PathLike, budget_bytes: int = DEFAULT_READ_BUDGET_BYTES) -> LogLosses:
    """The loss counters of the log at ``path`` (read up to any damage; ``budget_bytes``: the
    read budget, ``logs/budget.py``)."""
    out = LogLosses()
    for topic, log_time, _, data in MessageSource(path, budget_bytes=budget_bytes):
        if topic != "/loop":
            continue
        try:
            m = decoded(data)
            lost = _counts(obj(m, "source", optional=True).get("lost"))
            log = m.get("log")
            snl = integer(log, "samples_not_logged", optional=True) if isinstance(log, dict) else None
            outage = number(log.get("outage_s"), "$.log.outage_s") if snl is not None else None
        except BadMessage as exc:  # a foreign or damaged /loop: the totals stop before it
            out.damage = f"/loop message {out.loops + 1} (log time {log_time} ns) is not a valid ahrs.LoopStats: {exc}"
            break
        out.loops += 1
        if lost is not None:
            if out.first is None:
                out.first = lost
            out.last = lost
        if snl is not None:
            out.not_logged_samples = snl
            out.outage_s = 0.0 if outage != outage else outage  # null: none recorded
    return out
