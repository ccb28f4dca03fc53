"""SIGHUP: re-reading the configuration file and applying it to the running service.

A burst of signals is one reload (:meth:`ConfigReload.request` waits until they pause), run by
the loop between two blocks. A bad file changes nothing. New gains for the running filter are
applied like live parameter changes; another filter, calibration or mounting builds a new
pipeline (a new log file, so that it replays exactly); the flight log, MAVLink, the attitude
monitor and the live view are reopened only when their own settings changed.
"""

from __future__ import annotations

import time
from typing import Any, Protocol

from ahrs_service import config as config_mod
from ahrs_service import estimators, kernels
from ahrs_service.health import ServiceHealth
from ahrs_service.pipeline import EstimationPipeline
from ahrs_service.protocols.mavlink.endpoints import check_can_open
from ahrs_service.scheduler import DataReadyScheduler
from ahrs_service.systemd import Notifier

#: a SIGHUP's reload waits until no other SIGHUP has come for this long, so that a burst (a
#: script or configuration tool signalling at every file it writes, `systemctl reload`
#: repeated) is one reload of the file as last written, not one full reload per signal; a
#: signal during a reload makes one more. RELOAD_MAX_WAIT_NS bounds the wait after the first
#: signal of a burst that never pauses.
RELOAD_SETTLE_NS = 200_000_000
RELOAD_MAX_WAIT_NS = 2_000_000_000


class ReloadHost(Protocol):
    """The parts of the running service a reload replaces or reconfigures."""

    cfg: config_mod.Config
    notifier: Notifier
    compiler: kernels.ReloadCompiler
    pipeline: EstimationPipeline
    scheduler: Any
    log_writer: Any
    mavlink: Any
    live: Any
    health_report: ServiceHealth

    @property
    def estimator(self) -> Any: ...

    def report(self, text: str, severity: int = 6, kind: str | None = None) -> None: ...
    def status_line(self) -> str: ...
    def loop_counters(self) -> kernels.LoopCounters: ...
    def loop_rate_hz(self, cfg: config_mod.Config) -> float: ...
    def declination_deg(self, cfg: config_mod.Config) -> float: ...
    def set_estimator_param(self, name: str, value: float, source: str = "mavlink") -> float: ...
    def effective_config(self) -> dict[str, Any]: ...
    def build_estimation(self, cfg: config_mod.Config) -> None: ...
    def warm_up(self) -> None: ...
    def use_source_calibration(self) -> None: ...
    def use_clock_recovery(self) -> None: ...
    def open_log(self, cfg: config_mod.Config) -> None: ...
    def open_mavlink(self, cfg: config_mod.Config) -> None: ...
    def open_monitor(self, cfg: config_mod.Config) -> None: ...
    def open_divergence(self, cfg: config_mod.Config) -> None: ...
    def open_live(self, cfg: config_mod.Config) -> None: ...
    def connect_sinks(self) -> None: ...


