"""Connects the running service to its MAVLink component: telemetry, parameters, commands.

Parameters the ground station sees (PARAM_REQUEST_LIST):

* ``EST_<NAME>`` — every tuning parameter of the running estimator (e.g. ``EST_BETA``),
  applied live between two samples and recorded in the flight log;
* ``MAG_DECL_DEG`` — magnetic declination added to the published heading (true north);
* ``RATE_ATT_HZ``, ``RATE_ATTQ_HZ``, ``RATE_HRIMU_HZ``, ``RATE_SYSST_HZ``, ``RATE_VIBE_HZ`` —
  publishing rates;
* ``LOOP_RATE_HZ`` — the estimation rate (read-only: change it in the configuration).
"""

from __future__ import annotations

import contextlib
from typing import TYPE_CHECKING, Any

from ahrs_service import estimators
from ahrs_service.drivers.base import MAG_NEW
from ahrs_service.estimators import STATE_HEADER
from ahrs_service.protocols.mavlink import Identity, MavlinkComponent, ParameterTable, SensorStatus, Telemetry
from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.odometry import RULES as ODOMETRY_RULES
from ahrs_service.protocols.mavlink.odometry import AttitudeEstimate, OdometrySender
from ahrs_service.protocols.mavlink.timesync import TimeSync

if TYPE_CHECKING:
    from ahrs_service.config import Config
    from ahrs_service.service import Service

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
RATE_CONFIG_KEYS = {
    "HEARTBEAT": "heartbeat_hz",
    "ATTITUDE": "attitude_hz",
    "ATTITUDE_QUATERNION": "attitude_quaternion_hz",
    "HIGHRES_IMU": "highres_imu_hz",
    "SYS_STATUS": "sys_status_hz",
    "VIBRATION": "vibration_hz",
}


#: no sample estimated for this long: the attitude streams stop (Telemetry.attitude_fresh) and
#: the gyroscope is reported unhealthy, until samples come again
STALE_NS = 250_000_000

#: an EST_* parameter may move this factor away from its default (and to 0), not further
EST_RANGE_FACTOR = 1000.0


