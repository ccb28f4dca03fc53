"""What the running service says about itself: sensor health, the status line, the reports of
faults starting and ending, and the flight log's part of the final summary.

:class:`ServiceHealth` keeps the previous state of every condition it reports (overruns, lost
samples, a lost sensor, the flight log's status, the estimator's form; the divergence monitor
keeps its own flag and hands over its changes), so that each change is reported once —
STATUSTEXT, journal and ``/log`` through the service's ``report`` — and not at every
housekeeping run. It reads the parts it is handed and holds none of them: a reload may
replace the pipeline or the log writer at any time.
"""

from __future__ import annotations

from typing import Any, Callable, Protocol

from ahrs_service.core.divergence import DivergenceEvent
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_VALID, ImuSource, LossCounts
from ahrs_service.mavlink_bridge import LinkHealth
from ahrs_service.pipeline import EstimationPipeline
from ahrs_service.scheduler import LoopStats

#: a tick this late, as a share of what the source's FIFO holds, puts samples at risk
AT_RISK_SHARE = 0.5

#: report(text, severity, kind): STATUSTEXT (rate-limited per kind), journal and /log
Report = Callable[..., None]


class LoopClock(Protocol):
    """What health reads of the loop's scheduler."""

    overruns: int

    def stats(self) -> LoopStats: ...


