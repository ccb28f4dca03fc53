"""ODOMETRY (#331) out: a real pymavlink peer over UDP on 127.0.0.1 decodes what the sender
builds under the PX4 and the ArduPilot rules (frames, quaternion, covariance indices, time),
at the configured rate against a simulated clock; reset_counter on heading jumps; time_usec in
the peer's clock after TIMESYNC; and the running service's ODOMETRY stream."""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2
from timesync_peer import ClockPeer, link_to, sync

from ahrs_service.core.quaternion import quat_from_euler
from ahrs_service.protocols.mavlink.attitude import encode_attitude_quaternion
from ahrs_service.protocols.mavlink.odometry import (
    ARDUPILOT,
    COV_PITCH,
    COV_ROLL,
    COV_X,
    COV_YAW,
    POSITION_VARIANCE_UNKNOWN,
    PX4,
    YAW_VARIANCE_UNINFORMATIVE,
    AttitudeEstimate,
    OdometrySender,
    quality_of,
)
from ahrs_service.protocols.mavlink.telemetry import Telemetry
from ahrs_service.protocols.mavlink.timesync import TimeSync

pytestmark = pytest.mark.timeout(90)
M = mavlink2


def wait_for(peer: ClockPeer, name: str, n: int, seconds: float = 10.0) -> list:
    end = time.monotonic() + seconds
    while time.monotonic() < end and len(peer.messages(name)) < n:
        time.sleep(0.01)
    return peer.messages(name)


def estimate(t_ns: int, yaw_deg: float = 30.0, rate=(0.01, -0.02, 0.0), yaw_var=math.radians(4) ** 2, **kw) -> AttitudeEstimate:
    q = quat_from_euler(math.radians(5.0), math.radians(-3.0), math.radians(yaw_deg))
    return AttitudeEstimate(t_ns, q, rate, math.radians(1.5) ** 2, math.radians(1.6) ** 2, yaw_var, **kw)


@pytest.fixture
def peer():
    p = ClockPeer(offset_s=123.456, drift_ppm=50.0)
    yield p
    p.close()


@pytest.mark.parametrize("rules", [PX4, ARDUPILOT], ids=["px4", "ardupilot"])
def test_odometry_fields_and_rate_decoded_by_a_udp_peer(peer, rules):
    conn = link_to(peer)
    try:
        sender = OdometrySender(conn.mav.send, rate_hz=30.0, rules=rules)
        start = 5_000_000_000
        sent_t = []
        for i in range(400):  # 2 s of a 200 Hz loop, simulated clock
            now = start + i * 5_000_000
            if sender.tick(now, estimate(now)):
                sent_t.append(now)
        # the absolute schedule: one message per 1/30 s slot, starting at the first tick
        assert len(sent_t) == 60 and sender.stats.sent == 60
        slots = np.round((np.array(sent_t) - start) * 30 / 1e9)
        assert np.array_equal(slots, np.arange(60))
        got = wait_for(peer, "ODOMETRY", 60)
    finally:
        conn.close()
    assert len(got) == 60
    m = got[0][1]
    est = estimate(sent_t[0])
    # the quaternion is the ATTITUDE_QUATERNION's, float32 for float32
    aq = encode_attitude_quaternion(Telemetry.from_quaternion(0, est.q))
    assert list(m.q) == [np.float32(v) for v in (aq.q1, aq.q2, aq.q3, aq.q4)]
    assert m.child_frame_id == M.MAV_FRAME_BODY_FRD
    assert m.estimator_type == M.MAV_ESTIMATOR_TYPE_VISION
    assert m.time_usec == sent_t[0] // 1000  # no TIMESYNC: our monotonic µs
    cov = np.array(m.pose_covariance)
    assert cov[COV_ROLL] == pytest.approx(math.radians(1.5) ** 2, rel=1e-6)
    assert cov[COV_PITCH] == pytest.approx(math.radians(1.6) ** 2, rel=1e-6)
    assert cov[COV_YAW] == pytest.approx(math.radians(4.0) ** 2, rel=1e-6)
    assert cov[COV_X] == POSITION_VARIANCE_UNKNOWN and np.isfinite(cov[COV_X])  # ArduPilot reads [0]
    assert m.quality == quality_of(est) == 50  # σ_yaw 4° against the 2° reference
    assert m.reset_counter == 0
    if rules is PX4:
        assert m.frame_id == M.MAV_FRAME_LOCAL_NED  # heading observed: north-referenced
        assert all(math.isnan(v) for v in (m.x, m.y, m.z, m.vx, m.vy, m.vz))
        assert (m.rollspeed, m.pitchspeed, m.yawspeed) == pytest.approx((0.01, -0.02, 0.0), abs=1e-7)
        assert math.isnan(m.velocity_covariance[0])
    else:
        assert m.frame_id == M.MAV_FRAME_LOCAL_FRD  # the only frames its handler takes
        assert (m.x, m.y, m.z, m.vx, m.vy, m.vz) == (0.0,) * 6
        assert np.isfinite(m.pose_covariance).all() and np.isfinite(m.velocity_covariance).all()
        assert all(math.isnan(v) for v in (m.rollspeed, m.pitchspeed, m.yawspeed))


