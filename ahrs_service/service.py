"""The AHRS service: source → estimator at a fixed rate → MAVLink out, MCAP log, systemd.

One thread runs everything, in this order each tick: read a block of samples from the source
(a FIFO burst, or the one sample a polling source has), run the pipeline over it
(:meth:`~ahrs_service.pipeline.EstimationPipeline.process_block`: calibration, then the
estimator), hand the estimated block to the sinks (``sinks.py``: the attitude monitor, the
flight log — one call into the writer's queue, which encodes on its own thread — MAVLink, the
live view), then run the periodic jobs that are due (:class:`LoopSchedule`: MAVLink and the
live view publish the newest estimate at their own rates, diagnostics, the systemd watchdog,
housekeeping). Parameter changes and commands are therefore applied between two blocks, at a
sample index the log records, so a replay reproduces every published attitude.

The service pushes, sinks receive: no sink asks the service for data. Control goes the other
way — a ground station's parameter write or calibration command (``mavlink_bridge.ServiceLink``),
a Foxglove client's parameter set — and is applied by the loop between two blocks.

Beside the loop, each in its own module: the reload on SIGHUP (``reload.ConfigReload``), the
live calibrations and their fit off the loop thread (``live_calibration.LiveCalibration``),
and what the service reports about its health (``health.ServiceHealth``).
"""

from __future__ import annotations

import dataclasses
import gc
import logging
import signal
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable

from ahrs_service import config as config_mod
from ahrs_service import estimators, kernels
from ahrs_service.calibration.storage import calibration_from_config_dict
from ahrs_service.core.calibration import SensorCalibration
from ahrs_service.core.divergence import DivergenceSettings
from ahrs_service.core.samples import ImuSource, LossCounts, SampleBlock
from ahrs_service.core.vibration import VibrationMonitor
from ahrs_service.health import ServiceHealth
from ahrs_service.live_calibration import LiveCalibration

# imported with the service, not when the log opens: its ~40 ms of modules (mcap, the
# schemas) fell between the source's start and its first read
from ahrs_service.logs.redaction import redact_text, secret_values
from ahrs_service.logs.writer import FlightLogWriter
from ahrs_service.mavlink_bridge import STALE_NS, ServiceLink
from ahrs_service.pipeline import EstimatedBlock, EstimationPipeline
from ahrs_service.realtime import RealtimeSettings, apply_to_this_thread, undo_memory_lock
from ahrs_service.reload import RELOAD_MAX_WAIT_NS, RELOAD_SETTLE_NS, ConfigReload  # noqa: F401 (their old home)
from ahrs_service.scheduler import DataReadyScheduler, FixedRateScheduler, LoopStats
from ahrs_service.sinks import DivergenceSink, FlightLogSink, Sink
from ahrs_service.sources import make_source
from ahrs_service.systemd import Notifier

log = logging.getLogger("ahrs_service")

IO_PERIOD_NS = 5_000_000  # MAVLink publish/poll granularity: 200 Hz
HOUSEKEEPING_NS = 1_000_000_000  # loop statistics, STATUS=, health reports
SOURCE_SET_PERIOD_NS = 50_000_000  # the heading's health looked at for the EKF source set: 20 Hz
MAX_SAMPLES_PER_TICK = 64  # a source with a backlog catches up at most this fast (one block)
# how long close() waits for a running live-calibration fit, s: fits take tens of ms, and
# the whole stop must stay well within 2 s (systemd's TimeoutStopSec is 5 s)
LIVE_FIT_CLOSE_WAIT_S = 0.5


@dataclass
class PeriodicJob:
    """A job the loop runs every ``period_ns`` (monotonic ns) of its own clock.

    keep_phase: the next run is one period after the last *scheduled* one (a late tick does
    not shift the schedule, so publishing keeps its rate), unless the loop fell a whole
    period behind; otherwise one period after the actual run.
    """

    name: str
    period_ns: int
    run: Callable[[int], None]
    keep_phase: bool = False
    next_ns: int = 0
    failures: int = 0  # runs that raised (counted, reported, survived: LoopSchedule)


class LoopSchedule:
    """The loop's timers in one place: named periodic jobs, run in the order given when due.

    A job that raises is counted (``PeriodicJob.failures``) and handed to ``on_error``; the
    other jobs and the loop go on: one bad input reaching a job (a hostile message, a
    counter of the wrong kind) must not stop estimation and publishing."""

    def __init__(self, jobs: list[PeriodicJob], now_ns: int,
                 on_error: Callable[[PeriodicJob, Exception], None] | None = None) -> None:
        self.jobs = [j for j in jobs if j.period_ns > 0]
        self.on_error = on_error
        for job in self.jobs:
            job.next_ns = now_ns

    def run_due(self, now_ns: int) -> None:
        for job in self.jobs:
            if now_ns >= job.next_ns:
                if job.keep_phase:
                    job.next_ns += job.period_ns
                    if now_ns > job.next_ns:
                        job.next_ns = now_ns + job.period_ns
                else:
                    job.next_ns = now_ns + job.period_ns
                try:
                    job.run(now_ns)
                except Exception as exc:  # noqa: BLE001 - counted and reported, the loop goes on
                    job.failures += 1
                    if self.on_error is not None:
                        self.on_error(job, exc)

    def names(self) -> list[str]:
        return [j.name for j in self.jobs]


