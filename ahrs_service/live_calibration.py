"""Calibrating while the service runs: gyro bias at rest, and the magnetometer and
accelerometer collections with their fit.

The one computation too long for a tick, the fit at the end of a collection (tens of
milliseconds), runs on a daemon thread ("live-calibration",
:meth:`~ahrs_service.calibration.live.LiveCalibrator.finish_async`); the loop keeps estimating
with the old calibration and, once the fit is done, :meth:`LiveCalibration.apply` swaps the
calibration, reports and records it on the loop thread — between two samples like any other
change, so the log records it at a known sample index.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future, wait
from typing import Any, Protocol

from ahrs_service.calibration.live import LiveCalibrationResult, LiveCalibrator
from ahrs_service.calibration.storage import calibration_section, save_calibration
from ahrs_service.config import Config
from ahrs_service.core.samples import SampleBlock
from ahrs_service.pipeline import EstimationPipeline

log = logging.getLogger("ahrs_service")


class CalibrationHost(Protocol):
    """What a live calibration uses of the running service: the pipeline whose calibration it
    changes, where the calibration is stored, and where outcomes are reported."""

    cfg: Config
    pipeline: EstimationPipeline
    log_writer: Any

    def report(self, text: str, severity: int = 6, kind: str | None = None) -> None: ...

    def effective_config(self) -> dict[str, Any]: ...

    def record_calibration(self, kind: str) -> None: ...


class LiveCalibration:
    """The calibration commands of a running service and the fit running off the loop.

    collector: the running collection (magnetometer or accelerometer), fed by :meth:`collect`.
    """

    def __init__(self, host: CalibrationHost, max_rate_hz: float) -> None:
        self.host = host
        self.collector = LiveCalibrator(max_rate_hz=max_rate_hz)
        #: the running fit of a collection (done: waits for :meth:`apply`), or None
        self.fit: Future[LiveCalibrationResult] | None = None
        self._fit_kind = ""

    # ------------------------------------------------------------------ commands
    def calibrate_gyro(self) -> tuple[bool, str]:
        """The gyro-bias calibration command: accepted only at rest; stored when accepted."""
        pipeline = self.host.pipeline
        check = pipeline.calibrate_gyro_bias()
        if not check.at_rest:
            return False, f"gyro calibration refused: {check.reason}"
        self.host.record_calibration("gyro")
        return True, "gyro bias set to [{:.4f}, {:.4f}, {:.4f}] rad/s".format(*pipeline.calibration.gyro_bias)

    def start(self, kind: str) -> tuple[bool, str]:
        """Starts collecting samples for a magnetometer or accelerometer calibration.

        Returns (started, text for the operator); refused while a collection runs or the
        previous one is still being fitted."""
        try:
            return True, self.collector.start(kind)
        except RuntimeError as exc:  # one is already running, or its fit
            return False, str(exc)

    def record(self, kind: str) -> None:
        """Stores the calibration now in force: in the configuration file (when the service was
        started from one; a ``.bak`` keeps the previous file) and in the log."""
        host = self.host
        cal = host.pipeline.calibration
        host.cfg.raw["calibration"] = calibration_section(cal, host.cfg.raw["calibration"])
        if host.cfg.path is not None:
            try:
                save_calibration(host.cfg.path, cal)
            except (OSError, ValueError) as exc:
                host.report(f"{kind} calibration not saved: {exc}", 4)
        if host.log_writer is not None:
            host.log_writer.write_config(time.monotonic_ns(), host.effective_config(), reason=f"calibration:{kind}")

    # ------------------------------------------------------------------ loop thread
    def collect(self, block: SampleBlock) -> None:
        """Feeds a raw block (sensor axes, as the fit wants them) to the running collection;
        hands it to the fit once it has enough."""
        collector = self.collector
        for sample in block.samples():
            if collector.add(sample):
                self.start_fit()
                break

    def start_fit(self) -> None:
        """The collection is done: hands its data to the fit thread (loop thread, O(1)). The
        loop goes on with the calibration in force; :meth:`apply` swaps it when the fit is done."""
        kind = self.collector.kind or ""
        try:
            self.fit = self.collector.finish_async(self.host.pipeline.calibration)
            self._fit_kind = kind
        except RuntimeError as exc:  # no thread could be started: the collection is lost
            self.host.report(f"{kind} cal failed: {exc}", 4)

    def apply(self) -> None:
        """Applies the finished fit — on the loop thread, between two samples: STATUSTEXT of
        the outcome, and when accepted the new calibration in the pipeline, the configuration
        file and the log (the host's ``record_calibration``). A fit that raised is reported
        (STATUSTEXT warning, log with traceback) and changes nothing."""
        future = self.fit
        if future is None or not future.done():
            return  # nothing to apply yet: a running fit is kept
        self.fit = None
        host = self.host
        exc = future.exception(timeout=0)  # any exception, even a BaseException, stays here
        if exc is not None:
            log.error("live %s calibration: the fit raised", self._fit_kind, exc_info=exc)
            host.report(f"{self._fit_kind} cal failed: {type(exc).__name__}: {exc}", 4)
            return
        result = future.result(timeout=0)
        if result.accepted:
            # onto the calibration in force now: a gyro calibration or a reload during the
            # fit may have changed it, and only the calibrated sensor's terms are the fit's
            host.pipeline.calibration = result.apply_to(host.pipeline.calibration)
        # after the swap: a ground station that reads "done" finds the new calibration in use
        host.report(result.text, 6 if result.accepted else 4)
        if result.accepted:
            host.record_calibration(result.kind)

    def settle(self, timeout_s: float) -> None:
        """At shutdown, after the loop has ended: waits at most ``timeout_s`` s for a running
        fit and applies it (reported, saved, logged after the last sample); a fit still
        running then is abandoned — nothing is applied or saved, and its daemon thread ends
        with the process."""
        future = self.fit
        if future is None:
            return
        wait([future], timeout=timeout_s)
        if future.done():
            self.apply()
        else:
            self.fit = None
            log.warning("live %s calibration: the fit was still running at shutdown; abandoned, "
                        "calibration not changed", self._fit_kind)