def test_unknown_heading_and_failed_health():
    msgs = []
    px4 = OdometrySender(msgs.append, rate_hz=30.0, rules=PX4)
    ap = OdometrySender(msgs.append, rate_hz=30.0, rules=ARDUPILOT)
    est = estimate(0, yaw_var=float("nan"), healthy=False)
    a, b = px4.encode(est), ap.encode(est)
    assert a.frame_id == M.MAV_FRAME_LOCAL_FRD and math.isnan(a.pose_covariance[COV_YAW])  # PX4: NaN = unknown
    assert b.pose_covariance[COV_YAW] == YAW_VARIANCE_UNINFORMATIVE  # ArduPilot's ∛ would carry a NaN on
    assert a.quality == b.quality == -1  # failed, as the message defines it
    with pytest.raises(ValueError, match="mavlink.odometry.rate_hz"):
        OdometrySender(msgs.append, rate_hz=0.5)


def test_reset_counter_bumps_on_a_heading_jump_not_on_a_turn():
    sender = OdometrySender(lambda m: None, rate_hz=50.0, rules=PX4)
    period = 20_000_000
    counters = []
    yaw = 0.0
    r = math.radians(200.0)  # a fast turn the gyro explains
    for k in range(50):
        counters.append(sender.encode(estimate(k * period, yaw_deg=yaw, rate=(0.0, 0.0, r))).reset_counter)
        yaw += math.degrees(r) * period * 1e-9
    assert counters == [0] * 50
    # the heading jumps by 30° with no rate behind it (a new field reference): one bump
    t = 50 * period
    assert sender.encode(estimate(t, yaw_deg=yaw + 30.0, rate=(0.0, 0.0, r))).reset_counter == 1
    yaw += 30.0 + math.degrees(r) * period * 1e-9
    assert sender.encode(estimate(t + period, yaw_deg=yaw, rate=(0.0, 0.0, r))).reset_counter == 1
    # the caller's epoch (re-initialisation, a declination change) bumps it as well
    yaw += math.degrees(r) * period * 1e-9
    assert sender.encode(estimate(t + 2 * period, yaw_deg=yaw, rate=(0.0, 0.0, r), epoch=1)).reset_counter == 2
    assert sender.stats.resets == 2


def test_time_usec_is_in_the_autopilot_clock_after_timesync(peer):
    conn = link_to(peer)
    ts = TimeSync()
    try:
        sync(conn, ts)
        assert ts.synced
        sender = OdometrySender(conn.mav.send, rate_hz=30.0, rules=PX4, timesync=ts)
        stamps = []
        for k in range(5):
            t = time.monotonic_ns()
            assert sender.tick(t + k * 40_000_000, estimate(t))
            stamps.append(t)
        got = wait_for(peer, "ODOMETRY", 5)
    finally:
        conn.close()
    assert len(got) == 5 and sender.stats.not_synced == 0
    for t, (_, m) in zip(stamps, got):
        # the sample's time in the peer's clock (offset +123.456 s, 50 ppm fast), within 2 ms
        assert abs(m.time_usec - peer.clock_ns(t) // 1000) <= 2000


@pytest.mark.timeout(300)  # the first run compiles the default estimator's kernels
def test_the_service_streams_odometry_with_its_estimate(tmp_path):
    from test_service import RunningService, collect, make_gcs, service_config

    from ahrs_service.logs.reader import read_log

    conn, port = make_gcs()
    run = RunningService(service_config(tmp_path, port, mavlink={"odometry": {"rate_hz": 30, "rules": "px4"}}))
    try:
        msgs = collect(conn, 4.0)
    finally:
        run.stop()
        conn.close()
    odo = [m for m in msgs if m.get_type() == "ODOMETRY"]
    assert len(odo) >= 10
    assert run.service.mavlink.odometry.stats.sent >= len(odo)
    log = read_log(run.service.log_writer.files[0])
    q = np.array([m.q for m in odo])
    distance = np.abs(q[:, None, :] - log.attitudes[None, :, :]).max(axis=2)
    assert distance.min(axis=1).max() < 1e-7  # each is the estimate of a logged sample
    for m in odo[3:]:
        assert m.frame_id == M.MAV_FRAME_LOCAL_NED and m.child_frame_id == M.MAV_FRAME_BODY_FRD
        cov = np.array(m.pose_covariance)
        assert np.isfinite(cov[[COV_ROLL, COV_PITCH, COV_YAW]]).all() and (cov[[COV_ROLL, COV_PITCH, COV_YAW]] > 0).all()
        assert m.quality >= 1


@pytest.mark.parametrize("extra, warned", [
    ({}, True),
    ({"estimator": {"declination_deg": 12.7}}, False),
    ({"location": {"latitude_deg": -35.36, "longitude_deg": 149.17}}, False),
])
def test_a_magnetic_heading_sent_as_odometry_is_warned_about(tmp_path, caplog, extra, warned):
    from test_service import service_config

    from ahrs_service.service import Service

    cfg = service_config(tmp_path, 14550, mavlink={"odometry": {"rate_hz": 30, "rules": "ardupilot"}}, **extra)
    service = Service(cfg)
    with caplog.at_level(logging.WARNING, logger="ahrs_service"):
        service.declination_deg(cfg)
    said = [r.getMessage() for r in caplog.records if "declination 0" in r.getMessage()]
    assert len(said) == (1 if warned else 0), said
    if warned:
        assert "[location]" in said[0] and "estimator.declination_deg" in said[0]