def estimator_param_bounds(default: float) -> tuple[float, float]:
    """[minimum, maximum] of an ``EST_*`` parameter: from 0 to ``EST_RANGE_FACTOR`` times its
    default on the default's side (a gain, a time constant, a noise level); ±EST_RANGE_FACTOR
    around a default of 0. Keeps PARAM_SET from putting 3e38 into a filter over the air; wider
    changes go through the configuration file (``estimator.params``)."""
    if default > 0:
        return 0.0, default * EST_RANGE_FACTOR
    if default < 0:
        return default * EST_RANGE_FACTOR, 0.0
    return -EST_RANGE_FACTOR, EST_RANGE_FACTOR


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
    """The service's MAVLink side; :meth:`tick` is called from the estimation loop."""

    def __init__(self, service: "Service", cfg: "Config", *, io_period_ns: int) -> None:
        """io_period_ns: how often the loop calls :meth:`tick` (ns); the fastest a stream can
        go. Handed in by the service, so this module does not import the service's."""
        self.svc = service
        self._next_poll_ns = 0
        self._samples_seen = -1  # pipeline.samples at the last telemetry, and when it last grew
        self._fresh_at_ns = 0
        mcfg = cfg.mavlink
        identity = (
            Identity.standalone(mcfg["system_id"])
            if mcfg["identity"] == "standalone"
            else Identity.companion(mcfg["system_id"])
        )
        key = bytes.fromhex(mcfg["signing_key"]) if mcfg["signing_key"] else None
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
        )
        # beside an autopilot the service hands over the link's TIMESYNC estimate and the lock
        # its reader thread updates it under (docs/autopilot.md, "TIMESYNC")
        self.timesync: TimeSync | None = None
        self.timesync_lock: Any = contextlib.nullcontext()
        #: the autopilot link's send (AutopilotLink.send), set by the service beside an autopilot:
        #: ODOMETRY goes there as well as on the endpoints
        self.autopilot_send: Any = None
        self.odometry = self._odometry_sender(mcfg["odometry"])

    # ------------------------------------------------------------------ ODOMETRY (issue 17)
    def _odometry_sender(self, ocfg: dict[str, Any]) -> OdometrySender | None:
        if ocfg["rate_hz"] <= 0.0:
            return None
        self._odometry_epoch = 0
        self._odometry_ref: tuple[Any, float, bool] | None = None
        return OdometrySender(self._send_odometry, ocfg["rate_hz"], ODOMETRY_RULES[ocfg["rules"]])

    def _send_odometry(self, msg: Any) -> None:
        self.component.send(msg)
        if self.autopilot_send is not None:
            self.autopilot_send(msg)

    def odometry_estimate(self, now_ns: int) -> AttitudeEstimate | None:
        """The published attitude and its variances for ODOMETRY; None before the first sample.
        The epoch goes up when the estimator object, its initialisation or the declination
        changes (the heading reference moved: ODOMETRY's reset_counter follows)."""
        svc = self.svc
        pipeline = svc.pipeline
        sample = pipeline.last_sample
        if sample is None:
            return None
        if pipeline.samples != self._samples_seen:
            self._samples_seen, self._fresh_at_ns = pipeline.samples, now_ns
        fresh = now_ns - self._fresh_at_ns <= STALE_NS
        est = svc.estimator
        initialised = bool(est.state[STATE_HEADER.index.initialised])
        ref = (id(est), pipeline.declination_deg, initialised)
        if self._odometry_ref is not None and ref != self._odometry_ref:
            self._odometry_epoch += 1
        self._odometry_ref = ref
        var = est.attitude_variance()
        heading = pipeline.use_mag and not pipeline.reduced
        return AttitudeEstimate(
            t_ns=int(sample.t_ns),
            q=pipeline.published_quaternion(),
            body_rate=pipeline.body_rates(),
            roll_var=var.roll,
            pitch_var=var.pitch,
            yaw_var=var.yaw if heading else float("nan"),
            healthy=initialised and fresh,
            epoch=self._odometry_epoch,
        )

    # ------------------------------------------------------------------ parameters
    def _parameter_table(self) -> ParameterTable:
        svc = self.svc
        table = ParameterTable()
        defaults = estimators.create(svc.estimator.name).get_params()
        for name, mav_name in estimator_param_names(svc.estimator.param_names()).items():
            lo, hi = estimator_param_bounds(defaults[name])
            table.add(
                mav_name,
                getter=lambda n=name: svc.estimator.get_params()[n],
                setter=lambda v, n=name: svc.set_estimator_param(n, float(v)),
                minimum=lo,
                maximum=hi,
                description=f"{svc.estimator.name} parameter {name}",
            )
        table.add(
            "MAG_DECL_DEG",
            getter=lambda: svc.pipeline.declination_deg,
            setter=lambda v: svc.pipeline.set_declination(float(v)),
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
        table.add("LOOP_RATE_HZ", getter=lambda: svc.scheduler.rate_hz, description="estimation rate, Hz (read-only)")
        return table

    # ------------------------------------------------------------------ commands
    def _calibrate_gyro(self, action: int) -> tuple[int, str]:
        check = self.svc.pipeline.calibrate_gyro_bias()
        if not check.at_rest:
            return mavlink.MAV_RESULT_TEMPORARILY_REJECTED, f"gyro calibration refused: {check.reason}"
        bias = self.svc.pipeline.calibration.gyro_bias
        self.svc.record_calibration("gyro")
        return mavlink.MAV_RESULT_ACCEPTED, "gyro bias set to [{:.4f}, {:.4f}, {:.4f}] rad/s".format(*bias)

    def _start_collection(self, kind: str) -> tuple[int, str]:
        started, text = self.svc.start_live_calibration(kind)
        return (mavlink.MAV_RESULT_ACCEPTED if started else mavlink.MAV_RESULT_TEMPORARILY_REJECTED), text

    # ------------------------------------------------------------------ per tick
    def telemetry(self, now_ns: int) -> Telemetry | None:
        """What the streams publish now; None until the first sample is estimated (then
        HEARTBEAT alone goes out, state BOOT: there is no attitude yet)."""
        svc = self.svc
        pipeline = svc.pipeline
        sample = pipeline.last_sample
        if sample is None:
            return None
        if pipeline.samples != self._samples_seen:
            self._samples_seen, self._fresh_at_ns = pipeline.samples, now_ns
        fresh = now_ns - self._fresh_at_ns <= STALE_NS
        health = svc.health()
        st = svc.scheduler
        diag = svc.source.diagnostics
        mag_used = pipeline.use_mag and not pipeline.reduced
        return Telemetry.from_quaternion(
            (now_ns - svc.boot_ns) // 1_000_000,
            pipeline.published_quaternion(),
            pipeline.body_rates(),
            gyr=sample.gyr,
            acc=sample.acc,
            mag=sample.mag,
            mag_new=bool(sample.flags & MAG_NEW),
            temperature_c=sample.temperature_c,
            time_usec=(sample.t_ns - svc.boot_ns) // 1000,
            attitude_fresh=fresh,
            gyro=SensorStatus(True, True, health["gyro_healthy"] and fresh),
            accel=SensorStatus(True, True, health["accel_healthy"]),
            mag_status=SensorStatus(health["mag_present"], mag_used, health["mag_healthy"]),
            estimator=svc.estimator.name,
            # a stale estimate is an unhealthy AHRS, as ArduPilot's GCS::update_sensor_status_flags
            # clears MAV_SYS_STATUS_AHRS when ahrs.healthy() fails (docs/mavlink.md, "Health per sensor")
            ahrs_healthy=bool(svc.estimator.state[STATE_HEADER.index.initialised]) and fresh,
            reduced_mode=pipeline.reduced or not pipeline.use_mag,
            overruns=st.overruns,
            load_percent=svc.last_load_percent,
            comm_errors=diag.bus_errors,
            sensor_faults=diag.saturated + diag.non_finite,
            lost_samples=diag.lost.total,
            vibration=svc.vibration.levels(),
        )

    def tick(self, now_ns: int) -> None:
        """Publishes what is due and, every ``POLL_PERIOD_NS``, handles what came in.

        The telemetry snapshot is built only when a stream is due: at 100 Hz ATTITUDE that is
        every other 5 ms tick, and building it is the costliest part of a tick.
        """
        component = self.component
        if component.due(now_ns):
            component.publish(now_ns, self.telemetry(now_ns))
        odometry = self.odometry
        if odometry is not None and odometry.due(now_ns):
            odometry.timesync = self.timesync
            estimate = self.odometry_estimate(now_ns)
            with self.timesync_lock:
                odometry.tick(now_ns, estimate)
        if now_ns >= self._next_poll_ns:
            self._next_poll_ns = now_ns + POLL_PERIOD_NS
            component.poll(50)

    def statustext(self, severity: int, text: str, kind: str | None = None) -> None:
        self.component.statustext(severity, text, kind)

    def stats(self) -> dict[str, Any]:
        return self.component.stats.as_dict()

    def close(self) -> None:
        self.component.close()
