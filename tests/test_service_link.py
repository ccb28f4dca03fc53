"""The service ↔ MAVLink bridge interface and the loop's schedule, each on its own.

The bridge is driven with a hand-made :class:`ServiceLink` (no service, pipeline, scheduler or
source behind it) and talks to a pymavlink ground station over real UDP on 127.0.0.1; the
loop's :class:`LoopSchedule` runs against a simulated clock.
"""

from __future__ import annotations

import os
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from ahrs_service import config as config_mod  # noqa: E402
from ahrs_service.core.vibration import VibrationMonitor  # noqa: E402
from ahrs_service.mavlink_bridge import LatestEstimate, LinkHealth, MavlinkBridge, ServiceLink  # noqa: E402
from ahrs_service.service import LoopSchedule, PeriodicJob  # noqa: E402

pytestmark = pytest.mark.timeout(60)

Q = (0.8, 0.1, -0.2, 0.5477225575051661)  # a unit quaternion


class FakeService:
    """What a ServiceLink's callables answer, and what the bridge asked of it."""

    def __init__(self) -> None:
        self.samples = 0
        self.params = {"beta": 0.1}
        self.declination = 2.0
        self.calls: list[tuple] = []

    def latest(self) -> LatestEstimate | None:
        if self.samples == 0:
            return None
        return LatestEstimate(self.samples, 1_000_000 * self.samples, Q, (0.01, 0.02, 0.03), (0.0, 0.0, 0.0),
                              (0.0, 0.0, -9.8), (20.0, 0.0, 45.0), True, 25.0, True, True, False, 1, 0.0)

    def health(self) -> LinkHealth:
        self.calls.append(("health",))
        return LinkHealth(True, True, True, True, overruns=3, load_percent=12.5, comm_errors=4, sensor_faults=0,
                          lost_samples=17)

    def set_param(self, name: str, value: float) -> float:
        self.calls.append(("set", name, value))
        self.params[name] = value
        return value

    def link(self) -> ServiceLink:
        return ServiceLink(
            boot_ns=0, estimator="madgwick", param_names=["beta"], latest=self.latest, health=self.health,
            get_param=lambda n: self.params[n], set_param=self.set_param,
            get_declination=lambda: self.declination, set_declination=lambda d: self.calls.append(("decl", d)),
            loop_rate_hz=lambda: 200.0,
            calibrate_gyro=lambda: (self.calls.append(("gyro",)), (False, "gyro calibration refused: moving"))[1],
            start_calibration=lambda kind: (self.calls.append(("cal", kind)), (True, f"{kind} cal started"))[1],
            vibration=VibrationMonitor().levels, attitude_variance=lambda: None,
        )


def _until(bridge: MavlinkBridge, gcs, wanted, ticks: int = 4000):
    """Ticks the bridge (5 ms of its clock a tick) until the ground station got ``wanted``."""
    for _ in range(ticks):
        bridge.tick(time.monotonic_ns())
        m = gcs.recv_match(blocking=True, timeout=0.002)
        if m is not None and m.get_type() != "BAD_DATA" and wanted(m):
            return m
    return None


def test_the_bridge_publishes_and_commands_through_the_service_link_alone():
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=255, srcComponent=190)
    port = gcs.port.getsockname()[1]
    cfg = config_mod.validate({
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"]},
        "rates": {"estimation_hz": 200, "attitude_quaternion_hz": 50, "sys_status_hz": 5},
    })
    fake = FakeService()
    bridge = MavlinkBridge(fake.link(), cfg, io_period_ns=5_000_000)
    try:
        assert _until(bridge, gcs, lambda m: m.get_type() == "HEARTBEAT") is not None
        fake.samples = 10  # the first estimate
        att = _until(bridge, gcs, lambda m: m.get_type() == "ATTITUDE_QUATERNION")
        assert att is not None
        assert [att.q1, att.q2, att.q3, att.q4] == pytest.approx(Q, abs=1e-7)
        assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx((0.01, 0.02, 0.03), abs=1e-7)
        st = _until(bridge, gcs, lambda m: m.get_type() == "SYS_STATUS")
        assert st.errors_count3 == 17 and st.errors_comm == 4  # the link's loss and bus-error counters

        gcs.mav.param_set_send(1, 1, b"EST_BETA", 0.25, mavlink2.MAV_PARAM_TYPE_REAL32)
        ack = _until(bridge, gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "EST_BETA")
        assert ack.param_value == pytest.approx(0.25) and ("set", "beta", pytest.approx(0.25)) in fake.calls

        gcs.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = _until(bridge, gcs, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack.result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED and ("gyro",) in fake.calls
        gcs.mav.param_request_read_send(1, 1, b"LOOP_RATE_HZ", -1)
        rate = _until(bridge, gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "LOOP_RATE_HZ")
        assert rate.param_value == pytest.approx(200.0)
    finally:
        bridge.close()
        gcs.close()


def test_the_full_snapshot_is_built_only_when_a_stream_other_than_the_attitude_is_due():
    """ATTITUDE + ATTITUDE_QUATERNION at 100 Hz, HEARTBEAT and SYS_STATUS at 1 Hz, VIBRATION
    at 2 Hz, over 2 s of the bridge's clock: the health snapshot is asked for at those slow
    streams' times alone (not at each of the 200 attitude publishes), and every ATTITUDE
    carries the link's attitude."""
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=255, srcComponent=190)
    port = gcs.port.getsockname()[1]
    cfg = config_mod.validate({
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"]},
        "rates": {"estimation_hz": 200, "attitude_hz": 100, "attitude_quaternion_hz": 100, "heartbeat_hz": 1,
                  "sys_status_hz": 1, "vibration_hz": 2},
    })
    fake = FakeService()
    fake.samples = 10
    bridge = MavlinkBridge(fake.link(), cfg, io_period_ns=5_000_000)
    got = []
    try:
        start = time.monotonic_ns()
        for k in range(400):  # 2 s of 5 ms ticks
            fake.samples += 1  # a new estimate at every tick: the streams stay fresh
            bridge.tick(start + k * 5_000_000)
            if k % 20 == 0:
                got += [m for m in iter(gcs.recv_msg, None) if m.get_type() != "BAD_DATA"]
        end = time.monotonic() + 1.0
        while time.monotonic() < end:
            m = gcs.recv_match(blocking=True, timeout=0.05)
            if m is None:
                break
            got.append(m)
    finally:
        bridge.close()
        gcs.close()
    attitudes = [m for m in got if m.get_type() == "ATTITUDE_QUATERNION"]
    assert len(attitudes) == 200
    assert all([m.q1, m.q2, m.q3, m.q4] == pytest.approx(Q, abs=1e-7) for m in attitudes)
    health = fake.calls.count(("health",))
    # HEARTBEAT at 0 and 1 s, SYS_STATUS the same, VIBRATION at 0, 0.5, 1, 1.5 s: 4 publishes
    # (the first three streams share them) — never the 200 attitude-only ones
    assert 4 <= health <= 6, health
    assert len([m for m in got if m.get_type() == "SYS_STATUS"]) == 2


