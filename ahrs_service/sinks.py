"""Where estimated blocks go: the service pushes, sinks receive.

The loop runs the pipeline over each block from the source and hands the
:class:`~ahrs_service.pipeline.EstimatedBlock` to every sink, once, in a fixed order: the
attitude monitor, the flight log, MAVLink, the live view. A sink never asks the service for
data: what it needs is in the block, or in the pipeline that estimated it
(``EstimatedBlock.pipeline``), whose newest state the publishers read at their own rates.
What flows the other way — a ground station setting a parameter or starting a calibration —
is control, not data, and goes through the small interfaces the publishers are built with
(``mavlink_bridge.ServiceLink``, the live view's ``set_param``).
"""

from __future__ import annotations

from typing import Any, Callable, Protocol

from ahrs_service.estimators import STATE_HEADER
from ahrs_service.pipeline import EstimatedBlock

_H = STATE_HEADER.slices  # the state header every estimator shares


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
                 on_diagnostics: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.writer = writer
        self.log_truth = log_truth
        self.on_diagnostics = on_diagnostics
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
