"""The divergence monitor (ahrs_service/core/divergence.py): the accelerometer against the estimate.

* synthetic streams: a consistent one never flags, whatever the blocks; a tilt error ramped in
  flags within 2 s of passing 10° and clears once the estimate is consistent again;
* the loaded run of the pre-fix service (tests/fixtures/logs/robust_diverged_under_load.mcap,
  made by tests/fixtures/make_divergence_fixture.py): flagged within 2 s of the error passing 10°,
  against the simulator's truth in the log;
* BROAD and DIDO without gaps (skipped without them): no false alarm with ``robust`` or ``ekf``;
* the running service: SYS_STATUS, STATUSTEXT, ODOMETRY, the log's /attitude diagnostics and
  /log, and the summary, on a recorded flight whose gyroscope glitches.
"""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from ahrs_service import config as config_mod
from ahrs_service import estimators
from ahrs_service.core.divergence import DIVERGENCE, G, DivergenceMonitor, DivergenceSettings, scan
from ahrs_service.core.quaternion import (
    quat_conj_array,
    quat_from_euler_array,
    quat_from_rotvec_array,
    quat_mul_array,
    quat_rotate_array,
)
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID
from ahrs_service.estimators.base import time_steps
from ahrs_service.logs.reader import read_log
from ahrs_service.protocols.mavlink.dialect import mavlink
from ahrs_service.protocols.mavlink.odometry import DIVERGED_VARIANCE, PX4, AttitudeEstimate, OdometrySender, quality_of

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "logs" / "robust_diverged_under_load.mcap"
FIELD_NED = np.array([20.0, 0.0, 45.0])  # µT