class ServiceHealth:
    """Health bits, the one-line status and the change reports of a running service."""

    def __init__(self, report: Report) -> None:
        self.report = report
        self.last_load_percent = 0.0  # the loop's busy time at the last housekeeping, % (SYS_STATUS)
        self.last_lost = False  # the source reported its device lost at the last housekeeping
        self.was_reduced = False  # the estimator's form at the last check (report_form_change)
        self._last_loss = LossCounts()
        self._last_log_status = "ok"
        #: log writers a reload closed (their counts stay in the final summary)
        self.earlier_log_writers: list[Any] = []

    # ------------------------------------------------------------------ state now
    def sensors(self, pipeline: EstimationPipeline, source: ImuSource | None) -> dict[str, bool]:
        """Present/healthy bits for gyro, accelerometer and magnetometer (SYS_STATUS)."""
        s = pipeline.last_sample
        flags = s.flags if s is not None else 0
        lost = bool(source.diagnostics.device_lost) if source else True
        # a board names the parts it lost: a lost magnetometer is a magnetometer fault (reduced
        # mode), not an IMU fault; other sources only say "lost"
        parts = getattr(source, "lost", None)
        imu_lost = lost if not isinstance(parts, (set, frozenset)) else bool(parts & {"gyro", "acc"})
        mag_lost = isinstance(parts, (set, frozenset)) and "mag" in parts
        return {
            "gyro_healthy": bool(flags & GYR_VALID) and not imu_lost,
            "accel_healthy": bool(flags & ACC_VALID) and not imu_lost,
            "mag_present": bool(getattr(source, "has_mag", False)),
            "mag_healthy": bool(flags & MAG_VALID or s is not None and s.mag is None)
                           and not pipeline.reduced and not mag_lost,
        }

    def link_health(self, pipeline: EstimationPipeline, source: ImuSource, loop: LoopClock) -> LinkHealth:
        """Health bits and fault counters for SYS_STATUS."""
        h = self.sensors(pipeline, source)
        diag = source.diagnostics
        return LinkHealth(
            gyro_healthy=h["gyro_healthy"], accel_healthy=h["accel_healthy"],
            mag_present=h["mag_present"], mag_healthy=h["mag_healthy"],
            overruns=loop.overruns, load_percent=self.last_load_percent,
            comm_errors=diag.bus_errors, sensor_faults=diag.saturated + diag.non_finite,
            lost_samples=diag.lost.total,
        )

    def status_line(self, pipeline: EstimationPipeline, source: ImuSource | None, st: LoopStats) -> str:
        """One line of rate and health (systemd STATUS=, logs)."""
        mode = "reduced" if pipeline.reduced else "full"
        # a FIFO board's rows come at its sensor's rate, the loop wakes at its drain rate
        sensor_hz = source.diagnostics.extra.get("sensor_rate_hz") if source is not None else None
        rows = f"rows at {sensor_hz:.0f} Hz, " if isinstance(sensor_hz, (int, float)) else ""
        return (
            f"{pipeline.estimator.name} ({mode}) {rows}loop at {st.rate_hz:.0f} Hz, CPU {st.cpu_percent:.1f}% of a core, "
            f"busy {st.load_percent:.0f}% of each period, "
            f"jitter p99 {st.period_jitter_p99_us:.0f} us, overruns {st.overruns}, samples {pipeline.samples}, "
            f"lost {self.loss_text(source)}"
        )

    @staticmethod
    def loss_text(source: ImuSource | None, lost: LossCounts | None = None) -> str:
        """Lost IMU samples, total and by cause: "0" or "12 (fifo_overflow 12)"."""
        if lost is None:
            lost = source.diagnostics.lost if source is not None else LossCounts()
        return lost.summary()

    # ------------------------------------------------------------------ changes, reported once
    def report_faults(self, st: LoopStats, source: ImuSource, diag: dict[str, Any]) -> None:
        """Housekeeping's reports: overruns and lost samples of the last second, the sensor
        lost or back. ``diag``: the source's diagnostics as a dict, taken once."""
        self.last_load_percent = st.load_percent
        self.report_samples_at_risk(st, source)
        lost_now = source.diagnostics.lost
        if lost_now.total > self._last_loss.total:
            self.report(f"IMU samples lost: {self.loss_text(source, lost_now.since(self._last_loss))} "
                        "in the last second", 4)
            self._last_loss = lost_now.copy()
        lost = bool(diag.get("device_lost"))
        if lost != self.last_lost:
            self.last_lost = lost
            self.report(f"sensor lost: {diag.get('last_error', '')}" if lost else "sensor back", 3 if lost else 6)

    def report_samples_at_risk(self, st: LoopStats, source: ImuSource) -> None:
        """A warning when the loop came late by ``AT_RISK_SHARE`` of what the source's FIFO holds
        (``ImuSource.late_tolerance_s``): samples were nearly lost. A late tick whose samples the
        FIFO kept is only counted (``overruns``, ``lateness_max_us`` in ``/loop``); a sample
        actually lost is reported as lost."""
        tolerance_s = source.late_tolerance_s
        late_s = st.lateness_max_us * 1e-6
        if tolerance_s is None or late_s < max(AT_RISK_SHARE * tolerance_s, 1.0 / st.rate_hz):
            return
        self.report(f"loop overruns: the loop woke {late_s * 1e3:.0f} ms late and the IMU's FIFO holds "
                    f"{tolerance_s * 1e3:.0f} ms: samples at risk (a busy computer: docs/systemd.md, "
                    "real-time scheduling)", 4)

    def report_form_change(self, reduced: bool) -> None:
        """The estimator switched between its full and its reduced (no magnetometer) form."""
        if reduced != self.was_reduced:
            self.was_reduced = reduced
            self.report("magnetometer lost: estimating in reduced form" if reduced else "magnetometer back: full form",
                        4 if reduced else 6)

    def report_divergence(self, event: DivergenceEvent) -> None:
        """The divergence monitor flagged the attitude (STATUSTEXT CRITICAL: not to be trusted)
        or cleared it (INFO); the monitor hands over each change of its flag once."""
        self.report(event.text(), 2 if event.diverged else 6)

    def report_log_status(self, writer: Any) -> None:
        """STATUSTEXT + journal + /log when logging stops (the path and the system's error
        text) and when it resumes (what the outage cost); rate-limited as kind "flight log"."""
        status = writer.status
        if status == self._last_log_status or status == "starting":
            return
        self._last_log_status = status
        if status == "error":
            self.report(f"flight log stopped: {writer.last_error}; retrying", 3, kind="flight log")
        elif status == "ok" and writer.last_outage is not None:
            out = writer.last_outage
            self.report(f"flight log resumed: {out.samples} samples ({out.seconds:.1f} s) not logged", 5,
                        kind="flight log")

    # ------------------------------------------------------------------ the final summary
    def log_summary(self, writer: Any | None) -> str:
        """The flight log's part of the final summary: files, and what is not in them (over
        every writer of the run: ``writer``, the open one, and those a reload closed)."""
        writers = [*self.earlier_log_writers, *([writer] if writer is not None else [])]
        if not writers:
            return "log: off"
        w = writers[-1]
        gone = [x.not_logged() for x in writers]
        samples, messages = sum(g.samples for g in gone), sum(g.messages for g in gone)
        seconds, outages = sum(g.seconds for g in gone), sum(x.outages for x in writers)
        kept = [p for x in writers for p in x.files if p.exists()]  # a file deleted while written is not kept
        # the folders the files are in (a reload may have moved the log), else the configured one
        folders = list(dict.fromkeys(str(p.parent) for p in kept)) or [str(w.directory)]
        files = f"log: {len(kept)} file{'s' if len(kept) != 1 else ''} in {' and '.join(folders)}"
        if not messages:
            return f"{files}, everything logged"
        last_error = next((x.last_error for x in reversed(writers) if x.last_error), "none")
        return (f"{files}, not logged: {samples} samples, {messages} messages, {seconds:.1f} s "
                f"({outages} outage{'s' if outages != 1 else ''}; last error: {last_error})")