class ConfigReload:
    """When the next reload is due, and the reload itself."""

    def __init__(self, host: ReloadHost) -> None:
        self.host = host
        #: a reload is pending when set: the loop runs it from that time (monotonic ns)
        self.due_ns: int | None = None
        self._first_ns = 0  # the first signal of the pending burst

    def request(self, now_ns: int) -> None:
        """A SIGHUP: a reload once signals have paused for ``RELOAD_SETTLE_NS`` (at most
        ``RELOAD_MAX_WAIT_NS`` after the first): a burst of signals is one reload, which reads
        the file as it is then (the last content wins). A signal during a running reload
        (handled between two bytecodes of it) leaves one more pending."""
        if self.due_ns is None:
            self._first_ns = now_ns
        self.due_ns = min(now_ns + RELOAD_SETTLE_NS, self._first_ns + RELOAD_MAX_WAIT_NS)

    def poll_compiler(self) -> None:
        """Housekeeping while a child compiles for a pending reload: keeps systemd's start
        timeout extended; once the child is done, the reload runs at the end of this tick."""
        host = self.host
        if host.compiler.child is None:
            return
        host.notifier.extend_timeout(kernels.EXTEND_TIMEOUT_S)
        done = host.compiler.poll(host.loop_counters())
        if done is not None and done.ok:
            self.due_ns = 0
        elif done is not None:
            host.report(f"reload refused: compiling {done.name} failed: {done.error}", 3)
            host.notifier.ready(host.status_line())

    def run(self) -> None:
        """Re-reads the configuration file and applies it; a bad file changes nothing."""
        svc = self.host
        svc.notifier.reloading()
        try:
            new = config_mod.load(svc.cfg.path, svc.cfg.overrides)
        except Exception as exc:  # ConfigError, or anything unforeseen: the running config stays
            svc.report(f"reload refused: {exc}", 3)
            svc.notifier.ready(svc.status_line())
            return
        if new.source != svc.cfg.source:
            svc.report("reload: source changes need a restart; source kept", 4)
            new.raw["source"] = svc.cfg.source
        if new.service != svc.cfg.service:
            svc.report("reload: [service] scheduling changes need a restart; kept", 4)
            new.raw["service"] = svc.cfg.service
        added = [url for url in new.mavlink["endpoints"] if url not in svc.cfg.mavlink["endpoints"]]
        try:  # before anything is applied: an endpoint that cannot be opened refuses the reload
            check_can_open(added, new.mavlink["system_id"], 0)
        except OSError as exc:
            svc.report(f"reload refused: mavlink.endpoints: {exc}", 3)
            svc.notifier.ready(svc.status_line())
            return
        name = new.estimator["name"]
        if svc.compiler.needed(name, svc.estimator.name, svc.loop_counters()):
            # numba holds the interpreter lock while compiling: a child compiles, the loop runs
            # on with the old estimator, and housekeeping repeats this reload when it is done
            svc.report(f"reload: compiling {name} in a child process; {svc.estimator.name} runs meanwhile", 6)
            return
        old_cfg, svc.cfg = svc.cfg, new
        same_filter = new.estimator["name"] == old_cfg.estimator["name"]
        if same_filter and new.calibration == old_cfg.calibration and new.mounting == old_cfg.mounting:
            self._retune(new)
        else:
            self._rebuild(new, name, same_log=new.log == old_cfg.log)
        # a FIFO source's loop runs at its drain (watermark) rate, not estimation_hz
        if svc.loop_rate_hz(new) != svc.scheduler.rate_hz and not isinstance(svc.scheduler, DataReadyScheduler):
            svc.scheduler.set_rate(svc.loop_rate_hz(new))
        self._reopen_parts(new, old_cfg, same_filter)
        svc.connect_sinks()
        svc.report("configuration reloaded", 6)
        svc.notifier.ready(svc.status_line())

    def _retune(self, new: config_mod.Config) -> None:
        """New gains for the running filter: applied like live changes, recorded per parameter."""
        svc = self.host
        wanted = estimators.create(new.estimator["name"], **new.estimator["params"]).get_params()
        for name, value in wanted.items():
            if value != svc.estimator.get_params()[name]:
                svc.set_estimator_param(name, value, source="reload")
        svc.pipeline.set_declination(svc.declination_deg(new))
        svc.pipeline.mag_timeout_ns = int(new.estimator["mag_timeout_s"] * 1e9)

    def _rebuild(self, new: config_mod.Config, name: str, *, same_log: bool) -> None:
        """Another filter, calibration or mounting: a new pipeline, compiled before it runs."""
        svc = self.host
        svc.build_estimation(new)
        t0 = time.monotonic_ns()
        svc.warm_up()
        compiled = svc.compiler.last
        if compiled is not None and compiled.name == name and compiled.load_ms is None:
            compiled.load_ms = (time.monotonic_ns() - t0) / 1e6
            svc.report(compiled.text(), 6)
        svc.use_source_calibration()
        svc.use_clock_recovery()
        if svc.log_writer is not None and same_log:
            svc.log_writer.new_file()  # a fresh estimator: its own file replays exactly

    def _reopen_parts(self, new: config_mod.Config, old_cfg: config_mod.Config, same_filter: bool) -> None:
        """The flight log, MAVLink, the monitors and the live view, each reopened only when its
        own settings changed."""
        svc = self.host
        if new.log != old_cfg.log:
            if svc.log_writer is not None:
                svc.log_writer.close()
                svc.health_report.earlier_log_writers.append(svc.log_writer)  # its counts stay in the summary
            svc.open_log(new)
        elif svc.log_writer is not None:
            svc.log_writer.write_config(time.monotonic_ns(), svc.effective_config())
        if not same_filter or new.mavlink != old_cfg.mavlink or new.rates != old_cfg.rates:
            # another filter has other EST_* parameters: the table is rebuilt with the component
            svc.mavlink.close()
            try:
                svc.open_mavlink(new)
            except OSError as exc:  # taken since the check above: the running endpoints again
                new.raw["mavlink"] = old_cfg.mavlink
                svc.open_mavlink(new)
                svc.report(f"reload: mavlink.endpoints: {exc}; the running endpoints kept", 3)
        if new.monitor != old_cfg.monitor:
            svc.open_monitor(new)
        if new.divergence != old_cfg.divergence:
            svc.open_divergence(new)
        if new.live != old_cfg.live:  # a new address, rate, or switched on or off
            if svc.live is not None:
                svc.live.close()
                svc.live = None
            svc.open_live(new)
        elif svc.live is not None:
            svc.live.follow(svc.pipeline)  # before it tells its clients the new parameters
            svc.live.params_changed()