def _inclination_deg(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """Angle between the estimated and the true vertical in the body, deg (both q_ned←body)."""
    down = np.broadcast_to([0.0, 0.0, 1.0], (len(q_est), 3))
    a = quat_rotate_array(quat_conj_array(q_est), down)
    b = quat_rotate_array(quat_conj_array(q_true), down)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


def _moving_body(seconds: float, rate_hz: float = 400.0, seed: int = 3, shake: float = 1.0):
    """A body turning about all axes and, with ``shake`` 1, shaken horizontally (2 m/s² at
    1.3 Hz, 1.5 m/s² at 0.9 Hz, zero mean; 0: turning in place): (t s, q_true (n, 4)
    q_ned←body, acc (n, 3) m/s² specific force FRD with noise, mag µT)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    euler = np.stack([0.4 * np.sin(0.7 * t), 0.3 * np.sin(0.5 * t + 1.0), 0.8 * t], axis=1)
    q = quat_from_euler_array(euler)
    lin = shake * np.stack([2.0 * np.sin(2 * np.pi * 1.3 * t), 1.5 * np.cos(2 * np.pi * 0.9 * t), 0 * t], axis=1)
    f_ned = lin + np.array([0.0, 0.0, -G])
    qc = quat_conj_array(q)
    acc = quat_rotate_array(qc, f_ned) + rng.normal(0.0, 0.3, (len(t), 3))
    mag = quat_rotate_array(qc, np.broadcast_to(FIELD_NED, (len(t), 3))) + rng.normal(0.0, 0.5, (len(t), 3))
    return t, q, acc, mag


def _tilted(q_true: np.ndarray, error_deg: np.ndarray) -> np.ndarray:
    """The estimate ``error_deg`` off in tilt, about the earth's north axis."""
    rot = quat_from_rotvec_array(np.radians(error_deg)[:, None] * np.array([1.0, 0.0, 0.0]))
    return quat_mul_array(rot, q_true)


def _feed(monitor: DivergenceMonitor, t, acc, q, mag, sizes) -> list:
    events, i, k = [], 0, 0
    while i < len(t):
        n = sizes[k % len(sizes)]
        events += monitor.update(t[i:i + n], acc[i:i + n], q[i:i + n], None if mag is None else mag[i:i + n])
        i, k = i + n, k + 1
    return events


# ---------------------------------------------------------------------------------- synthetic
def test_a_consistent_estimate_of_a_moving_shaken_body_never_flags():
    t, q, acc, mag = _moving_body(60.0)
    monitor = DivergenceMonitor()
    events = _feed(monitor, t, acc, q, mag, [1, 7, 64, 400])
    v = monitor.verdict
    assert events == [] and not v.diverged and v.flags == 0
    assert 0.0 <= v.test_ratio < 0.5 and v.tilt_innovation_deg < 3.0 and abs(v.heading_innovation_deg) < 3.0
    assert v.samples > 0.9 * 3.0 * 400
    assert monitor.summary() == "attitude: consistent throughout"


def test_a_tilt_error_ramped_to_15_deg_flags_within_2_s_of_passing_10_and_clears():
    t, q, acc, mag = _moving_body(40.0, shake=0.0)
    # 0 until 10 s, 15° by 11.5 s (10° at 11 s), held until 20 s, then consistent again
    error = np.clip((t - 10.0) / 1.5, 0.0, 1.0) * 15.0
    error[t >= 20.0] = 0.0
    q_est = _tilted(q, error)
    t10 = t[np.argmax(error > 10.0)]
    runs = []
    for sizes in ([1], [7, 64], [1000], [len(t)]):  # the verdicts do not depend on the blocks
        monitor = DivergenceMonitor()
        runs.append((_feed(monitor, t, acc, q_est, mag, sizes), monitor))
    events, monitor = runs[0]
    assert [(e.t_s, e.diverged) for e in events] == [(e.t_s, e.diverged) for e in runs[-1][0]]
    assert [e.diverged for e in events] == [True, False]
    flagged, cleared = events[0].t_s, events[1].t_s
    assert t10 < flagged <= t10 + 2.0, (t10, flagged)
    assert events[0].verdict.tilt_innovation_deg > 8.0 and events[0].verdict.test_ratio > 1.0
    # consistent from 20 s: the 3 s window empties of the error, then 2 s below half the gate
    assert 20.0 + 2.0 <= cleared <= 20.0 + 3.0 + 2.0 + 0.5, cleared
    assert monitor.verdict.flags == 1 and not monitor.verdict.diverged
    assert monitor.verdict.diverged_s == pytest.approx(cleared - flagged, abs=1e-9)
    assert events[0].text().startswith("attitude diverged: tilt innovation ")
    assert monitor.summary() == f"attitude: diverged 1 time ({cleared - flagged:.1f} s in all), consistent at the end"


def test_a_shaken_body_widens_the_gate_but_a_larger_error_is_still_flagged():
    t, q, acc, mag = _moving_body(30.0)
    for degrees, within_s in ((30.0, 2.0), (40.0, 1.0)):
        error = np.where(t >= 10.0, degrees, 0.0)
        monitor, events = scan(t, acc, _tilted(q, error), mag)
        assert events and events[0].diverged and 10.0 < events[0].t_s <= 10.0 + within_s, (degrees, events[:1])


def test_a_tumbling_estimate_flags_within_a_second():
    t, q, acc, mag = _moving_body(20.0)
    error = np.where(t >= 8.0, 90.0, 0.0)
    monitor, events = scan(t, acc, _tilted(q, error), mag)
    assert events and events[0].diverged and 8.0 < events[0].t_s <= 9.0
    assert monitor.verdict.gross_innovation_deg > 60.0


def test_no_accelerometer_decides_nothing():
    t, q, acc, mag = _moving_body(10.0)
    acc[:] = np.nan
    monitor, events = scan(t, acc, _tilted(q, np.full(len(t), 40.0)), mag)
    assert events == [] and not monitor.verdict.diverged and math.isnan(monitor.verdict.test_ratio)
    assert monitor.verdict.samples == 0


def test_the_configuration_section_is_checked():
    assert config_mod.validate({}).divergence == {k: v[0] for k, v in DIVERGENCE.items()}
    cfg = config_mod.validate({"divergence": {"gate_deg": 8.0, "window_s": 4.0}})
    assert DivergenceSettings.from_config(cfg.divergence) == DivergenceSettings(gate_deg=8.0, window_s=4.0)
    with pytest.raises(config_mod.ConfigError, match=r"^divergence\.gate_deg: 0\.1 is out of range"):
        config_mod.validate({"divergence": {"gate_deg": 0.1}})
    with pytest.raises(config_mod.ConfigError, match=r"^divergence\.clear_sec: unknown key"):
        config_mod.validate({"divergence": {"clear_sec": 1.0}})


def test_odometry_of_a_diverged_estimate_is_failed_with_uninformative_variances():
    est = AttitudeEstimate(0, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1e-4, 1e-4, 4e-4)
    bad = AttitudeEstimate(0, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 1e-4, 1e-4, float("nan"), diverged=True)
    assert quality_of(est) > 0 and quality_of(bad) == -1
    msg = OdometrySender(lambda m: None, 30.0, PX4).encode(bad)
    assert msg.quality == -1
    assert [msg.pose_covariance[i] for i in (15, 18, 20)] == [DIVERGED_VARIANCE] * 3


# ---------------------------------------------------------------------------------- the loaded run
def test_the_loaded_pre_fix_run_is_flagged_within_2_s_of_its_error_passing_10_deg():
    assert FIXTURE.stat().st_size < 1_500_000
    log = read_log(FIXTURE)
    assert log.estimator == "robust" and log.truth is not None and log.damage is None
    t = log.t_ns * 1e-9
    error = _inclination_deg(log.attitudes, log.truth)
    assert error.max() > 150.0  # the recorded estimate was that far off the simulator's truth
    monitor, events = scan(t, log.rows[:, 3:6], log.attitudes, log.rows[:, 6:9])
    t10 = t[np.argmax(error > 10.0)]
    assert t10 - t[0] > 1.5  # a consistent start: nothing to flag before
    first = events[0]
    assert first.diverged and t10 < first.t_s <= t10 + 2.0, (t10 - t[0], first.t_s - t[0])
    # every divergence (above 10° for 0.3 s or more) has the flag up within 2 s of its start
    bad = error > 10.0
    starts = np.flatnonzero(np.diff(bad.astype(int)) == 1) + 1
    flags = [(e.t_s, e.diverged) for e in events]
    for s in starts:
        end = s + np.argmax(~bad[s:]) if (~bad[s:]).any() else len(t) - 1
        if t[end] - t[s] < 0.3:
            continue
        state = [d for ts, d in flags if ts <= t[s] + 2.0]
        assert state and state[-1], f"error from {t[s] - t[0]:.2f} s not flagged within 2 s"
    assert any(not d for _, d in flags)  # it clears when the estimate is consistent again
    assert monitor.verdict.flags >= 3


# ---------------------------------------------------------------------------------- BROAD, DIDO
def _flags_on(trial, name: str) -> tuple[list, np.ndarray, np.ndarray]:
    est = estimators.create(name)
    stamps = getattr(trial, "timestamps", None)
    t = np.asarray(stamps, float) if stamps is not None else np.arange(len(trial)) / trial.rate_hz
    dt = time_steps(len(trial), None if stamps is not None else trial.rate_hz, stamps)
    mag = trial.mag if est.uses_mag and np.isfinite(trial.mag).any() else None
    q = est.run(trial.gyr, trial.acc, mag, dt=dt)
    _, events = scan(t, trial.acc, q, mag)
    # the reference is q_up←sensor (BROAD: ENU, DIDO: z up): its vertical against ours
    up = np.broadcast_to([0.0, 0.0, 1.0], (len(t), 3))
    ref_up = quat_rotate_array(quat_conj_array(trial.ref), up)
    our_up = quat_rotate_array(quat_conj_array(q), -up)
    error = np.degrees(np.arccos(np.clip(np.sum(ref_up * our_up, axis=1), -1.0, 1.0)))
    return events, t, error


def _check_no_false_alarm(source, data_dir) -> dict[str, int]:
    counts = {}
    for trial_name in source.list_trials(data_dir):
        trial = source.load_trial(data_dir, trial_name)
        for name in ("robust", "ekf"):
            events, t, error = _flags_on(trial, name)
            counts[f"{name} {trial_name}"] = sum(e.diverged for e in events)
            if name == "robust":
                assert events == [], (trial_name, [(e.t_s - t[0], e.verdict.test_ratio) for e in events])
            for e in events:  # the EKF's flags are its real tilt errors, not false alarms
                if e.diverged:
                    window = (t > e.t_s - 3.0) & (t <= e.t_s)
                    assert np.nanmax(error[window]) > 10.0, (trial_name, name, e.t_s - t[0])
    return counts


@pytest.mark.timeout(600)
def test_no_false_alarm_on_broad(broad_dir):
    from ahrs_service.evaluation import broad

    counts = _check_no_false_alarm(broad, broad_dir)
    assert len(counts) == 24


@pytest.mark.timeout(600)
def test_no_false_alarm_on_dido():
    from ahrs_service.evaluation import dido

    reason = dido.missing_reason(dido.default_dir())
    if reason:
        pytest.skip(reason)
    counts = _check_no_false_alarm(dido, dido.default_dir())
    assert len(counts) == 16 and sum(counts.values()) == 0, counts


# ---------------------------------------------------------------------------------- the service
def _glitch_log(directory: Path, seconds: float = 22.0, rate_hz: float = 200.0) -> Path:
    """A recorded flight of a resting, level IMU whose gyroscope glitches twice: +30° about x
    over 0.1 s at 3 s, −30° at 10 s. An estimator that trusts its gyroscope is 30° off in roll
    between the two while the accelerometer says level."""
    from ahrs_service.logs.writer import FlightLogWriter

    rng = np.random.default_rng(5)
    n = int(seconds * rate_hz)
    t = np.arange(n) / rate_hz
    rows = np.empty((n, 10))
    rows[:, 0:3] = rng.normal(0.0, 0.002, (n, 3))
    glitch = math.radians(30.0) / 0.1
    rows[(t >= 3.0) & (t < 3.1), 0] += glitch
    rows[(t >= 10.0) & (t < 10.1), 0] -= glitch
    rows[:, 3:6] = np.array([0.0, 0.0, -G]) + rng.normal(0.0, 0.05, (n, 3))
    rows[:, 6:9] = FIELD_NED + rng.normal(0.0, 0.3, (n, 3))
    rows[:, 9] = 1.0 / rate_hz
    t_ns = (1_000_000_000 + np.round(t * 1e9)).astype(np.int64)
    writer = FlightLogWriter(directory)
    writer.write_config(int(t_ns[0]), {"estimator": {"name": "madgwick", "params": {}}})
    flags = np.full(n, GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW)
    writer.write_block(t_ns, rows, flags, q=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), estimator="madgwick",
                       truth_q=np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))
    writer.close()
    return writer.files[0]