def _freeze_heap() -> None:
    """Moves everything allocated so far (modules, compiled kernels, config) out of the cyclic
    garbage collector's reach: a full collection over them takes ~30 ms, thirty missed ticks
    at 1 kHz, and none of them will ever become garbage in the loop."""
    gc.collect()
    gc.freeze()


class Service:
    """The running service. ``start`` → ``run`` (until stopped) → ``close``."""

    def __init__(self, cfg: config_mod.Config, *, duration_s: float | None = None, notifier: Notifier | None = None):
        self.cfg = cfg
        self.duration_s = duration_s
        self.notifier = notifier or Notifier()
        self.boot_ns = time.monotonic_ns()
        self._stop = False
        self.reloads = ConfigReload(self)  # SIGHUP: when the next reload is due, and the reload
        self.health_report = ServiceHealth(self.report)
        self.source: ImuSource | None = None
        self.mavlink = None
        self.log_writer = None
        self.log_sink: FlightLogSink | None = None  # the flight log as a sink, when [log] enabled
        self.live = None  # the Foxglove live view (live_view.LiveView) when [live] enabled
        self.monitor = None  # the autopilot attitude monitor (attitude_monitor.py) beside an autopilot
        self.divergence: DivergenceSink | None = None  # the divergence monitor, when [divergence] enabled
        #: beside ArduPilot fusing our heading: asks it for its fallback EKF source set when the
        #: heading is not trustworthy or the service stops (open_source_switch)
        self.source_switch: Any = None
        self._heading_samples, self._heading_fresh_ns = -1, 0  # heading_trust's freshness test
        #: what receives each estimated block, in this order (connect_sinks)
        self.sinks: tuple[Sink, ...] = ()
        self.calibration_session = LiveCalibration(self, max_rate_hz=cfg.rates["estimation_hz"])
        self.live_calibration = self.calibration_session.collector  # the running collection, if any
        self.vibration = VibrationMonitor()  # VIBRATION's levels and clipping, from every sample row
        #: the field's use in the last diagnostics record: "accepted", "confirming" (the
        #: start-up field not confirmed yet) or "rejected" (_report_mag_rejection)
        self._mag_state = "accepted"
        self.compiler = kernels.ReloadCompiler()  # a reload to an estimator not yet compiled
        # beside an autopilot (source.type = "mavlink"): the source's link, which carries
        # ODOMETRY (open_mavlink), the monitor's attitudes and TIMESYNC; set once the source
        # is open (a reload keeps the source)
        self._autopilot_link: Any = None
        self._timesync_logged_ns: int | None = None  # the TIMESYNC estimate last on /timesync
        self._secrets_of: Any = None  # the configuration self._secrets were taken from
        self._secrets: list[str] = []
        self._memory_locked = False  # [service] lock_memory took effect (undone by close)
        #: the handlers install_signal_handlers replaced, put back by close()
        self._replaced_handlers: dict[signal.Signals, Any] = {}

    # ------------------------------------------------------------------ set-up
    def start(self) -> None:
        cfg = self.cfg
        self.build_estimation(cfg)
        if not estimators.kernels_cached(self.estimator.name):  # a start that would say nothing for minutes
            log.info("compiling the %s kernels: the first start after an install or upgrade takes seconds for a "
                     "paper filter, minutes for robust; later starts load them from the cache", self.estimator.name)
        if self.notifier.enabled:
            # under systemd a first start compiles for up to minutes: a child does it while
            # this process keeps extending systemd's start timeout (EXTEND_TIMEOUT_USEC)
            child = kernels.compile_in_child([self.estimator.name], self.notifier, stop=lambda: self._stop)
            if self._stop:
                raise RuntimeError("stopped while the estimator kernels compiled")
            if not child.ok:
                log.warning("compiling in a child process failed (%s); compiling here", child.error)
        t0 = time.monotonic()
        self.warm_up()
        if time.monotonic() - t0 > 1.0:
            log.info("compiled the %s kernels in %.0f s (first start only)", self.estimator.name, time.monotonic() - t0)
        # the heap so far (modules, compiled kernels) frozen before the part starts filling its
        # FIFO: run()'s own freeze then walks only what the start adds after this (tens of ms
        # less between the source's start and its first read)
        _freeze_heap()
        self.source = make_source(cfg.source, cfg.rates["estimation_hz"], cfg.mavlink["system_id"],
                                  companion=cfg.mavlink["identity"] == "companion")
        self.source.open()
        self._autopilot_link = getattr(self.source, "autopilot_link", None)
        if not self.source.has_mag:
            # a part without magnetometer (ICM-42688-P, BMI088): no start waiting for a field
            self.pipeline.use_mag = False
        self.use_clock_recovery()
        line = getattr(self.source, "data_ready_line", None)
        if line is not None:
            # the FIFO watermark wakes the loop; the timer stays the fallback (DataReadyScheduler)
            self.scheduler = DataReadyScheduler(line, self.source.wakeup_rate_hz)
        else:
            # a source whose samples carry their own times (a FIFO) is not timed by the
            # wake-up: polling the clock for the last microseconds before it buys nothing
            spin_ns = 0 if self.source.times_on_sensor_clock else FixedRateScheduler.SPIN_NS
            self.scheduler = FixedRateScheduler(self.loop_rate_hz(cfg), spin_ns=spin_ns)
        self._ticks_missed_counted = 0  # the scheduler's missed ticks already counted as lost
        self.use_source_calibration()
        self.open_divergence(cfg)
        self.open_log(cfg)
        self.open_mavlink(cfg)
        self.open_live(cfg)
        self.open_monitor(cfg)
        self.connect_sinks()

    def connect_sinks(self) -> None:
        """The sinks of each estimated block, in the order they get it; the publishers follow
        the pipeline now in force (at the start, and after a reload replaced parts)."""
        self.sinks = tuple(sink for sink in (self.monitor, self.divergence, self.log_sink, self.mavlink, self.live)
                           if sink is not None)
        for publisher in (self.mavlink, self.live):
            if publisher is not None:
                publisher.follow(self.pipeline)

    def open_divergence(self, cfg: config_mod.Config) -> None:
        """The divergence monitor (``[divergence]``): the accelerometer against the estimate;
        its flag's changes are reported once each (``ServiceHealth.report_divergence``). A reload
        with other settings starts a new monitor; a flag that was up is reported cleared."""
        earlier = self.divergence
        if earlier is not None and earlier.diverged:
            self.report("divergence monitor restarted with new settings: flag cleared", 6)
        self.divergence = None
        section = cfg.divergence
        if section["enabled"]:
            self.divergence = DivergenceSink(DivergenceSettings.from_config(section),
                                             on_change=self.health_report.report_divergence)

    def attitude_diverged(self) -> bool:
        """The divergence monitor says the attitude is not to be trusted (SYS_STATUS, ODOMETRY)."""
        return self.divergence is not None and self.divergence.diverged

    def _divergence_diagnostics(self) -> dict[str, Any]:
        """The divergence monitor's verdict for the log's /attitude diagnostics ({} when off)."""
        return self.divergence.diagnostics() if self.divergence is not None else {}

    def divergence_summary(self) -> str:
        """The final summary's part about the attitude's consistency."""
        return self.divergence.summary() if self.divergence is not None else "attitude: not monitored"

    def odometry_summary(self) -> str:
        """The final summary's part about ODOMETRY sent to an autopilot ("" when it is off)."""
        odometry = None if self.mavlink is None else self.mavlink.odometry
        if odometry is None:
            return ""
        st = odometry.stats
        return (f"ODOMETRY: sent {st.sent} ({st.not_synced} before TIMESYNC synced), heading resets {st.resets}, "
                f"send errors {st.send_errors}")

    def _timesync_tick(self) -> None:
        """Beside an autopilot: the link's TIMESYNC estimate, logged on /timesync once per new
        estimate (ODOMETRY's link and clock: open_mavlink)."""
        link = self._autopilot_link
        with link.timesync_lock:
            status = link.timesync.last_status
        if status is not None and status.local_ns != self._timesync_logged_ns and self.log_writer is not None:
            self._timesync_logged_ns = status.local_ns
            self.log_writer.write_timesync(status)

    def open_monitor(self, cfg: config_mod.Config) -> None:
        """The attitude monitor, when the source has an autopilot link (source.type = "mavlink")."""
        if self.monitor is not None:  # a reload with other [monitor] settings
            self.monitor.close()
            self.monitor = None
        link = self._autopilot_link
        if link is None or not cfg.monitor["enabled"]:
            return
        from ahrs_service.attitude_monitor import AttitudeMonitor

        mon = cfg.monitor
        self.monitor = AttitudeMonitor(link, threshold_deg=mon["threshold_deg"], hold_s=mon["hold_s"])
        self._monitor_period_ns = int(1e9 / mon["rate_hz"])
        self._next_monitor_ns = 0

    def _monitor_tick(self, now: int) -> None:
        """Compares the autopilot's attitudes received so far with ours; at ``[monitor] rate_hz``
        publishes the disagreement (NAMED_VALUE_FLOAT); logs every comparison; reports the
        warning and the all-clear (STATUSTEXT through the rate limit, journal, /log)."""
        from ahrs_service.protocols.mavlink.dialect import mavlink

        self.monitor.request_stream(now)
        comparisons, events = self.monitor.update(self.pipeline.declination_deg)
        if self.log_writer is not None:
            for d in comparisons:
                self.log_writer.write_autopilot_attitude(d)
        for event in events:
            self.mavlink.component.statustext(event.severity, event.text, kind="attitude monitor")
            self.log_event(event.text, event.severity)
        if now >= self._next_monitor_ns and self.monitor.latest is not None:
            self._next_monitor_ns = now + self._monitor_period_ns
            boot_ms = (now - self.boot_ns) // 1_000_000
            for name, value in self.monitor.named_values():
                self.mavlink.component.send(
                    mavlink.MAVLink_named_value_float_message(boot_ms & 0xFFFFFFFF, name.encode(), value))
            if self.live is not None:  # viewers get the latest comparison at the same rate
                from ahrs_service.logs.schemas import autopilot_attitude_messages

                d = self.monitor.latest
                for topic, message in autopilot_attitude_messages(d.t_ns, list(d.q_autopilot), list(d.q_estimate),
                                                                  d.total_deg, d.inclination_deg,
                                                                  d.heading_deg).items():
                    self.live.publish(topic, d.t_ns, message)

    def warm_up(self) -> None:
        """Compiles the pipeline's kernels. numba saves each new kernel to its cache after
        compiling it and raises when the disk refuses the file (full, read-only); the kernel
        is in memory all the same, so the next call goes on to the next kernel: a full disk
        costs the cache, never the start."""
        attempts = 64  # bounded: one kernel more per attempt, a pipeline has ~10
        for attempt in range(attempts):
            try:
                kernels.warm_up(self.estimator.name)  # the pipeline's kernels and VIBRATION's
                return
            except OSError as exc:
                if attempt == attempts - 1:
                    raise
                if attempt == 0:
                    log.warning("compiled kernels not cached: %s", exc)

    def loop_rate_hz(self, cfg: config_mod.Config) -> float:
        """How often the loop wakes, Hz: a source read in bursts (a FIFO) at its drain rate
        (``wakeup_rate_hz``, each wake-up a block), any other once per sample."""
        return self.source.wakeup_rate_hz or cfg.rates["estimation_hz"]

    def use_clock_recovery(self) -> None:
        """Sample times from stamps that are host arrival times: recovered onto the sensor's
        clock (``sample_clock.SampleClock`` at the estimation rate) for a source that hands
        out every sample it receives (``may_have_backlog``: a recording, a CAN node). Not for
        a FIFO board or a flight log (``times_on_sensor_clock``: timed already), nor for a
        polling board that reads only the newest sample: a late loop skips samples there
        without a counter to tell, and the clock line then bends instead of counting a gap
        (recovered times tens of ms before the read times), so its read times are kept
        (docs/timing.md)."""
        source = self.source
        if not source.times_on_sensor_clock and source.may_have_backlog:
            self.pipeline.use_sample_clock(self.cfg.rates["estimation_hz"])

    def open_live(self, cfg: config_mod.Config) -> None:
        if cfg.live["enabled"]:
            from ahrs_service.live_view import open_live_view

            self.live = open_live_view(self.pipeline, self.set_estimator_param, cfg.live)

    def build_estimation(self, cfg: config_mod.Config) -> None:
        est_cfg = cfg.estimator
        estimator = estimators.create(est_cfg["name"], **est_cfg["params"])
        self.pipeline = EstimationPipeline(
            estimator,
            calibration_from_config_dict(cfg.raw),
            mag_timeout_s=est_cfg["mag_timeout_s"],
            declination_deg=self.declination_deg(cfg),
            nominal_dt=1.0 / cfg.rates["estimation_hz"],
            use_mag=self.source is None or self.source.has_mag,
        )

    def declination_deg(self, cfg: config_mod.Config) -> float:
        """The configured declination, or the World Magnetic Model's for the configured place today."""
        loc = cfg.location
        if loc["latitude_deg"] is None:
            heading_sent = cfg.mavlink["odometry"]["rate_hz"] > 0 and (self.source is None or self.source.has_mag)
            if cfg.estimator["declination_deg"] == 0.0 and heading_sent:
                log.warning("ODOMETRY sends a magnetic heading (declination 0) that the autopilot takes as "
                            "true north: set [location] (declination from the World Magnetic Model) or "
                            "estimator.declination_deg")
            return cfg.estimator["declination_deg"]
        from ahrs_service.calibration.declination import declination_deg

        value = declination_deg(loc["latitude_deg"], loc["longitude_deg"], loc["altitude_km"])
        log.info("magnetic declination %.2f° from the World Magnetic Model", value)
        return value

    def use_source_calibration(self) -> None:
        """A recorded log hands out samples already calibrated into the body frame."""
        if getattr(self.source, "calibrated", False):
            if self.cfg.calibration:
                log.info("recorded source is already calibrated: the configured calibration is not applied")
            self.pipeline.calibration = SensorCalibration()

    @property
    def estimator(self):
        return self.pipeline.estimator

    def open_log(self, cfg: config_mod.Config) -> None:
        earlier = self.log_sink
        if not cfg.log["enabled"]:
            self.log_writer = self.log_sink = None
            return
        mb, minutes = cfg.log["rotate_mb"], cfg.log["rotate_minutes"]
        self.log_writer = FlightLogWriter(
            cfg.log["directory"],
            rotate_bytes=int(mb * 1e6) if mb else None,
            rotate_seconds=minutes * 60 if minutes else None,
            first_sample_index=self.pipeline.samples,
            loop=self.scheduler,  # the writer leaves the interpreter free at the loop's wake-ups
            block_messages_above_hz=cfg.log["block_messages_above_hz"],
        )
        self.log_writer.write_config(time.monotonic_ns(), self.effective_config())
        self.log_sink = FlightLogSink(self.log_writer, log_truth=cfg.log["truth"],
                                      on_diagnostics=self._report_mag_rejection,
                                      more_diagnostics=self._divergence_diagnostics)
        if earlier is not None and earlier.diagnostics_pending:  # a record due goes to the new file
            self.log_sink.diagnostics_due()

    def effective_config(self) -> dict[str, Any]:
        """The configuration in force, with the estimator's full parameter set."""
        raw = {k: dict(v) for k, v in self.cfg.raw.items()}
        raw["estimator"] = dict(raw["estimator"], params=self.estimator.get_params())
        return raw

    def open_mavlink(self, cfg: config_mod.Config) -> None:
        from ahrs_service.mavlink_bridge import MavlinkBridge

        self.mavlink = MavlinkBridge(self.bridge_link(), cfg, io_period_ns=IO_PERIOD_NS, estimates=self.pipeline)
        self.open_source_switch(cfg)

    def open_source_switch(self, cfg: config_mod.Config) -> None:
        """ArduPilot's EKF source sets (``protocols/mavlink/ekf_source.py``, docs/autopilot.md,
        "Fallback when the companion stops"): on when ODOMETRY goes on the autopilot link
        under ArduPilot's rules and ``fallback_source_set`` is not 0. A reload with the same
        sets keeps the switch and what it asked; other sets start a new one, counters kept."""
        from ahrs_service.protocols.mavlink.ekf_source import EkfSourceSwitch

        ocfg = cfg.mavlink["odometry"]
        sets = (ocfg["primary_source_set"], ocfg["fallback_source_set"])
        wanted = (self._autopilot_link is not None and ocfg["rate_hz"] > 0 and ocfg["rules"] == "ardupilot"
                  and sets[1] != 0)
        earlier = self.source_switch
        if earlier is not None and wanted and (earlier.primary_set, earlier.fallback_set) == sets:
            return
        if earlier is not None:
            earlier.close()
        self.source_switch = None
        if wanted:
            self.source_switch = EkfSourceSwitch(self._autopilot_link, primary_set=sets[0], fallback_set=sets[1],
                                                 stats=None if earlier is None else earlier.stats)

    def heading_trust(self, now_ns: int) -> tuple[bool, str]:
        """Whether the heading we publish is worth an autopilot's fusing, and if not why: an
        estimate initialised, fresh (a sample within the bridge's ``STALE_NS``), with the
        magnetometer in use (reduced form observes no heading) and not flagged by the
        divergence monitor."""
        est = self.pipeline.latest_estimate() if self.pipeline is not None else None
        if est is None:
            return False, "no estimate yet"
        if est.samples != self._heading_samples:
            self._heading_samples, self._heading_fresh_ns = est.samples, now_ns
        if now_ns - self._heading_fresh_ns > STALE_NS:
            return False, "no IMU samples"
        if not est.initialised:
            return False, "estimator not initialised"
        if self.attitude_diverged():
            return False, "attitude diverged"
        if not est.mag_used:
            return False, "no magnetometer in use"
        return True, ""

    def _source_set_tick(self, now: int) -> None:
        trusted, why = self.heading_trust(now)
        for severity, text in self.source_switch.update(now, trusted, why):
            self.report(text, severity, kind="ekf source set")

    def _fall_back_at_stop(self) -> None:
        """A clean stop: ArduPilot is asked for its fallback source set, its answer waited for
        (``EkfSourceSwitch.fall_back_at_stop``: under a second) and reported once."""
        switch = self.source_switch
        if switch is None or switch.stopped:
            return
        try:
            for severity, text in switch.fall_back_at_stop():
                self.report(text, severity, kind="ekf source set")
        except Exception as exc:  # noqa: BLE001 - the rest of the stop must happen all the same
            log.warning("EKF source set at stop: %s: %s", type(exc).__name__, exc)
        finally:
            switch.close()

    def source_set_summary(self) -> str:
        """The final summary's part about ArduPilot's EKF source sets ("" when not asked for)."""
        return "" if self.source_switch is None else self.source_switch.summary()

    def bridge_link(self) -> ServiceLink:
        """The control and status the MAVLink bridge passes through (mavlink_bridge.ServiceLink);
        the estimates it publishes are pushed to it as a sink."""
        est = self.estimator
        link = self._autopilot_link
        calibration = self.calibration_session
        return ServiceLink(
            boot_ns=self.boot_ns,
            estimator=est.name,
            param_names=est.param_names(),
            health=self.link_health,
            get_param=lambda name: self.estimator.get_params()[name],
            set_param=self.set_estimator_param,
            get_declination=lambda: self.pipeline.declination_deg,
            set_declination=lambda deg: self.pipeline.set_declination(deg),
            loop_rate_hz=lambda: float(self.cfg.rates["estimation_hz"]),
            calibrate_gyro=calibration.calibrate_gyro,
            start_calibration=calibration.start,
            vibration=self.vibration.levels,
            # beside an autopilot ODOMETRY goes on its link, stamped in its clock (docs/autopilot.md)
            odometry_send=None if link is None else link.send,
            odometry_clock=None if link is None else link.clock,
            attitude_diverged=self.attitude_diverged,
            set_param_from=self.set_estimator_param,  # (name, value, source): /params and /log with the sender
            record_write=self.record_write,
            autopilot=link,  # its HEARTBEATs say whether it is armed (no calibration then)
        )

    def link_health(self):
        """Health bits and fault counters for SYS_STATUS (mavlink_bridge.LinkHealth)."""
        return self.health_report.link_health(self.pipeline, self.source, self.scheduler)

    def health(self) -> dict[str, bool]:
        """Present/healthy bits for gyro, accelerometer and magnetometer (SYS_STATUS)."""
        return self.health_report.sensors(self.pipeline, self.source)

    # ------------------------------------------------------------------ control
    def request_stop(self, *_: Any) -> None:
        self._stop = True

    def request_reload(self, *_: Any) -> None:
        """SIGHUP: a reload, run by the loop once signals have paused (``ConfigReload.request``)."""
        self.reloads.request(time.monotonic_ns())

    def reload(self) -> None:
        """Re-reads the configuration file and applies it; a bad file changes nothing."""
        self.reloads.run()

    def install_signal_handlers(self) -> None:
        """SIGTERM and SIGINT stop the loop, SIGHUP reloads the configuration; :meth:`close`
        puts back the handlers these replaced, once everything is closed (a signal during
        the log's close only asks for a stop that is under way)."""
        for sig, handler in ((signal.SIGTERM, self.request_stop), (signal.SIGINT, self.request_stop),
                             (signal.SIGHUP, self.request_reload)):
            self._replaced_handlers.setdefault(sig, signal.getsignal(sig))
            signal.signal(sig, handler)

    def _restore_signal_handlers(self) -> None:
        for sig, previous in self._replaced_handlers.items():
            if previous is None:  # installed outside Python: nothing to put back
                continue
            try:
                signal.signal(sig, previous)
            except ValueError:  # closed from another thread than the one that installed them
                log.warning("signal handlers not restored: close() called outside the main thread")
                break
        self._replaced_handlers.clear()

    def report(self, text: str, severity: int = 6, kind: str | None = None) -> None:
        """A health message: STATUSTEXT on MAVLink, the service log and /log. ``kind`` puts
        the STATUSTEXT under the rate limit of that kind (``statustext_limit``)."""
        text = self._without_secrets(text)
        if self.mavlink is not None:
            self.mavlink.statustext(severity, text, kind)
        self.log_event(text, severity)

    def _without_secrets(self, text: str) -> str:
        """``text`` with the configuration's secrets (``mavlink.signing_key`` …) redacted: an
        error may quote a value, and nothing secret goes to STATUSTEXT, the journal or /log."""
        cfg = self.cfg
        if self._secrets_of is not cfg:
            self._secrets_of, self._secrets = cfg, secret_values(cfg.raw)
        return redact_text(text, self._secrets) if self._secrets else text

    def log_event(self, text: str, severity: int = 6) -> None:
        """A health event for the journal and /log (flight log and live view), not STATUSTEXT:
        rejections and parameter changes, too frequent or too minor for the ground station.
        ``severity``: MAVLink's, 0 emergency … 7 debug."""
        text = self._without_secrets(text)
        log.log(logging.WARNING if severity <= 4 else logging.INFO, text)
        now = time.monotonic_ns()
        if self.log_writer is not None:
            self.log_writer.write_log(now, severity, text)
        if self.live is not None:
            self.live.log_event(now, severity, text)

    def diagnostics(self) -> dict[str, Any]:
        """The estimator's diagnostics (rest, rejections, bias trust …) and the form it runs in."""
        return self.pipeline.diagnostics()

    def _report_mag_rejection(self, diag: dict[str, Any]) -> None:
        """Each diagnostics record the flight log writes: reports the field's use changing.

        ``mag_disturbed`` says the estimator does not use its field for the heading. While it
        has not confirmed its start-up field yet (``mag_confirmed`` False: robust's start-up
        confirmation, VQF's magNewFirstTime, docs/robust-estimator.md) that is the
        confirmation under way — the first field set the heading, and steers it once it has
        stayed steady while turning — which has found no disturbance: information. A field
        rejected after it was confirmed (or by an estimator without that flag) failed the
        estimator's disturbance tests: a warning."""
        if not diag.get("mag_disturbed", False):
            state = "accepted"
        elif diag.get("mag_confirmed", True):
            state = "rejected"
        else:
            state = "confirming"
        previous, self._mag_state = self._mag_state, state
        if state == previous:
            return
        if state == "rejected":
            self.log_event("magnetometer rejected: disturbed field", 4)
        elif state == "confirming":
            self.log_event("magnetometer not confirmed yet: the start-up field set the heading, and "
                           "corrects it once it has stayed steady while turning", 6)
        elif previous == "confirming":
            self.log_event("magnetometer confirmed: the start-up field corrects the heading", 6)
        else:
            self.log_event("magnetometer accepted again", 6)

    # ------------------------------------------------------------------ the loop
    def run(self) -> int:
        """Runs until stopped, the duration ends, or a recorded source finishes. Returns 0."""
        # the log writer's thread must not hold the interpreter for Python's default 5 ms
        sys.setswitchinterval(0.0001)
        self._make_this_thread_realtime()
        _freeze_heap()
        end_ns = None if self.duration_s is None else time.monotonic_ns() + int(self.duration_s * 1e9)
        self._ready_sent = False
        self.health_report.was_reduced = self.pipeline.reduced
        calibration, reloads = self.calibration_session, self.reloads
        schedule = LoopSchedule(self._periodic_jobs(), time.monotonic_ns(), on_error=self._job_failed)
        while not self._stop:
            now = self.scheduler.wait()
            if self.source.skipped_ticks_lose_samples:
                self._count_skipped_ticks()
            self._estimate(self.source.read_block(MAX_SAMPLES_PER_TICK if self.source.may_have_backlog else 1))
            # one attribute test per tick while no fit runs; done() takes a lock only during one
            fit = calibration.fit
            if fit is not None and fit.done():
                calibration.apply()
            schedule.run_due(now)
            self.health_report.report_form_change(self.pipeline.reduced)
            self.scheduler.done()
            due = reloads.due_ns
            if due is not None and time.monotonic_ns() >= due:
                # cleared before the reload: a signal from here on is one more (a signal
                # between the test and this line is served by this reload, which reads later)
                reloads.due_ns = None
                self.reload()
                self.health_report.was_reduced = self.pipeline.reduced  # a new pipeline starts in full form
                schedule = LoopSchedule(self._periodic_jobs(), now, on_error=self._job_failed)  # new intervals, rates
                _freeze_heap()
            if end_ns is not None and now >= end_ns:
                break
            if getattr(self.source, "finished", False):
                break
        return 0

    def _make_this_thread_realtime(self) -> None:
        """``[service]``: real-time priority, CPU pinning and locked memory for the thread that
        runs the loop (``ahrs_service.realtime``), after every other thread has started; a
        setting the process may not apply is one warning, and the loop runs on without it."""
        settings = RealtimeSettings.from_config(self.cfg.service)
        if not settings.wanted:
            return
        outcome = apply_to_this_thread(settings)
        self._memory_locked = outcome.memory_locked
        for line in outcome.applied:
            self.log_event(line, 6)
        for line in outcome.refused:
            self.report(line, 4, kind="realtime")

    def _job_failed(self, job: PeriodicJob, exc: Exception) -> None:
        """A periodic job raised: one line (STATUSTEXT, journal, /log) at its 1st, 2nd, 4th,
        8th … failure, so that a job failing at every run cannot flood the links and logs."""
        n = job.failures
        if n & (n - 1) == 0:
            self.report(f"{job.name} failed ({n} time{'s' if n > 1 else ''} so far), the service goes on: "
                        f"{type(exc).__name__}: {exc}", 3, kind="job failure")

    def _count_skipped_ticks(self) -> None:
        """A source polled once per tick without FIFO (``skipped_ticks_lose_samples``): the
        ticks the scheduler skipped (an overrun, a host stall) are samples its part
        overwrote unread, counted in ``lost.host_stall`` so that the summary, /loop,
        SYS_STATUS and ``log info`` report them as lost samples, not only as overruns."""
        missed = self.scheduler.missed_ticks
        if missed > self._ticks_missed_counted:
            self.source.diagnostics.lost.host_stall += missed - self._ticks_missed_counted
        self._ticks_missed_counted = missed

    def _periodic_jobs(self) -> list[PeriodicJob]:
        """The loop's timers: what runs when, in this order within a tick (0 ns: off)."""
        diag_hz = self.cfg.log["diagnostics_hz"]
        return [
            PeriodicJob("publish", IO_PERIOD_NS, self._publish, keep_phase=True),
            PeriodicJob("log diagnostics", int(1e9 / diag_hz) if diag_hz else 0, self._diagnostics_due),
            PeriodicJob("watchdog", self.notifier.watchdog_interval_ns or 0, lambda now: self.notifier.watchdog()),
            PeriodicJob("housekeeping", HOUSEKEEPING_NS, self._housekeeping),
            PeriodicJob("ekf source set", SOURCE_SET_PERIOD_NS if self.source_switch is not None else 0,
                        self._source_set_tick),
        ]

    def _estimate(self, block: SampleBlock) -> EstimatedBlock | None:
        """One block from the source: live-calibration collection, pipeline, then the sinks."""
        if not len(block):
            return None
        if self.live_calibration.active:
            self.calibration_session.collect(block)  # raw sensor-axis samples, as the fit wants them
        done = self.pipeline.process_block(block)
        if done is not None:
            self.vibration.update(done.rows, done.flags)  # VIBRATION from the rows fed to the estimator
            for sink in self.sinks:
                sink.receive(done)
        return done

    def _publish(self, now: int) -> None:
        """MAVLink and the live view from the newest state, at their own rates; READY=1 once."""
        self.mavlink.tick(now)
        if self.live is not None:
            self.live.tick(now)
        if self.monitor is not None:
            self._monitor_tick(now)
        if self._autopilot_link is not None:
            self._timesync_tick()
        if not self._ready_sent and self.pipeline.samples > 0:
            self.notifier.ready(self.status_line())
            self._ready_sent = True

    def _diagnostics_due(self, now: int) -> None:
        if self.log_sink is not None:
            self.log_sink.diagnostics_due()

    def status_line(self, st: LoopStats | None = None) -> str:
        """One line of rate and health (systemd STATUS=, logs); ``st``: stats already taken."""
        return self.health_report.status_line(self.pipeline, self.source, st or self.scheduler.stats())

    def _loss_text(self, lost: LossCounts | None = None) -> str:
        """Lost IMU samples, total and by cause: "0" or "12 (fifo_overflow 12)"."""
        return self.health_report.loss_text(self.source, lost)

    def loop_counters(self) -> kernels.LoopCounters:
        sched = self.scheduler
        return kernels.LoopCounters(sched.ticks, sched.missed_ticks, sched.overruns, self.pipeline.samples)

    def _housekeeping(self, now: int) -> None:
        self.reloads.poll_compiler()  # a reload may wait for a child compile
        st = self.scheduler.stats()
        health = self.health_report
        health.last_load_percent = st.load_percent
        self.notifier.status(self.status_line(st))
        if self.live_calibration.state != "idle":  # collecting, or "<kind> cal: fitting"
            self.report(self.live_calibration.status_text(), 6)
        if self._autopilot_link is not None:  # identity and time sanity (docs/autopilot.md): once each
            for severity, text in self._autopilot_link.take_notices():
                self.report(text, severity, kind="autopilot link")
        diag = self.source.diagnostics.as_dict()
        health.report_faults(st, self.source, diag)
        self._record_loop(now, st, diag)
        if self.log_writer is not None:
            health.report_log_status(self.log_writer)

    def _record_loop(self, now: int, st: LoopStats, diag: dict[str, Any]) -> None:
        """The loop's, the source's and the estimator's counters on ``/loop`` (log and live
        view) and the links' on ``/mavlink``: once a second, and once more at :meth:`close`
        so that the log's last counters cover its last samples."""
        if self.live is None and self.log_writer is None:
            return
        loop = dict(st.as_dict(), estimator=self.estimator.diagnostics, source=diag, reduced=self.pipeline.reduced,
                    process_cpu_s=time.process_time())
        simulation_cpu_s = self.source.simulation_cpu_s
        if simulation_cpu_s is not None:  # the simulated hardware's share of process_cpu_s
            loop["simulation_cpu_s"] = simulation_cpu_s
        if self.log_writer is not None:
            loop["log"] = self.log_writer.stats()  # docs/logs.md: /loop `log`, what was not logged
        if self._autopilot_link is not None:  # the link, TIMESYNC's offset and drift (docs/autopilot.md)
            loop["autopilot"] = self._autopilot_link.status()
        odometry = None if self.mavlink is None else self.mavlink.odometry
        if odometry is not None:  # what went to the autopilot: sent, unsynced, resets, send errors
            loop["odometry"] = dataclasses.asdict(odometry.stats)
        if self.source_switch is not None:  # what was asked of ArduPilot's EKF source sets, and its answers
            loop["ekf_source_set"] = dataclasses.asdict(self.source_switch.stats)
        if self.live is not None:
            self.live.publish("/loop", now, loop)
        if self.log_writer is not None:
            self.log_writer.write_loop(now, loop)
            if self.mavlink is not None:
                self.log_writer.write_mavlink(now, self.mavlink.stats())

    def log_summary(self) -> str:
        """The flight log's part of the final summary (``ServiceHealth.log_summary``)."""
        return self.health_report.log_summary(self.log_writer)

    def record_calibration(self, kind: str) -> None:
        """Stores the calibration now in force: in the configuration file (when the service was
        started from one; a ``.bak`` keeps the previous file) and in the log."""
        self.calibration_session.record(kind)

    # ------------------------------------------------------------------ live changes
    def set_estimator_param(self, name: str, value: float, source: str = "mavlink") -> float:
        """Applies one estimator parameter live; logs it at the sample index where it takes effect."""
        old = self.estimator.get_params()[name]
        self.estimator.set_params(**{name: value})
        new = self.estimator.get_params()[name]
        self._record_change(name, old, new, source, f"parameter {name}")
        if self.live is not None and source != "foxglove":  # the live view tells its clients about its own sets
            self.live.params_changed()
        return new

    def record_write(self, name: str, old: Any, new: Any, source: str) -> None:
        """A ground station's accepted write other than an estimator parameter (declination,
        stream rates, message intervals, a calibration started): once on /params and /log."""
        self._record_change(name, old, new, source, name)

    def _record_change(self, name: str, old: Any, new: Any, source: str, what: str) -> None:
        """A live change on /params (flight log and live view) at the sample index where it
        takes effect, and one line on /log and the journal."""
        now = time.monotonic_ns()
        if self.log_writer is not None:
            self.log_writer.write_param_change(now, self.pipeline.samples, name, old, new, source)
        if self.live is not None:
            self.live.publish("/params", now, {"t_ns": now, "sample_index": self.pipeline.samples, "name": name,
                                               "old": old, "new": new, "source": source})
        self.log_event(f"{what}: {old} -> {new} ({source}, from sample {self.pipeline.samples})", 6)

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        """Stops everything after :meth:`run` has returned. A live-calibration fit still
        running gets at most ``LIVE_FIT_CLOSE_WAIT_S`` to finish (``LiveCalibration.settle``)."""
        self.notifier.stopping()
        self._fall_back_at_stop()  # first: the autopilot flies on a stale heading until it switches
        self.compiler.close()
        try:
            self.calibration_session.settle(LIVE_FIT_CLOSE_WAIT_S)
        except Exception as exc:  # applying it must not keep the parts below open
            log.warning("live calibration at shutdown: %s", exc)
        if self.log_writer is not None and self.source is not None:
            try:  # the last second's losses and counters, after the last housekeeping's record
                if self.source.skipped_ticks_lose_samples:
                    self._count_skipped_ticks()
                self._record_loop(time.monotonic_ns(), self.scheduler.stats(), self.source.diagnostics.as_dict())
            except Exception as exc:  # the log is closed below all the same
                log.warning("final /loop record: %s", exc)
        for part in (self.live, self.mavlink, self.log_writer, self.source):
            if part is None:
                continue
            try:
                part.close()
            except Exception as exc:  # a failing part must not keep the others open
                log.warning("closing %s: %s", type(part).__name__, exc)
        self.notifier.close()
        if self._memory_locked:
            undo_memory_lock()
            self._memory_locked = False
        self._restore_signal_handlers()
