"""Connects the running service to its MAVLink component: telemetry, parameters, commands.

Parameters the ground station sees (PARAM_REQUEST_LIST):

* ``EST_<NAME>`` — every tuning parameter of the running estimator (e.g. ``EST_BETA``),
  applied live between two samples and recorded in the flight log;
* ``MAG_DECL_DEG`` — magnetic declination added to the published heading (true north);
* ``RATE_ATT_HZ``, ``RATE_ATTQ_HZ``, ``RATE_HRIMU_HZ``, ``RATE_SYSST_HZ``, ``RATE_VIBE_HZ`` —
  publishing rates;
* ``LOOP_RATE_HZ`` — the estimation rate (read-only: change it in the configuration).

The bridge is one of the service's sinks (``ahrs_service.sinks``): the loop hands it every
estimated block (:meth:`MavlinkBridge.receive`), and the streams publish, at their own rates,
the newest estimate of the pipeline that estimated it (:class:`LatestEstimate`, built only
when a stream is due). What a ground station sends — parameter writes, calibration commands —
goes into the service through :class:`ServiceLink`, with the health and loss counters
(:class:`LinkHealth`). The bridge holds no reference to the service, its scheduler or source.

Writes follow the rules of docs/mavlink.md, "Security": a calibration starts only while the
IMU is at rest (the pipeline's rest window, judged as the gyro calibration judges it) and no
linked autopilot says it is armed; every accepted write that changed something is recorded
once with its sender (``ServiceLink.set_param_from`` for ``EST_*``, ``record_write`` for the
others), a write of the value in force not at all.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Sequence

from ahrs_service import _moved, estimators
from ahrs_service.estimators.settings import param_bounds
from ahrs_service.pipeline import EstimatedBlock, EstimationPipeline, LatestAttitude, LatestEstimate
from ahrs_service.protocols.mavlink import Identity, MavlinkComponent, ParameterTable, SensorStatus, Telemetry
from ahrs_service.protocols.mavlink.commands import ArmingState, Sender
from ahrs_service.protocols.mavlink.component import AcceptedWrite
from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.odometry import RULES as ODOMETRY_RULES
from ahrs_service.protocols.mavlink.odometry import AttitudeEstimate, OdometrySender
from ahrs_service.protocols.mavlink.settings import RATE_CONFIG_KEYS

if TYPE_CHECKING:
    from ahrs_service.config import Config


@dataclass(frozen=True, slots=True)
class LinkHealth:
    """SYS_STATUS inputs: sensor health bits and the fault counters since the start.

    overruns: loop deadline misses. load_percent: loop busy time, % of its period.
    comm_errors: bus errors. sensor_faults: saturated + non-finite readings. lost_samples:
    IMU samples that never reached the host, all causes (SYS_STATUS errors_count3).
    """

    gyro_healthy: bool
    accel_healthy: bool
    mag_present: bool
    mag_healthy: bool
    overruns: int
    load_percent: float
    comm_errors: int
    sensor_faults: int
    lost_samples: int


@dataclass(frozen=True)
class ServiceLink:
    """The control the bridge passes into the running service, its constants, and the
    status the estimate does not carry (built by the service).

    Constants — boot_ns: the service's start, monotonic ns (MAVLink's "time since boot").
    estimator: the running estimator's name; param_names: its tuning parameters.

    Control — get_param / set_param: an estimator parameter (set applies it live, logged;
    returns the value in force). get_declination / set_declination: degrees east.
    loop_rate_hz: the estimation rate. calibrate_gyro: () → (accepted, text).
    start_calibration: kind ("mag" | "accel") → (started, text).

    Status — health: :class:`LinkHealth` now. vibration: the VIBRATION levels now
    (``vibration.VibrationLevels``). odometry_send, odometry_clock: beside an autopilot,
    where ODOMETRY goes (the autopilot link's ``send``) and the clock it is stamped in
    (``AutopilotLink.clock``: TIMESYNC under the link's lock); None: the bridge's own
    endpoints, our clock (docs/autopilot.md). attitude_diverged: the divergence monitor
    flags the attitude as not trustworthy now (SYS_STATUS AHRS unhealthy, ODOMETRY failed);
    None: never.

    For a bridge with no pipeline to follow (driven by hand, as in tests): latest,
    latest_attitude: the newest estimate and its attitude, None before the first;
    attitude_variance: the roll/pitch/yaw variances now, rad² (ODOMETRY). A bridge that
    follows a pipeline (:meth:`MavlinkBridge.receive`) reads these from the pipeline.

    Who wrote — set_param_from: set_param with the writer, (name, value, source) → the value
    in force, where source names the sender (``"mavlink 255/190 unsigned"``) and the service
    records the change with it (its ``set_estimator_param``); None: set_param, the writer not
    recorded. record_write: (name, old, new, source) — every other accepted write that changed
    something (``MAG_DECL_DEG``, ``RATE_*``, ``"<MESSAGE> rate Hz"`` of a message interval,
    ``"calibration"`` with the sensor as its new value), to record once on the flight log's
    /params and /log; None: not recorded. autopilot: the ``AutopilotLink`` beside an
    autopilot, whose HEARTBEATs say whether it is armed (no calibration starts then).
    """

    boot_ns: int
    estimator: str
    param_names: Sequence[str]
    health: Callable[[], LinkHealth]
    get_param: Callable[[str], float]
    set_param: Callable[[str, float], float]
    get_declination: Callable[[], float]
    set_declination: Callable[[float], None]
    loop_rate_hz: Callable[[], float]
    calibrate_gyro: Callable[[], tuple[bool, str]]
    start_calibration: Callable[[str], tuple[bool, str]]
    vibration: Callable[[], Any]
    odometry_send: Callable[[Any], Any] | None = None
    odometry_clock: Any = None
    attitude_diverged: Callable[[], bool] | None = None
    latest: Callable[[], LatestEstimate | None] | None = None
    latest_attitude: Callable[[], LatestAttitude | LatestEstimate | None] | None = None
    attitude_variance: Callable[[], Any] | None = None
    set_param_from: Callable[[str, float, str], float] | None = None
    record_write: Callable[[str, Any, Any, str], None] | None = None
    autopilot: Any = None

# incoming commands and parameter writes are handled at 50 Hz: a ground station does not
# notice 20 ms, and an idle non-blocking read costs as much as a published message
POLL_PERIOD_NS = 20_000_000

RATE_PARAMS = {
    "RATE_ATT_HZ": "ATTITUDE",
    "RATE_ATTQ_HZ": "ATTITUDE_QUATERNION",
    "RATE_HRIMU_HZ": "HIGHRES_IMU",
    "RATE_SYSST_HZ": "SYS_STATUS",
    "RATE_VIBE_HZ": "VIBRATION",
}


#: no sample estimated for this long: the attitude streams stop (Telemetry.attitude_fresh) and
#: the gyroscope is reported unhealthy, until samples come again
STALE_NS = 250_000_000

#: an EST_* parameter may move this factor away from its default (and to 0), not further
EST_RANGE_FACTOR = 1000.0

def rest_refusal(pipeline: EstimationPipeline) -> str:
    """Why ``pipeline``'s rest window (its last ``REST_WINDOW_S`` of samples) does not show the
    IMU at rest, judged as the gyro calibration judges it (``EstimationPipeline.rest_check``);
    "" when it does."""
    check = pipeline.rest_check()
    return "" if check.at_rest else f"not at rest ({check.reason})"


def write_source(sender: Sender | None) -> str:
    """How the flight log names a writer: ``"mavlink 255/190 unsigned"`` (``"mavlink"`` when
    unknown)."""
    return "mavlink" if sender is None else f"mavlink {sender}"


def estimator_param_bounds(default: float, factor: float = EST_RANGE_FACTOR) -> tuple[float, float]:
    """[minimum, maximum] of an estimator parameter over the air
    (:func:`ahrs_service.estimators.settings.param_bounds`): ``EST_RANGE_FACTOR`` keeps
    PARAM_SET from putting 3e38 into a filter; the configuration file (``estimator.params``)
    gets the wider ``CONFIG_RANGE_FACTOR`` of the same module."""
    return param_bounds(default, factor)


def estimator_param_names(names: list[str]) -> dict[str, str]:
    """MAVLink names (≤ 16 characters) of an estimator's parameters: ``EST_`` + upper case,
    long names shortened word by word (``consistency_tau`` → ``EST_CONS_TAU``), clashes
    numbered. The full name is each parameter's description."""
    out: dict[str, str] = {}
    for name in names:
        words = name.upper().split("_")
        for width in (99, 6, 5, 4, 3, 2):
            short = "_".join(w[:width] for w in words)
            if len(short) <= 12:
                break
        short = short[:12]
        candidate, k = short, 1
        while "EST_" + candidate in out.values():
            k += 1
            candidate = f"{short[:10]}{k:02d}"
        out[name] = "EST_" + candidate
    return out


class MavlinkBridge:
    """The service's MAVLink side: a sink of estimated blocks (:meth:`receive`);
    :meth:`tick` is called from the estimation loop."""

    def __init__(self, link: ServiceLink, cfg: "Config", *, io_period_ns: int,
                 estimates: EstimationPipeline | None = None) -> None:
        """link: the control and status interface of the service. io_period_ns: how often
        the loop calls :meth:`tick` (ns); the fastest a stream can go. estimates: the pipeline
        whose newest estimate the streams publish, until a block of another one arrives."""
        self.link = link
        self.estimates = estimates
        self._next_poll_ns = 0
        self._samples_seen = -1  # samples estimated at the last telemetry, and when it last grew
        self._fresh_at_ns = 0
        mcfg = cfg.mavlink
        identity = (
            Identity.standalone(mcfg["system_id"])
            if mcfg["identity"] == "standalone"
            else Identity.companion(mcfg["system_id"])
        )
        key = bytes.fromhex(mcfg["signing_key"]) if mcfg["signing_key"] else None
        self.arming = ArmingState()
        self._autopilot = link.autopilot
        if self._autopilot is not None:
            self._autopilot.subscribe(["HEARTBEAT"], self.arming.on_heartbeat)
        self.component = MavlinkComponent(
            mcfg["endpoints"],
            identity,
            rates={msg: cfg.rates[key_] for msg, key_ in RATE_CONFIG_KEYS.items()},
            signing_key=key,
            params=self._parameter_table(),
            gyro_calibration=self._calibrate_gyro,
            mag_calibration=lambda action: self._start_collection("mag"),
            accel_calibration=lambda action: self._start_collection("accel"),
            max_rate_hz=1e9 / io_period_ns,
            current_telemetry=lambda: self.telemetry(time.monotonic_ns(), self.latest()),
            calibration_guard=self._calibration_refusal,
            on_write=self._record_write,
            require_signed_writes=mcfg["require_signing_for_writes"],
        )
        self.odometry = self._odometry_sender(mcfg["odometry"])

    # ------------------------------------------------------------------ estimates in
    def receive(self, estimated: EstimatedBlock) -> None:
        """An estimated block (loop thread, once per block): the streams publish from the
        pipeline that estimated it, at their own rates (nothing is built here)."""
        self.estimates = estimated.pipeline

    def follow(self, pipeline: EstimationPipeline) -> None:
        """Publishes ``pipeline``'s estimates from now on (a reload built a new one)."""
        self.estimates = pipeline

    def latest(self) -> LatestEstimate | None:
        """The newest estimate to publish; None before the first."""
        estimates = self.estimates
        if estimates is not None:
            return estimates.latest_estimate()
        latest = self.link.latest
        return latest() if latest is not None else None

    def _latest_attitude(self) -> LatestAttitude | LatestEstimate | None:
        estimates = self.estimates
        if estimates is not None:
            return estimates.latest_attitude()
        link = self.link
        return link.latest_attitude() if link.latest_attitude is not None else self.latest()

    def _attitude_variance(self) -> Any:
        estimates = self.estimates
        if estimates is not None:
            return estimates.estimator.attitude_variance()
        return self.link.attitude_variance() if self.link.attitude_variance is not None else None

    # ------------------------------------------------------------------ ODOMETRY
    def _odometry_sender(self, ocfg: dict[str, Any]) -> OdometrySender | None:
        if ocfg["rate_hz"] <= 0.0:
            return None
        self._odometry_epoch = 0
        self._odometry_ref: tuple[Any, float, bool] | None = None
        link = self.link
        return OdometrySender(link.odometry_send or self.component.send, ocfg["rate_hz"], ODOMETRY_RULES[ocfg["rules"]],
                              timesync=link.odometry_clock)

    def _fresh(self, est: LatestEstimate | LatestAttitude, now_ns: int) -> bool:
        """Whether a sample was estimated within ``STALE_NS`` of ``now_ns`` (the estimate's
        sample count grew)."""
        if est.samples != self._samples_seen:
            self._samples_seen, self._fresh_at_ns = est.samples, now_ns
        return now_ns - self._fresh_at_ns <= STALE_NS

    def odometry_estimate(self, now_ns: int, est: LatestEstimate | None) -> AttitudeEstimate | None:
        """The published attitude of ``est`` (the link's newest) and its variances for
        ODOMETRY; None before the first sample. The epoch goes up when the estimator object,
        its initialisation or the declination changes (the heading reference moved:
        ODOMETRY's reset_counter follows)."""
        if est is None:
            return None
        fresh = self._fresh(est, now_ns)
        ref = (est.estimator_id, est.declination_deg, est.initialised)
        if self._odometry_ref is not None and ref != self._odometry_ref:
            self._odometry_epoch += 1
        self._odometry_ref = ref
        var = self._attitude_variance()
        diverged = self._diverged()
        return AttitudeEstimate(
            t_ns=int(est.t_ns),
            q=est.q,
            body_rate=est.body_rate,
            roll_var=var.roll,
            pitch_var=var.pitch,
            yaw_var=var.yaw if est.mag_used else float("nan"),
            healthy=est.initialised and fresh,
            epoch=self._odometry_epoch,
            diverged=diverged,
        )

    def _diverged(self) -> bool:
        check = self.link.attitude_diverged
        return bool(check()) if check is not None else False

    # ------------------------------------------------------------------ parameters
    def _parameter_table(self) -> ParameterTable:
        link = self.link
        table = ParameterTable()
        defaults = estimators.create(link.estimator).get_params()
        for name, mav_name in estimator_param_names(list(link.param_names)).items():
            lo, hi = estimator_param_bounds(defaults[name])
            table.add(
                mav_name,
                getter=lambda n=name: link.get_param(n),
                setter=lambda v, n=name: self._set_estimator_param(n, float(v)),
                minimum=lo,
                maximum=hi,
                description=f"{link.estimator} parameter {name}",
            )
        table.add(
            "MAG_DECL_DEG",
            getter=link.get_declination,
            setter=lambda v: link.set_declination(float(v)),
            minimum=-180.0,
            maximum=180.0,
            description="magnetic declination, degrees east, added to the published heading",
        )
        for pname, msg in RATE_PARAMS.items():
            table.add(
                pname,
                getter=lambda m=msg: self.component.rates[m],
                setter=lambda v, m=msg: self.component.set_rate(m, float(v)),
                minimum=0.0,
                maximum=200.0,
                description=f"{msg} rate, Hz (0 = off)",
            )
        table.add("LOOP_RATE_HZ", getter=link.loop_rate_hz, description="estimation rate, Hz (read-only)")
        return table

    def _set_estimator_param(self, name: str, value: float) -> float:
        """An ``EST_*`` write, recorded by the service with the sender the component is
        handling (``set_param_from``) when it can take one."""
        link = self.link
        if link.set_param_from is None:
            return link.set_param(name, value)
        return link.set_param_from(name, value, write_source(self.component.sender))

    def _record_write(self, write: AcceptedWrite) -> None:
        """An accepted write that changed something: recorded once, with its sender. ``EST_*``
        writes were recorded by the service as they were applied."""
        record = self.link.record_write
        if record is None or write.name.startswith("EST_"):
            return
        record(write.name, write.old, write.new, write_source(write.sender))

    # ------------------------------------------------------------------ commands
    def _calibration_refusal(self, sensor: str) -> str:
        """Why a ``sensor`` calibration may not start now ("" when it may): an armed autopilot
        (PX4 and ArduPilot refuse calibrating while armed), or an IMU not at rest (what keeps
        a vehicle in flight out where no autopilot is linked). A bridge following no pipeline
        leaves rest to the callbacks."""
        if self.arming.armed:
            return "the autopilot is armed"
        if self.estimates is not None:
            return rest_refusal(self.estimates)
        return ""

    def _calibrate_gyro(self, action: int) -> tuple[int, str]:
        accepted, text = self.link.calibrate_gyro()
        return (mavlink.MAV_RESULT_ACCEPTED if accepted else mavlink.MAV_RESULT_TEMPORARILY_REJECTED), text

    def _start_collection(self, kind: str) -> tuple[int, str]:
        started, text = self.link.start_calibration(kind)
        return (mavlink.MAV_RESULT_ACCEPTED if started else mavlink.MAV_RESULT_TEMPORARILY_REJECTED), text

    # ------------------------------------------------------------------ per tick
    def telemetry(self, now_ns: int, est: LatestEstimate | None) -> Telemetry | None:
        """What the streams publish now from ``est`` (the link's newest); None until the first
        sample is estimated (then HEARTBEAT alone goes out, state BOOT: there is no attitude yet)."""
        link = self.link
        if est is None:
            return None
        fresh = self._fresh(est, now_ns)
        h = link.health()
        return Telemetry.from_quaternion(
            (now_ns - link.boot_ns) // 1_000_000,
            est.q,
            est.body_rate,
            gyr=est.gyr,
            acc=est.acc,
            mag=est.mag,
            mag_new=est.mag_new,
            temperature_c=est.temperature_c,
            time_usec=(est.t_ns - link.boot_ns) // 1000,
            attitude_fresh=fresh,
            gyro=SensorStatus(True, True, h.gyro_healthy and fresh),
            # no new estimate for STALE_NS: nothing of the IMU arrives (an autopilot that stopped
            # its IMU stream but beats on), the accelerometer no more than the gyroscope
            accel=SensorStatus(True, True, h.accel_healthy and fresh),
            mag_status=SensorStatus(h.mag_present, est.mag_used, h.mag_healthy),
            estimator=link.estimator,
            # a stale estimate is an unhealthy AHRS, as ArduPilot's GCS::update_sensor_status_flags
            # clears MAV_SYS_STATUS_AHRS when ahrs.healthy() fails (docs/mavlink.md, "Health per sensor")
            # the divergence monitor's flag too: an estimate the accelerometer contradicts is
            # no healthy AHRS (docs/autopilot.md, "Divergence monitor")
            ahrs_healthy=est.initialised and fresh and not self._diverged(),
            reduced_mode=est.reduced,
            overruns=h.overruns,
            load_percent=h.load_percent,
            comm_errors=h.comm_errors,
            sensor_faults=h.sensor_faults,
            lost_samples=h.lost_samples,
            vibration=link.vibration(),
        )

    def attitude_telemetry(self, now_ns: int) -> Telemetry | None:
        """What ATTITUDE and ATTITUDE_QUATERNION publish now (``attitude_only``: the health,
        readings and vibration fields left at their defaults); None before the first sample."""
        link = self.link
        att = self._latest_attitude()
        if att is None:
            return None
        return Telemetry.from_quaternion((now_ns - link.boot_ns) // 1_000_000, att.q, att.body_rate,
                                         attitude_fresh=self._fresh(att, now_ns), attitude_only=True)

    def tick(self, now_ns: int) -> None:
        """Publishes what is due and, every ``POLL_PERIOD_NS``, handles what came in.

        The telemetry snapshot is built only when a stream is due (at 100 Hz ATTITUDE that is
        every other 5 ms tick), and in full only when a stream other than ATTITUDE and
        ATTITUDE_QUATERNION is due (HEARTBEAT, SYS_STATUS, VIBRATION at 1-2 Hz): the health,
        readings and vibration snapshot is the costliest part of a publish (docs/mavlink.md).
        """
        component, odometry = self.component, self.odometry
        odometry_due = odometry is not None and odometry.due(now_ns)
        # the newest estimate in full only where ODOMETRY or a full snapshot needs it, once
        est = self.latest() if odometry_due else None
        if component.due(now_ns):
            component.publish_built(now_ns, lambda attitude_only: (
                self.attitude_telemetry(now_ns) if attitude_only
                else self.telemetry(now_ns, est if est is not None else self.latest())))
        if odometry_due:
            odometry.tick(now_ns, self.odometry_estimate(now_ns, est))  # type: ignore[union-attr]
        if now_ns >= self._next_poll_ns:
            self._next_poll_ns = now_ns + POLL_PERIOD_NS
            component.poll(50)

    def statustext(self, severity: int, text: str, kind: str | None = None) -> None:
        self.component.statustext(severity, text, kind)

    def stats(self) -> dict[str, Any]:
        return self.component.stats.as_dict()

    def close(self) -> None:
        if self._autopilot is not None:
            self._autopilot.unsubscribe(self.arming.on_heartbeat)
        self.component.close()


def __getattr__(name: str):  # names that moved out of this module keep working for one release
    return _moved.moved_name(__name__, name)