@pytest.mark.timeout(180)
def test_the_service_reports_a_divergence_everywhere_and_clears_it(tmp_path, gcs):
    from tests.test_service import RunningService, collect

    conn, port = gcs
    flight = _glitch_log(tmp_path / "recorded")
    cfg = config_mod.validate({
        "source": {"type": "recorded", "recorded_path": str(flight), "recorded_realtime": True},
        # beta 0: the gyroscope alone, so the glitch stays in the estimate until it is undone
        "estimator": {"name": "madgwick", "params": {"beta": 0.0}},
        "rates": {"estimation_hz": 200, "sys_status_hz": 5, "attitude_hz": 1, "attitude_quaternion_hz": 1},
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"], "odometry": {"rate_hz": 5, "rules": "px4"}},
        "log": {"directory": str(tmp_path / "logs"), "diagnostics_hz": 5},
    })
    run = RunningService(cfg, duration_s=60.0)
    svc = run.service
    try:
        msgs = collect(conn, 40.0, until=lambda m: not run.thread.is_alive())
        run.thread.join(30)
    finally:
        run.stop()
    assert svc.source.finished
    texts = [(m.severity, m.text) for m in msgs if m.get_type() == "STATUSTEXT"]
    diverged = [x for x in texts if x[1].startswith("attitude diverged")]
    cleared = [x for x in texts if x[1].startswith("attitude consistent again")]
    assert len(diverged) == 1 and diverged[0][0] == mavlink.MAV_SEVERITY_CRITICAL, texts
    assert len(cleared) == 1 and cleared[0][0] == mavlink.MAV_SEVERITY_INFO, texts
    # SYS_STATUS: the AHRS present and enabled throughout, unhealthy while flagged, healthy around it
    ahrs = mavlink.MAV_SYS_STATUS_AHRS
    sys_status = [m for m in msgs if m.get_type() == "SYS_STATUS"]
    assert all(m.onboard_control_sensors_present & ahrs and m.onboard_control_sensors_enabled & ahrs
               for m in sys_status)
    health = [bool(m.onboard_control_sensors_health & ahrs) for m in sys_status]
    first_bad = health.index(False)
    assert any(health[:first_bad]) and not all(health[first_bad:]) and health[-1], health
    # ODOMETRY: failed with uninformative variances while flagged, good before
    odometry = [m for m in msgs if m.get_type() == "ODOMETRY"]
    failed = [m for m in odometry if m.quality == -1]
    assert failed and all(m.pose_covariance[15] >= DIVERGED_VARIANCE and m.pose_covariance[18] >= DIVERGED_VARIANCE
                          for m in failed)
    assert odometry[0].quality > 0 and odometry[0].pose_covariance[15] < 0.1
    assert odometry[-1].quality > 0
    # the flight log: the flag in /attitude diagnostics, both events on /log
    (path,) = (tmp_path / "logs").glob("*.mcap")
    diagnostics, logs = [], []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/attitude", "/log"]):
            data = json.loads(message.data)
            if channel.topic == "/log":
                logs.append(data["message"])
            elif data.get("diagnostics"):
                diagnostics.append(data["diagnostics"])
    flags = [d["diverged"] for d in diagnostics]
    assert not flags[0] and True in flags and not flags[-1], flags
    during = [d for d in diagnostics if d["diverged"]]
    assert max(d["tilt_innovation_deg"] for d in during) > 20.0  # the 30° glitch, seen through the window
    known = [d["tilt_innovation_deg"] for d in diagnostics if d["tilt_innovation_deg"] is not None]
    assert known[0] < 2.0 and known[-1] < 2.0  # level before the glitch and after it is undone
    assert diagnostics[-1]["divergence_flags"] == 1
    assert sum(t.startswith("attitude diverged") for t in logs) == 1
    assert sum(t.startswith("attitude consistent again") for t in logs) == 1
    # the summary line
    summary = svc.divergence_summary()
    assert summary.startswith("attitude: diverged 1 time (") and summary.endswith("s in all), consistent at the end")
    diverged_s = float(summary.split("(")[1].split(" s in all")[0])
    assert 3.0 < diverged_s < 12.0, summary
