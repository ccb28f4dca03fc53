"""Where estimated blocks go: the service pushes, sinks receive.

The loop runs the pipeline over each block from the source and hands the
:class:`~ahrs_service.pipeline.EstimatedBlock` to every sink, once, in a fixed order: the
attitude monitor, the divergence monitor, the flight log, MAVLink, the live view. A sink never
asks the service for data: what it needs is in the block, or in the pipeline that estimated it
(``EstimatedBlock.pipeline``), whose newest state the publishers read at their own rates.
What flows the other way — a ground station setting a parameter or starting a calibration —
is control, not data, and goes through the small interfaces the publishers are built with
(``mavlink_bridge.ServiceLink``, the live view's ``set_param``).
"""

from __future__ import annotations

from typing import Any, Callable, Protocol

import numpy as np

from ahrs_service.core.divergence import DivergenceEvent, DivergenceMonitor, DivergenceSettings, DivergenceVerdict
from ahrs_service.estimators import SAMPLE_ROW, STATE_HEADER
from ahrs_service.pipeline import EstimatedBlock

_H = STATE_HEADER.slices  # the state header every estimator shares
_R = SAMPLE_ROW.slices


class Sink(Protocol):
    """A receiver of estimated blocks, called on the loop thread."""

    def receive(self, estimated: EstimatedBlock) -> None:
        """One block, right after the estimator ran over it. Must be cheap: it runs once per
        block on the loop thread (heavy work goes to the sink's own thread or its own rate)."""

    def close(self) -> None:
        """Stops the sink (the service closes its sinks at shutdown and when a reload replaces them)."""


class FlightLogSink:
    """The MCAP flight log as a sink: every block in one writer call (the writer encodes on
    its own thread); the estimator's diagnostics ride on the next block after each
    :meth:`diagnostics_due`.

    writer: the open ``logs.writer.FlightLogWriter``. log_truth: record the source's ground
    truth (``[log] truth``). on_diagnostics: told each diagnostics record as it is written
    (the service reports a magnetometer rejection starting or ending from it).
    """

    def __init__(self, writer: Any, *, log_truth: bool,
                 on_diagnostics: Callable[[dict[str, Any]], None] | None = None,
                 more_diagnostics: Callable[[], dict[str, Any]] | None = None) -> None:
        self.writer = writer
        self.log_truth = log_truth
        self.on_diagnostics = on_diagnostics
        #: fields added to each diagnostics record (the divergence monitor's verdict)
        self.more_diagnostics = more_diagnostics
        self._diagnostics_due = False

    def diagnostics_due(self) -> None:
        """The next block written carries the estimator's diagnostics."""
        self._diagnostics_due = True

    @property
    def diagnostics_pending(self) -> bool:
        """A diagnostics record is due and not written yet (a reload hands it to the next sink)."""
        return self._diagnostics_due

    def receive(self, estimated: EstimatedBlock) -> None:
        pipeline = estimated.pipeline
        diagnostics = None
        if self._diagnostics_due:
            diagnostics = pipeline.diagnostics()
            if self.more_diagnostics is not None:
                diagnostics.update(self.more_diagnostics())
            if self.on_diagnostics is not None:
                self.on_diagnostics(diagnostics)
        self.writer.write_block(
            estimated.t_ns, estimated.rows, estimated.flags, q=estimated.q, estimator=pipeline.estimator.name,
            t_source_ns=estimated.t_source_ns if pipeline.clock is not None else None,
            bias=estimated.state[_H.bias], state=estimated.state, raw=estimated.raw,
            temperature=estimated.temperature_c, truth_q=estimated.truth_q if self.log_truth else None,
            diagnostics=diagnostics,
        )
        self._diagnostics_due = False

    def close(self) -> None:
        self.writer.close()


class DivergenceSink:
    """The divergence monitor (``core/divergence.py``) as a sink: each block's accelerometer and
    field rows and the estimate after each row go to :class:`DivergenceMonitor`, batched to at
    least ``step_s`` of sample time so the loop pays one list append per block; each change of
    the flag is handed to ``on_change`` (the service reports it) on the loop thread.

    The field goes in only while the pipeline uses it (an estimator with a magnetometer, not in
    its reduced form); rows without a usable field are skipped by the monitor.
    """

    def __init__(self, settings: DivergenceSettings | None = None,
                 on_change: Callable[[DivergenceEvent], None] | None = None) -> None:
        self.monitor = DivergenceMonitor(settings or DivergenceSettings())
        self.on_change = on_change
        self._pending: list[EstimatedBlock] = []
        self._pending_from_ns: int | None = None
        self._batch_ns = int(self.monitor.settings.step_s * 1e9)

    @property
    def verdict(self) -> DivergenceVerdict:
        """The monitor's latest verdict."""
        return self.monitor.verdict

    @property
    def diverged(self) -> bool:
        """The attitude is flagged as not trustworthy now."""
        return self.monitor.verdict.diverged

    def receive(self, estimated: EstimatedBlock) -> None:
        if not len(estimated):
            return
        self._pending.append(estimated)
        if self._pending_from_ns is None:
            self._pending_from_ns = int(estimated.t_ns[0])
        if int(estimated.t_ns[-1]) - self._pending_from_ns >= self._batch_ns:
            self.flush()

    def flush(self) -> None:
        """Runs the monitor over the blocks received and not yet examined."""
        blocks, self._pending, self._pending_from_ns = self._pending, [], None
        if not blocks:
            return
        one = len(blocks) == 1
        t_ns = blocks[0].t_ns if one else np.concatenate([b.t_ns for b in blocks])
        rows = blocks[0].rows if one else np.concatenate([b.rows for b in blocks])
        q = blocks[0].q if one else np.concatenate([b.q for b in blocks])
        pipeline = blocks[-1].pipeline
        mag = rows[:, _R.mag] if pipeline is None or pipeline.use_mag else None
        events = self.monitor.update(t_ns * 1e-9, rows[:, _R.acc], q, mag)
        if self.on_change is not None:
            for event in events:
                self.on_change(event)

    def diagnostics(self) -> dict[str, Any]:
        """The verdict's fields for the log's /attitude diagnostics."""
        return self.monitor.verdict.as_dict()

    def summary(self) -> str:
        """The final summary's part: "attitude: consistent throughout" or how often it diverged."""
        return self.monitor.summary()

    def close(self) -> None:
        self._pending = []