def test_the_loop_schedule_runs_each_named_job_on_its_period():
    runs: list[tuple[str, int]] = []
    ms = 1_000_000

    def job(name: str):
        return lambda now: runs.append((name, now))

    schedule = LoopSchedule([
        PeriodicJob("publish", 5 * ms, job("publish"), keep_phase=True),
        PeriodicJob("off", 0, job("off")),
        PeriodicJob("housekeeping", 1000 * ms, job("housekeeping")),
    ], now_ns=0)
    assert schedule.names() == ["publish", "housekeeping"]  # a zero period is no job
    # ticks every 1 ms of a simulated clock, one of them 12 ms late
    now = 0
    for _ in range(30):
        schedule.run_due(now)
        now += 13 * ms if now == 10 * ms else ms
    publish = [t // ms for name, t in runs if name == "publish"]
    # on phase (0, 5, 10 …); after the late tick one run, then the schedule from there
    assert publish == [0, 5, 10, 23, 28, 33, 38]
    assert [t for name, t in runs if name == "housekeeping"] == [0]
    assert runs[0] == ("publish", 0) and runs[1] == ("housekeeping", 0)  # in the order given


def test_without_new_estimates_the_accelerometer_is_unhealthy_like_the_gyroscope():
    """Issue 14 re-probe: an autopilot (source.type = "mavlink") that stops its HIGHRES_IMU
    stream and keeps beating gave SYS_STATUS gyro unhealthy but accelerometer healthy, though
    neither arrived: both come in the same message. (A board that loses its gyroscope already
    marked both, the service's health() counting it as an IMU loss.)"""
    from ahrs_service.mavlink_bridge import STALE_NS

    cfg = config_mod.validate({"mavlink": {"endpoints": ["udpout:127.0.0.1:15598"]}})
    fake = FakeService()
    bridge = MavlinkBridge(fake.link(), cfg, io_period_ns=5_000_000)
    try:
        fake.samples, now = 10, 10**12
        t = bridge.telemetry(now, fake.latest())
        assert t.gyro.healthy and t.accel.healthy and t.ahrs_healthy
        t = bridge.telemetry(now + STALE_NS + 1, fake.latest())  # no sample estimated since
        assert not t.gyro.healthy and not t.accel.healthy and not t.ahrs_healthy
        fake.samples += 1  # the stream is back
        t = bridge.telemetry(now + STALE_NS + 2, fake.latest())
        assert t.gyro.healthy and t.accel.healthy and t.ahrs_healthy
    finally:
        bridge.close()


def test_a_job_that_raises_is_counted_and_the_others_and_later_runs_go_on():
    ms = 1_000_000
    runs: list[str] = []
    failed: list[tuple[str, int, str]] = []

    def broken(now: int) -> None:
        runs.append("broken")
        raise ZeroDivisionError("a hostile quaternion")

    schedule = LoopSchedule([
        PeriodicJob("monitor", ms, broken),
        PeriodicJob("publish", ms, lambda now: runs.append("publish")),
    ], now_ns=0, on_error=lambda job, exc: failed.append((job.name, job.failures, type(exc).__name__)))
    for t in range(5):
        schedule.run_due(t * ms)
    assert runs == ["broken", "publish"] * 5  # every tick: the failing job again, the next one still
    assert failed == [("monitor", n, "ZeroDivisionError") for n in range(1, 6)]
    assert schedule.jobs[0].failures == 5 and schedule.jobs[1].failures == 0

