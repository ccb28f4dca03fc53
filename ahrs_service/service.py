"""The AHRS service: source → estimator at a fixed rate → MAVLink out, MCAP log, systemd.

One thread runs everything, in this order each tick: read a block of samples from the source
(a FIFO burst, or the one sample a polling source has), run the estimator over it
(:meth:`~ahrs_service.pipeline.EstimationPipeline.process_block`), hand the block to the log
writer's queue in one call (the writer encodes on its own thread), then run the periodic
jobs that are due (:class:`LoopSchedule`: MAVLink and the live view publish from the newest
state at their own rates, diagnostics, the systemd watchdog, housekeeping). Parameter changes
and commands are therefore applied between two blocks, at a sample index the log records, so
a replay reproduces every published attitude.

The one computation too long for a tick, the fit at the end of a live calibration (tens of
milliseconds), runs on a daemon thread ("live-calibration",
:meth:`~ahrs_service.calibration.live.LiveCalibrator.finish_async`); the loop keeps
estimating with the old calibration and, once the fit is done, swaps the calibration, reports
and records it itself — between two samples like any other change.
"""

from __future__ import annotations

import gc
import logging
import signal
import sys
import time
from concurrent.futures import Future, wait
from dataclasses import dataclass
from typing import Any, Callable

from ahrs_service import config as config_mod
from ahrs_service import estimators, kernels
from ahrs_service.estimators import STATE_HEADER
from ahrs_service.drivers.base import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID, ImuSource, LossCounts, SampleBlock
from ahrs_service.drivers.calibration import SensorCalibration
# imported with the service, not when the log opens: its ~40 ms of modules (mcap, the
# schemas) fell between the source's start and its first read
from ahrs_service.logs.writer import FlightLogWriter
from ahrs_service.calibration.live import LiveCalibrationResult, LiveCalibrator
from ahrs_service.calibration.storage import calibration_from_config_dict, calibration_section, save_calibration
from ahrs_service.mavlink_bridge import LatestAttitude, LatestEstimate, LinkHealth, ServiceLink
from ahrs_service.pipeline import EstimatedBlock, EstimationPipeline
from ahrs_service.protocols.mavlink.endpoints import check_can_open
from ahrs_service.scheduler import DataReadyScheduler, FixedRateScheduler, LoopStats
from ahrs_service.sources import make_source
from ahrs_service.vibration import VibrationMonitor
from ahrs_service.systemd import Notifier

_H = STATE_HEADER.slices  # the state header every estimator shares

log = logging.getLogger("ahrs_service")

IO_PERIOD_NS = 5_000_000  # MAVLink publish/poll granularity: 200 Hz
HOUSEKEEPING_NS = 1_000_000_000  # loop statistics, STATUS=, health reports
MAX_SAMPLES_PER_TICK = 64  # a source with a backlog catches up at most this fast (one block)
# how long close() waits for a running live-calibration fit, s: fits take tens of ms, and
# the whole stop must stay well within 2 s (systemd's TimeoutStopSec is 5 s)
LIVE_FIT_CLOSE_WAIT_S = 0.5
#: a SIGHUP's reload waits until no other SIGHUP has come for this long, so that a burst (a
#: script or configuration tool signalling at every file it writes, `systemctl reload`
#: repeated) is one reload of the file as last written, not one full reload per signal; a
#: signal during a reload makes one more. RELOAD_MAX_WAIT_NS bounds the wait after the first
#: signal of a burst that never pauses.
RELOAD_SETTLE_NS = 200_000_000
RELOAD_MAX_WAIT_NS = 2_000_000_000


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
        # a reload is pending when _reload_due_ns is set: the loop runs it from that time
        # (request_reload); _reload_first_ns: the first signal of the pending burst
        self._reload_due_ns: int | None = None
        self._reload_first_ns = 0
        self.source: ImuSource | None = None
        self.mavlink = None
        self.log_writer = None
        self.live = None  # the Foxglove live view (live_view.LiveView) when [live] enabled
        self.monitor = None  # the autopilot attitude monitor (attitude_monitor.py) beside an autopilot
        self.live_calibration = LiveCalibrator(max_rate_hz=cfg.rates["estimation_hz"])
        self.vibration = VibrationMonitor()  # VIBRATION's levels and clipping, from every sample row
        self._earlier_log_writers: list[Any] = []  # closed by reloads; for the final summary
        # the running fit of a live calibration (see apply_live_calibration) and its kind
        self._live_fit: Future[LiveCalibrationResult] | None = None
        self._live_fit_kind = ""
        self.compiler = kernels.ReloadCompiler()  # a reload to an estimator not yet compiled
        # beside an autopilot (source.type = "mavlink"): the source's link, which carries
        # ODOMETRY (_open_mavlink), the monitor's attitudes and TIMESYNC; set once the source
        # is open (a reload keeps the source)
        self._autopilot_link: Any = None
        self._timesync_logged_ns: int | None = None  # the TIMESYNC estimate last on /timesync
        #: the handlers install_signal_handlers replaced, put back by close()
        self._replaced_handlers: dict[signal.Signals, Any] = {}

    # ------------------------------------------------------------------ set-up
    def start(self) -> None:
        cfg = self.cfg
        self._build_estimation(cfg)
        if self.notifier.enabled:
            # under systemd a first start compiles for up to minutes: a child does it while
            # this process keeps extending systemd's start timeout (EXTEND_TIMEOUT_USEC)
            child = kernels.compile_in_child([self.estimator.name], self.notifier, stop=lambda: self._stop)
            if self._stop:
                raise RuntimeError("stopped while the estimator kernels compiled")
            if not child.ok:
                log.warning("compiling in a child process failed (%s); compiling here", child.error)
        t0 = time.monotonic()
        self._warm_up()
        if time.monotonic() - t0 > 1.0:
            log.info("compiled the %s kernels in %.0f s (first start only)", self.estimator.name, time.monotonic() - t0)
        # the heap so far (modules, compiled kernels) frozen before the part starts filling its
        # FIFO: run()'s own freeze then walks only what the start adds after this (tens of ms
        # less between the source's start and its first read)
        _freeze_heap()
        self.source = make_source(cfg.source, cfg.rates["estimation_hz"], cfg.mavlink["system_id"])
        self.source.open()
        self._autopilot_link = getattr(self.source, "autopilot_link", None)
        if not self.source.has_mag:
            # a part without magnetometer (ICM-42688-P, BMI088): no start waiting for a field
            self.pipeline.use_mag = False
        self._clock_recovery()
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
        self._use_source_calibration()
        self._open_log(cfg)
        self._open_mavlink(cfg)
        self._open_live(cfg)
        self._open_monitor(cfg)

    def _timesync_tick(self) -> None:
        """Beside an autopilot: the link's TIMESYNC estimate, logged on /timesync once per new
        estimate (ODOMETRY's link and clock: _open_mavlink)."""
        link = self._autopilot_link
        with link.timesync_lock:
            status = link.timesync.last_status
        if status is not None and status.local_ns != self._timesync_logged_ns and self.log_writer is not None:
            self._timesync_logged_ns = status.local_ns
            self.log_writer.write_timesync(status)

    def _open_monitor(self, cfg: config_mod.Config) -> None:
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

    def _warm_up(self) -> None:
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

    def _clock_recovery(self) -> None:
        """Sample times from stamps that are host arrival times: recovered onto the sensor's
        clock (``sample_clock.SampleClock`` at the estimation rate) for a source that hands
        out every sample it receives (``may_have_backlog``: a recording, a CAN node). Not for
        a FIFO board or a flight log (``times_on_sensor_clock``: timed already), nor for a
        polling board that reads only the newest sample: a late loop skips samples there
        without a counter to tell, and the clock line then bends instead of counting a gap
        (measured on the simulated GY-80 at 200 Hz on this loaded host: recovered times up to
        29 ms before the read times), so its read times are kept (docs/timing.md)."""
        source = self.source
        if not source.times_on_sensor_clock and source.may_have_backlog:
            self.pipeline.use_sample_clock(self.cfg.rates["estimation_hz"])

    def _open_live(self, cfg: config_mod.Config) -> None:
        if cfg.live["enabled"]:
            from ahrs_service.live_view import open_live_view

            self.live = open_live_view(self, cfg.live)

    def _build_estimation(self, cfg: config_mod.Config) -> None:
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
            return cfg.estimator["declination_deg"]
        from ahrs_service.calibration.declination import declination_deg

        value = declination_deg(loc["latitude_deg"], loc["longitude_deg"], loc["altitude_km"])
        log.info("magnetic declination %.2f° from the World Magnetic Model", value)
        return value

    def _use_source_calibration(self) -> None:
        """A recorded log hands out samples already calibrated into the body frame."""
        if getattr(self.source, "calibrated", False):
            if self.cfg.calibration:
                log.info("recorded source is already calibrated: the configured calibration is not applied")
            self.pipeline.calibration = SensorCalibration()

    @property
    def estimator(self):
        return self.pipeline.estimator

    def _open_log(self, cfg: config_mod.Config) -> None:
        if not cfg.log["enabled"]:
            self.log_writer = None
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

    def effective_config(self) -> dict[str, Any]:
        """The configuration in force, with the estimator's full parameter set."""
        raw = {k: dict(v) for k, v in self.cfg.raw.items()}
        raw["estimator"] = dict(raw["estimator"], params=self.estimator.get_params())
        return raw

    def _open_mavlink(self, cfg: config_mod.Config) -> None:
        from ahrs_service.mavlink_bridge import MavlinkBridge

        self.mavlink = MavlinkBridge(self.bridge_link(), cfg, io_period_ns=IO_PERIOD_NS)

    def bridge_link(self) -> ServiceLink:
        """What the MAVLink bridge may use of this service (mavlink_bridge.ServiceLink)."""
        est = self.estimator
        link = self._autopilot_link
        return ServiceLink(
            boot_ns=self.boot_ns,
            estimator=est.name,
            param_names=est.param_names(),
            latest=self.latest_estimate,
            health=self.link_health,
            get_param=lambda name: self.estimator.get_params()[name],
            set_param=self.set_estimator_param,
            get_declination=lambda: self.pipeline.declination_deg,
            set_declination=lambda deg: self.pipeline.set_declination(deg),
            loop_rate_hz=lambda: float(self.cfg.rates["estimation_hz"]),
            calibrate_gyro=self.calibrate_gyro,
            start_calibration=self.start_live_calibration,
            vibration=self.vibration.levels,
            attitude_variance=lambda: self.estimator.attitude_variance(),
            # beside an autopilot ODOMETRY goes on its link, stamped in its clock (docs/autopilot.md)
            odometry_send=None if link is None else link.send,
            odometry_clock=None if link is None else link.clock,
            latest_attitude=self.latest_attitude,
        )

    def latest_estimate(self) -> LatestEstimate | None:
        """The newest estimated sample for the publishers; None before the first."""
        pipeline = self.pipeline
        sample = pipeline.last_sample
        if sample is None:
            return None
        return LatestEstimate(
            samples=pipeline.samples,
            t_ns=sample.t_ns,
            q=pipeline.published_quaternion(),
            body_rate=pipeline.body_rates(),
            gyr=sample.gyr,
            acc=sample.acc,
            mag=sample.mag,
            mag_new=bool(sample.flags & MAG_NEW),
            temperature_c=sample.temperature_c,
            initialised=bool(self.estimator.state[STATE_HEADER.index.initialised]),
            mag_used=pipeline.use_mag and not pipeline.reduced,
            reduced=pipeline.reduced or not pipeline.use_mag,
            estimator_id=id(self.estimator),
            declination_deg=pipeline.declination_deg,
        )

    def latest_attitude(self) -> LatestAttitude | None:
        """The newest estimate's attitude alone (what ATTITUDE / ATTITUDE_QUATERNION carry);
        None before the first sample."""
        pipeline = self.pipeline
        if pipeline.last_sample is None:
            return None
        return LatestAttitude(pipeline.samples, pipeline.published_quaternion(), pipeline.body_rates())

    def link_health(self) -> LinkHealth:
        """Health bits and fault counters for SYS_STATUS."""
        h = self.health()
        diag = self.source.diagnostics
        return LinkHealth(
            gyro_healthy=h["gyro_healthy"], accel_healthy=h["accel_healthy"],
            mag_present=h["mag_present"], mag_healthy=h["mag_healthy"],
            overruns=self.scheduler.overruns, load_percent=self.last_load_percent,
            comm_errors=diag.bus_errors, sensor_faults=diag.saturated + diag.non_finite,
            lost_samples=diag.lost.total,
        )

    def calibrate_gyro(self) -> tuple[bool, str]:
        """The gyro-bias calibration command: accepted only at rest; stored when accepted."""
        check = self.pipeline.calibrate_gyro_bias()
        if not check.at_rest:
            return False, f"gyro calibration refused: {check.reason}"
        self.record_calibration("gyro")
        return True, "gyro bias set to [{:.4f}, {:.4f}, {:.4f}] rad/s".format(*self.pipeline.calibration.gyro_bias)

    # ------------------------------------------------------------------ control
    def request_stop(self, *_: Any) -> None:
        self._stop = True

    def request_reload(self, *_: Any) -> None:
        """SIGHUP: a reload, run by the loop once signals have paused for ``RELOAD_SETTLE_NS``
        (at most ``RELOAD_MAX_WAIT_NS`` after the first): a burst of signals is one reload,
        which reads the file as it is then (the last content wins). A signal during a running
        reload (handled between two bytecodes of it) leaves one more pending."""
        now = time.monotonic_ns()
        if self._reload_due_ns is None:
            self._reload_first_ns = now
        self._reload_due_ns = min(now + RELOAD_SETTLE_NS, self._reload_first_ns + RELOAD_MAX_WAIT_NS)

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
        if self.mavlink is not None:
            self.mavlink.statustext(severity, text, kind)
        self.log_event(text, severity)

    def log_event(self, text: str, severity: int = 6) -> None:
        """A health event for the journal and /log (flight log and live view), not STATUSTEXT:
        rejections and parameter changes, too frequent or too minor for the ground station.
        ``severity``: MAVLink's, 0 emergency … 7 debug."""
        log.log(logging.WARNING if severity <= 4 else logging.INFO, text)
        now = time.monotonic_ns()
        if self.log_writer is not None:
            self.log_writer.write_log(now, severity, text)
        if self.live is not None:
            self.live.log_event(now, severity, text)

    def diagnostics(self) -> dict[str, Any]:
        """The estimator's diagnostics (rest, rejections, bias trust …) and the form it runs in."""
        return dict(self.estimator.diagnostics, reduced=self.pipeline.reduced)

    def _diagnostics_for_log(self) -> dict[str, Any]:
        """:meth:`diagnostics` at the configured rate; reports a magnetometer rejection starting or ending."""
        diag = self.diagnostics()
        rejected = bool(diag.get("mag_disturbed", False))
        if rejected != self._mag_rejected:
            self._mag_rejected = rejected
            self.log_event("magnetometer rejected: disturbed field" if rejected else "magnetometer accepted again",
                           4 if rejected else 6)
        return diag

    # ------------------------------------------------------------------ the loop
    def run(self) -> int:
        """Runs until stopped, the duration ends, or a recorded source finishes. Returns 0."""
        # the log writer's thread must not hold the interpreter for Python's default 5 ms
        sys.setswitchinterval(0.0001)
        _freeze_heap()
        end_ns = None if self.duration_s is None else time.monotonic_ns() + int(self.duration_s * 1e9)
        self._diag_due = False  # the next logged block carries the estimator's diagnostics
        self._ready_sent = False
        self._was_reduced = self.pipeline.reduced
        schedule = LoopSchedule(self._periodic_jobs(), time.monotonic_ns(), on_error=self._job_failed)
        while not self._stop:
            now = self.scheduler.wait()
            if self.source.skipped_ticks_lose_samples:
                self._count_skipped_ticks()
            self._estimate(self.source.read_block(MAX_SAMPLES_PER_TICK if self.source.may_have_backlog else 1))
            # one attribute test per tick while no fit runs; done() takes a lock only during one
            if self._live_fit is not None and self._live_fit.done():
                self.apply_live_calibration()
            schedule.run_due(now)
            self._report_form_change()
            self.scheduler.done()
            due = self._reload_due_ns
            if due is not None and time.monotonic_ns() >= due:
                # cleared before the reload: a signal from here on is one more (a signal
                # between the test and this line is served by this reload, which reads later)
                self._reload_due_ns = None
                self.reload()
                self._was_reduced = self.pipeline.reduced  # a new pipeline starts in full form
                schedule = LoopSchedule(self._periodic_jobs(), now, on_error=self._job_failed)  # new intervals, rates
                _freeze_heap()
            if end_ns is not None and now >= end_ns:
                break
            if getattr(self.source, "finished", False):
                break
        return 0

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
        ]

    def _estimate(self, block: SampleBlock) -> EstimatedBlock | None:
        """One block from the source: live-calibration collection, estimator, log."""
        if not len(block):
            return None
        if self.live_calibration.active:
            for sample in block.samples():  # raw sensor-axis samples, as the fit wants them
                if self.live_calibration.add(sample):
                    self.start_live_fit()
                    break
        done = self.pipeline.process_block(block)
        if done is not None:
            self.vibration.update(done.rows, done.flags)  # VIBRATION from the rows fed to the estimator
            if self.monitor is not None:
                self.monitor.add_estimates(done.t_ns, done.q)
        writer = self.log_writer
        if done is not None and writer is not None:
            pipeline = self.pipeline
            writer.write_block(
                done.t_ns, done.rows, done.flags, q=done.q, estimator=pipeline.estimator.name,
                t_source_ns=done.t_source_ns if pipeline.clock is not None else None,
                bias=done.state[_H.bias], state=done.state, raw=done.raw, temperature=done.temperature_c,
                truth_q=done.truth_q if self.cfg.log["truth"] else None,
                diagnostics=self._diagnostics_for_log() if self._diag_due else None,
            )
            self._diag_due = False
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
        self._diag_due = True

    def _report_form_change(self) -> None:
        reduced = self.pipeline.reduced
        if reduced != self._was_reduced:
            self._was_reduced = reduced
            self.report("magnetometer lost: estimating in reduced form" if reduced else "magnetometer back: full form",
                        4 if reduced else 6)

    def status_line(self, st: LoopStats | None = None) -> str:
        """One line of rate and health (systemd STATUS=, logs); ``st``: stats already taken."""
        st = st or self.scheduler.stats()
        mode = "reduced" if self.pipeline.reduced else "full"
        # a FIFO board's rows come at its sensor's rate, the loop wakes at its drain rate
        sensor_hz = self.source.diagnostics.extra.get("sensor_rate_hz") if self.source is not None else None
        rows = f"rows at {sensor_hz:.0f} Hz, " if isinstance(sensor_hz, (int, float)) else ""
        return (
            f"{self.estimator.name} ({mode}) {rows}loop at {st.rate_hz:.0f} Hz, load {st.load_percent:.1f}%, "
            f"jitter p99 {st.period_jitter_p99_us:.0f} us, overruns {st.overruns}, samples {self.pipeline.samples}, "
            f"lost {self._loss_text()}"
        )

    def _loss_text(self, lost: LossCounts | None = None) -> str:
        """Lost IMU samples, total and by cause: "0" or "12 (fifo_overflow 12)"."""
        if lost is None:
            lost = self.source.diagnostics.lost if self.source is not None else LossCounts()
        return lost.summary()

    def _loop_counters(self) -> kernels.LoopCounters:
        sched = self.scheduler
        return kernels.LoopCounters(sched.ticks, sched.missed_ticks, sched.overruns, self.pipeline.samples)

    def _housekeeping(self, now: int) -> None:
        if self.compiler.child is not None:  # a reload waits for a child compile
            self.notifier.extend_timeout(kernels.EXTEND_TIMEOUT_S)
            done = self.compiler.poll(self._loop_counters())
            if done is not None and done.ok:
                self._reload_due_ns = 0  # the loop calls reload() at the end of this tick
            elif done is not None:
                self.report(f"reload refused: compiling {done.name} failed: {done.error}", 3)
                self.notifier.ready(self.status_line())
        st = self.scheduler.stats()
        self.last_load_percent = st.load_percent
        self.notifier.status(self.status_line(st))
        if self.live_calibration.state != "idle":  # collecting, or "<kind> cal: fitting"
            self.report(self.live_calibration.status_text(), 6)
        diag = self.source.diagnostics.as_dict()
        if self._last_overruns is not None and st.overruns > self._last_overruns:
            self.report(f"loop overruns: {st.overruns - self._last_overruns} in the last second", 4)
        self._last_overruns = st.overruns
        lost_now = self.source.diagnostics.lost
        if lost_now.total > self._last_loss.total:
            self.report(f"IMU samples lost: {self._loss_text(lost_now.since(self._last_loss))} in the last second", 4)
            self._last_loss = lost_now.copy()
        lost = bool(diag.get("device_lost"))
        if lost != self._last_lost:
            self._last_lost = lost
            self.report(f"sensor lost: {diag.get('last_error', '')}" if lost else "sensor back", 3 if lost else 6)
        self._record_loop(now, st, diag)
        if self.log_writer is not None:
            self._report_log_status(self.log_writer)

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
        if self.live is not None:
            self.live.publish("/loop", now, loop)
        if self.log_writer is not None:
            self.log_writer.write_loop(now, loop)
            if self.mavlink is not None:
                self.log_writer.write_mavlink(now, self.mavlink.stats())

    def _report_log_status(self, writer: Any) -> None:
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

    def log_summary(self) -> str:
        """The flight log's part of the final summary: files, and what is not in them (over
        every writer of the run: a reload that changed [log] closed the earlier ones)."""
        writers = [*self._earlier_log_writers, *([self.log_writer] if self.log_writer is not None else [])]
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

    _last_overruns: int | None = None
    _last_loss = LossCounts()
    _mag_rejected = False
    _last_lost = False
    _last_log_status = "ok"
    last_load_percent = 0.0

    def record_calibration(self, kind: str) -> None:
        """Stores the calibration now in force: in the configuration file (when the service was
        started from one; a ``.bak`` keeps the previous file) and in the log."""
        cal = self.pipeline.calibration
        self.cfg.raw["calibration"] = calibration_section(cal, self.cfg.raw["calibration"])
        if self.cfg.path is not None:
            try:
                save_calibration(self.cfg.path, cal)
            except (OSError, ValueError) as exc:
                self.report(f"{kind} calibration not saved: {exc}", 4)
        if self.log_writer is not None:
            self.log_writer.write_config(time.monotonic_ns(), self.effective_config(), reason=f"calibration:{kind}")

    def start_live_calibration(self, kind: str) -> tuple[bool, str]:
        """Starts collecting samples for a magnetometer or accelerometer calibration.

        Returns (started, text for the operator); refused while a collection runs or the
        previous one is still being fitted."""
        try:
            return True, self.live_calibration.start(kind)
        except RuntimeError as exc:  # one is already running, or its fit
            return False, str(exc)

    def start_live_fit(self) -> None:
        """The collection is done: hands its data to the fit thread (loop thread, O(1)). The
        loop goes on with the calibration in force; :meth:`apply_live_calibration` swaps it
        when the fit is done."""
        kind = self.live_calibration.kind or ""
        try:
            self._live_fit = self.live_calibration.finish_async(self.pipeline.calibration)
            self._live_fit_kind = kind
        except RuntimeError as exc:  # no thread could be started: the collection is lost
            self.report(f"{kind} cal failed: {exc}", 4)

    def apply_live_calibration(self) -> None:
        """Applies the finished fit of a live calibration — on the loop thread, between two
        samples, so the log records the change at a known sample index: STATUSTEXT of the
        outcome, and when accepted the new calibration in the pipeline, the configuration
        file and the log (:meth:`record_calibration`). A fit that raised is reported
        (STATUSTEXT warning, log with traceback) and changes nothing."""
        future = self._live_fit
        if future is None or not future.done():
            return  # nothing to apply yet: a running fit is kept
        self._live_fit = None
        exc = future.exception(timeout=0)  # any exception, even a BaseException, stays here
        if exc is not None:
            log.error("live %s calibration: the fit raised", self._live_fit_kind, exc_info=exc)
            self.report(f"{self._live_fit_kind} cal failed: {type(exc).__name__}: {exc}", 4)
            return
        result = future.result(timeout=0)
        if result.accepted:
            # onto the calibration in force now: a gyro calibration or a reload during the
            # fit may have changed it, and only the calibrated sensor's terms are the fit's
            self.pipeline.calibration = result.apply_to(self.pipeline.calibration)
        # after the swap: a ground station that reads "done" finds the new calibration in use
        self.report(result.text, 6 if result.accepted else 4)
        if result.accepted:
            self.record_calibration(result.kind)

    def _settle_live_fit(self, timeout_s: float) -> None:
        """At shutdown, after the loop has ended: waits at most ``timeout_s`` s for a running
        fit and applies it (reported, saved, logged after the last sample); a fit still
        running then is abandoned — nothing is applied or saved, and its daemon thread ends
        with the process."""
        future = self._live_fit
        if future is None:
            return
        wait([future], timeout=timeout_s)
        if future.done():
            self.apply_live_calibration()
        else:
            self._live_fit = None
            log.warning("live %s calibration: the fit was still running at shutdown; abandoned, "
                        "calibration not changed", self._live_fit_kind)

    def health(self) -> dict[str, bool]:
        """Present/healthy bits for gyro, accelerometer and magnetometer (SYS_STATUS)."""
        s = self.pipeline.last_sample
        flags = s.flags if s is not None else 0
        lost = bool(self.source.diagnostics.device_lost) if self.source else True
        # a board names the parts it lost: a lost magnetometer is a magnetometer fault (reduced
        # mode), not an IMU fault; other sources only say "lost"
        parts = getattr(self.source, "lost", None)
        imu_lost = lost if not isinstance(parts, (set, frozenset)) else bool(parts & {"gyro", "acc"})
        mag_lost = isinstance(parts, (set, frozenset)) and "mag" in parts
        return {
            "gyro_healthy": bool(flags & GYR_VALID) and not imu_lost,
            "accel_healthy": bool(flags & ACC_VALID) and not imu_lost,
            "mag_present": bool(getattr(self.source, "has_mag", False)),
            "mag_healthy": bool(flags & MAG_VALID or s is not None and s.mag is None)
                           and not self.pipeline.reduced and not mag_lost,
        }

    # ------------------------------------------------------------------ live changes
    def set_estimator_param(self, name: str, value: float, source: str = "mavlink") -> float:
        """Applies one estimator parameter live; logs it at the sample index where it takes effect."""
        old = self.estimator.get_params()[name]
        self.estimator.set_params(**{name: value})
        new = self.estimator.get_params()[name]
        now = time.monotonic_ns()
        if self.log_writer is not None:
            self.log_writer.write_param_change(now, self.pipeline.samples, name, old, new, source)
        if self.live is not None:
            self.live.publish("/params", now, {"t_ns": now, "sample_index": self.pipeline.samples, "name": name,
                                               "old": old, "new": new, "source": source})
            if source != "foxglove":  # the live view tells its clients about its own sets
                self.live.params_changed()
        self.log_event(f"parameter {name}: {old} -> {new} ({source}, from sample {self.pipeline.samples})", 6)
        return new

    def reload(self) -> None:
        """SIGHUP: re-reads the configuration file and applies it; a bad file changes nothing."""
        self.notifier.reloading()
        try:
            new = config_mod.load(self.cfg.path, self.cfg.overrides)
        except Exception as exc:  # ConfigError, or anything unforeseen: the running config stays
            self.report(f"reload refused: {exc}", 3)
            self.notifier.ready(self.status_line())
            return
        if new.source != self.cfg.source:
            self.report("reload: source changes need a restart; source kept", 4)
            new.raw["source"] = self.cfg.source
        added = [url for url in new.mavlink["endpoints"] if url not in self.cfg.mavlink["endpoints"]]
        try:  # before anything is applied: an endpoint that cannot be opened refuses the reload
            check_can_open(added, new.mavlink["system_id"], 0)
        except OSError as exc:
            self.report(f"reload refused: mavlink.endpoints: {exc}", 3)
            self.notifier.ready(self.status_line())
            return
        name = new.estimator["name"]
        if self.compiler.needed(name, self.estimator.name, self._loop_counters()):
            # numba holds the interpreter lock while compiling: a child compiles, the loop runs
            # on with the old estimator, and _housekeeping repeats this reload when it is done
            self.report(f"reload: compiling {name} in a child process; {self.estimator.name} runs meanwhile", 6)
            return
        old_cfg, self.cfg = self.cfg, new
        same_filter = new.estimator["name"] == old_cfg.estimator["name"]
        if same_filter and new.calibration == old_cfg.calibration and new.mounting == old_cfg.mounting:
            # new gains for the running filter: applied like live changes, recorded per parameter
            wanted = estimators.create(new.estimator["name"], **new.estimator["params"]).get_params()
            for name, value in wanted.items():
                if value != self.estimator.get_params()[name]:
                    self.set_estimator_param(name, value, source="reload")
            self.pipeline.set_declination(self.declination_deg(new))
            self.pipeline.mag_timeout_ns = int(new.estimator["mag_timeout_s"] * 1e9)
        else:
            self._build_estimation(new)
            t0 = time.monotonic_ns()
            self._warm_up()
            compiled = self.compiler.last
            if compiled is not None and compiled.name == name and compiled.load_ms is None:
                compiled.load_ms = (time.monotonic_ns() - t0) / 1e6
                self.report(compiled.text(), 6)
            self._use_source_calibration()
            self._clock_recovery()
            if self.log_writer is not None and new.log == old_cfg.log:
                self.log_writer.new_file()  # a fresh estimator: its own file replays exactly
        # a FIFO source's loop runs at its drain (watermark) rate, not estimation_hz
        if self.loop_rate_hz(new) != self.scheduler.rate_hz and not isinstance(self.scheduler, DataReadyScheduler):
            self.scheduler.set_rate(self.loop_rate_hz(new))
        if new.log != old_cfg.log:
            if self.log_writer is not None:
                self.log_writer.close()
                self._earlier_log_writers.append(self.log_writer)  # its counts stay in the summary
            self._open_log(new)
        elif self.log_writer is not None:
            self.log_writer.write_config(time.monotonic_ns(), self.effective_config())
        if not same_filter or new.mavlink != old_cfg.mavlink or new.rates != old_cfg.rates:
            # another filter has other EST_* parameters: the table is rebuilt with the component
            self.mavlink.close()
            try:
                self._open_mavlink(new)
            except OSError as exc:  # taken since the check above: the running endpoints again
                new.raw["mavlink"] = old_cfg.mavlink
                self._open_mavlink(new)
                self.report(f"reload: mavlink.endpoints: {exc}; the running endpoints kept", 3)
        if new.monitor != old_cfg.monitor:
            self._open_monitor(new)
        if new.live != old_cfg.live:  # a new address, rate, or switched on or off
            if self.live is not None:
                self.live.close()
                self.live = None
            self._open_live(new)
        elif self.live is not None:
            self.live.params_changed()
        self.report("configuration reloaded", 6)
        self.notifier.ready(self.status_line())

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        """Stops everything after :meth:`run` has returned. A live-calibration fit still
        running gets at most ``LIVE_FIT_CLOSE_WAIT_S`` to finish (see :meth:`_settle_live_fit`)."""
        self.notifier.stopping()
        self.compiler.close()
        try:
            self._settle_live_fit(LIVE_FIT_CLOSE_WAIT_S)
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
        self._restore_signal_handlers()
