"""Beside an autopilot: the autopilot link, its IMU as a source, the attitude monitor.

A simulated flight controller (tests/sim_autopilot.py) streams a BROAD recording over real
UDP sockets on 127.0.0.1 and over a pseudo-terminal pair, to the real service.
"""

from __future__ import annotations

import math
import socket
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from ahrs_service import config as config_mod
from ahrs_service import estimators
from ahrs_service.attitude_monitor import ATTITUDE_REQUEST_HZ, AttitudeMonitor, Disagreement, EstimateHistory
from ahrs_service.core.quaternion import quat_from_euler, quat_mul
from ahrs_service.estimators import SAMPLE_ROW
from ahrs_service.logs.reader import MessageSource, read_log
from ahrs_service.logs.schemas import decode
from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink, RemoteTimeline
from ahrs_service.protocols.mavlink.imu_source import MavlinkImuSource, decode_scaled
from ahrs_service.service import Service
from tests.test_service import make_gcs

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim_autopilot import PtyTransport, Recording, SimAutopilot, UdpTransport  # noqa: E402

_R = SAMPLE_ROW.slices
ESTIMATOR = "madgwick"
#: both filters of these tests at the papers' gains, fixed: the monitor's bounds compare two
#: filters, and the tuned defaults of the estimators must not move them
PRESET = "paper"
SECONDS = 3.0


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


@pytest.fixture(scope="module")
def broad_segment(broad_dir):
    """SECONDS of BROAD trial 07 (fast rotation) as the autopilot streams it: float32 values,
    whole-µs times 3500 µs apart (the trial's own 285.714 Hz), and the autopilot's own
    attitude: another filter's estimate over the same samples."""
    from ahrs_service.evaluation.broad_import import load_broad

    s = load_broad(broad_dir / "07_undisturbed_fast_rotation_B.hdf5", 10.0, SECONDS)
    period_us = int(round(1e6 / s.rate_hz))
    assert period_us == 3500
    rows = s.rows
    rec = Recording.uniform(rows[:, _R.gyr], rows[:, _R.acc], rows[:, _R.mag], np.tile([1.0, 0, 0, 0], (len(rows), 1)),
                            period_us)
    gyr, acc, mag = rec.wire_values()
    rec.q = estimators.run("mahony_passive", gyr, acc, mag, rate_hz=1e6 / period_us, preset=PRESET)
    return rec


def reference(rec: Recording, keep: np.ndarray | None = None) -> np.ndarray:
    """The estimate straight from the recording rounded as on the wire (float32 values,
    whole-µs times), by estimators.run."""
    gyr, acc, mag = rec.wire_values()
    rate_hz = 1e6 / rec.period_us
    # the service integrates (Δt_ns)·1e-9; on this grid that is exactly 1 / rate_hz
    assert float(rec.period_us * 1000) * 1e-9 == 1.0 / rate_hz
    if keep is not None:
        gyr, acc, mag = gyr[keep], acc[keep], mag[keep]
    return estimators.run(ESTIMATOR, gyr, acc, mag, rate_hz=rate_hz, preset=PRESET)


def drain(gcs, out: list, stop: threading.Event) -> None:
    while not stop.is_set():
        m = gcs.recv_match(blocking=True, timeout=0.05)
        if m is not None and m.get_type() != "BAD_DATA":
            out.append(m)


def service_config(tmp_path, connection: str, gcs_port: int, period_us: int, **sections) -> config_mod.Config:
    data = {
        "source": {"type": "mavlink", "mavlink_connection": connection, "mavlink_imu": "highres",
                   "mavlink_imu_hz": 1e6 / period_us},
        "estimator": {"name": ESTIMATOR, "preset": PRESET},
        "rates": {"estimation_hz": 1e6 / period_us, "attitude_hz": 20, "attitude_quaternion_hz": 0},
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{gcs_port}"]},
        "log": {"directory": str(tmp_path / "logs"), "diagnostics_hz": 0},
        "monitor": {"threshold_deg": 5.0, "hold_s": 0.5, "rate_hz": 10.0},
    }
    for name, values in sections.items():
        data.setdefault(name, {}).update(values)
    return config_mod.validate(data)


class Rig:
    """The service on a thread, the simulated autopilot, and a ground station listening."""

    def __init__(self, tmp_path, rec: Recording, transport, connection: str, sections: dict | None = None,
                 **sim_options) -> None:
        self.gcs, gcs_port = make_gcs()
        self.gcs_messages: list = []
        self._stop = threading.Event()
        self._gcs_thread = threading.Thread(target=drain, args=(self.gcs, self.gcs_messages, self._stop), daemon=True)
        self._gcs_thread.start()
        cfg = service_config(tmp_path, connection, gcs_port, rec.period_us, **(sections or {}))
        self.service = Service(cfg, duration_s=60.0)
        self.service.start()
        self.thread = threading.Thread(target=self.service.run, daemon=True)
        self.thread.start()
        self.sim = SimAutopilot(transport, rec, **sim_options).start()
        self.expected = len(rec.rel_us) - len(sim_options.get("drop", ()))

    def run_to_end(self, expected: int | None = None, timeout_s: float = 40.0) -> None:
        """Until the autopilot has sent everything and the service has estimated it (bounded)."""
        assert self.sim.join(timeout_s), "the simulated autopilot did not finish"
        want = self.expected if expected is None else expected
        end = time.monotonic() + 10.0
        while self.service.pipeline.samples < want and time.monotonic() < end:
            time.sleep(0.02)
        time.sleep(0.3)  # the last comparisons and NAMED_VALUE_FLOATs

    def close(self) -> None:
        self.service.request_stop()
        self.thread.join(10)
        self.service.close()
        self.sim.stop()
        self._stop.set()
        self._gcs_thread.join(2)
        self.gcs.close()

    def log(self):
        files = sorted((Path(self.service.cfg.log["directory"])).glob("*.mcap"))
        assert len(files) == 1
        return read_log(files[0])


def _named(messages, name):
    return [m.value for m in messages if m.get_type() == "NAMED_VALUE_FLOAT" and m.name == name]


def test_udp_autopilot_highres_imu_estimates_bit_identical_and_monitor_agrees(tmp_path, broad_segment):
    rec = broad_segment
    port = free_udp_port()
    rig = Rig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}",
              sections={"mavlink": {"odometry": {"rate_hz": 20.0, "rules": "px4"}}})
    try:
        rig.run_to_end()
        svc = rig.service
        link = svc.source.autopilot_link
        # ODOMETRY went to the autopilot on its link, each stamped with the autopilot's own
        # time of the sample it carries the estimate of
        sample_times = set((rig.sim.stream_start_us + rec.rel_us).tolist())
        odometry = rig.sim.stats.odometry_times_us
        assert len(odometry) >= 20 and set(odometry) <= sample_times
        assert link.autopilot is not None and link.autopilot.kind == "px4"
        imu_requests = [r for r in rig.sim.stats.interval_requests if r[0] == mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU]
        assert imu_requests[0] == (mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 3500.0)
        assert svc.pipeline.samples == len(rec.rel_us)
        assert svc.source.diagnostics.lost.total == 0
        # TIMESYNC with the autopilot converged; its clock is ours minus its boot time
        assert link.timesync.synced and rig.sim.stats.timesync_replies >= 5
        # (PX4's gate admits round trips up to 10 ms: ±5 ms of asymmetry at worst on a busy host)
        assert abs(link.timesync.offset_ns + rig.sim.boot_ns) < 5_000_000
        # the samples' times on our clock: the TIMESYNC offset the first samples waited for,
        # held (no slewing, no step), within the deadband of the autopilot's true clock
        assert link.timeline.slewed_ns == 0 and link.timeline.steps == 0
        assert abs(link.timeline.offset_ns - rig.sim.boot_ns) < link.timeline.deadband_ns
        monitor = svc.monitor
        assert monitor.compared > 0.8 * rig.sim.stats.attitudes
        assert monitor.warnings == 0
    finally:
        rig.close()
    log = rig.log()
    q_ref = reference(rec)
    assert log.attitudes.shape == q_ref.shape
    assert np.array_equal(log.attitudes, q_ref)  # bit for bit
    # the samples' times are the autopilot's, 3500 µs apart on our clock
    assert set(np.diff(log.t_ns).tolist()) == {3_500_000}
    # the two filters agree within noise: published and logged, no warning
    diffs = _named(rig.gcs_messages, "ATT_DIFF")
    assert len(diffs) >= 5 and max(diffs) < 5.0
    assert _named(rig.gcs_messages, "ATT_INCL") and _named(rig.gcs_messages, "ATT_HDG")
    assert not [m for m in rig.gcs_messages if m.get_type() == "STATUSTEXT" and "autopilot" in m.text]
    assert log.counts.get("/monitor", 0) == monitor.compared
    assert log.counts.get("/autopilot/attitude", 0) == monitor.compared
    # once a second the link, TIMESYNC's offset and drift in /loop
    loops = [decode(d) for topic, _, _, d in MessageSource(log.path) if topic == "/loop"]
    synced = [m["autopilot"] for m in loops if m["autopilot"]["timesync"]["synced"]]
    assert synced and synced[-1]["autopilot"]["kind"] == "px4" and synced[-1]["link"]["messages"] > 0
    assert abs(synced[-1]["timesync"]["offset_ns"] + rig.sim.boot_ns) < 5_000_000
    assert "drift_ppm" in synced[-1]["timesync"] and synced[-1]["timeline"]["slewed_ns"] == 0
    # a second body for Foxglove's 3-D panel: frame "autopilot" beside "body" in "ned"
    children = [decode(data)["child_frame_id"] for topic, _, _, data in MessageSource(log.path) if topic == "/tf"]
    assert children.count("autopilot") == monitor.compared and "body" in children


def test_pty_serial_autopilot_drops_counted_and_estimate_bit_identical(tmp_path, broad_segment):
    rec = broad_segment
    pty = PtyTransport(tmp_path)
    drop = frozenset({100, 101, 102, 400, 650})  # the autopilot loses these samples
    rig = Rig(tmp_path, rec, pty, pty.url, drop=drop, kind="ardupilot", attitude_offset_deg=10.0)
    try:
        rig.run_to_end()
        svc = rig.service
        assert svc.source.autopilot_link.autopilot.kind == "ardupilot"
        assert svc.pipeline.samples == len(rec.rel_us) - len(drop)
        assert svc.source.diagnostics.lost.gap == len(drop)
        assert svc.source.diagnostics.lost.total == len(drop)
        # the autopilot's attitude is 10° off in heading: the monitor warns once, after hold_s
        assert svc.monitor.warnings == 1 and svc.monitor.warning
        # the held offset came from TIMESYNC and never moved: every spacing is the autopilot's
        timeline = svc.source.autopilot_link.timeline
        assert timeline.slewed_ns == 0 and timeline.steps == 0
        assert 9.0 < svc.monitor.latest.total_deg < 11.0
        assert abs(svc.monitor.latest.heading_deg - 10.0) < 1.0
    finally:
        rig.close()
    log = rig.log()
    keep = np.setdiff1d(np.arange(len(rec.rel_us)), sorted(drop))
    # the samples around a loss keep the autopilot's spacing: the estimator integrates the gap;
    # ArduPilot's field unit in HIGHRES_IMU is its own (drivers/mavlink_imu.py)
    gyr, acc, mag = rec.wire_values("ardupilot")
    dt = np.diff(rec.rel_us[keep] * 1000) * 1e-9
    first_dt = 1.0 / (1e6 / rec.period_us)  # the service's nominal period for the first sample
    q_ref = estimators.create(ESTIMATOR, preset=PRESET).run(gyr[keep], acc[keep], mag[keep], dt=np.concatenate([[first_dt], dt]))
    assert np.array_equal(log.attitudes, q_ref)
    warnings = [m.text for m in rig.gcs_messages if m.get_type() == "STATUSTEXT" and "differs from autopilot" in m.text]
    assert len(warnings) == 1


def test_the_monitor_asks_an_autopilot_that_streams_only_on_request_for_its_attitude(tmp_path, broad_segment):
    """ArduPilot streams a link nothing its MAVn_* rates or a request did not ask for: the
    monitor asks for ATTITUDE_QUATERNION itself, and compares what comes."""
    rec = broad_segment
    port = free_udp_port()
    rig = Rig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}", kind="ardupilot",
              attitude_on_request=True)
    try:
        rig.run_to_end()
        monitor = rig.service.monitor
        attitude_id = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION
        asked = [r for r in rig.sim.stats.interval_requests if r[0] == attitude_id]
        assert asked and asked[0] == (attitude_id, 1e6 / ATTITUDE_REQUEST_HZ)
        assert monitor.stream_requests >= 1
        # the recording lasts about 3.5 s at 10 Hz: most of its attitudes were compared
        assert rig.sim.stats.attitudes >= 20
        assert monitor.compared >= 0.8 * rig.sim.stats.attitudes and monitor.warnings == 0
    finally:
        rig.close()


def test_serial_device_vanishing_and_coming_back(tmp_path, broad_segment):
    rec = broad_segment
    pty = PtyTransport(tmp_path)
    rig = Rig(tmp_path, rec, pty, pty.url, pause=(300, 0.8))
    try:
        rig.run_to_end(expected=0)
        svc = rig.service
        link = svc.source.autopilot_link
        dropped = rig.sim.stats.imu_dropped  # not sent while the device was unplugged
        assert dropped > 100
        n = len(rec.rel_us)
        end = time.monotonic() + 10.0
        while svc.pipeline.samples + svc.source.diagnostics.lost.gap < n and time.monotonic() < end:
            time.sleep(0.02)
        # every sample is estimated or counted lost; the lost ones are those the autopilot did
        # not send plus those it wrote before the device was opened again (opening a serial
        # port discards its input, as on hardware)
        assert svc.pipeline.samples + svc.source.diagnostics.lost.gap == n
        assert svc.source.diagnostics.lost.gap >= dropped
        assert svc.pipeline.samples > 300 + 100  # before the unplugging, and after
        assert link.stats.read_errors >= 1 and link.stats.reopens >= 1
        assert link.stats.losses >= 1 and link.stats.recoveries == 1
        # the stream is asked for again after the link came back
        imu_id = mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU
        assert sum(r[0] == imu_id for r in rig.sim.stats.interval_requests) >= 2
    finally:
        rig.close()
    texts = [m.text for m in rig.gcs_messages if m.get_type() == "STATUSTEXT"]
    assert any(t.startswith("sensor lost") for t in texts) and "sensor back" in texts


def test_udp_silence_is_a_link_loss_and_the_stream_is_requested_again(tmp_path):
    period_us = 5000
    n = 800
    rng = np.random.default_rng(1)
    rec = Recording.uniform(rng.normal(0, 0.05, (n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)),
                            np.tile([20.0, 1.0, 45.0], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), period_us)
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}", silence_s=0.3)
    src = MavlinkImuSource(link, rate_hz=200.0)
    src.open()
    sim = SimAutopilot(UdpTransport(port), rec, pause=(300, 0.8)).start()
    got, carrying = [], 0
    try:
        end = time.monotonic() + 20.0
        while time.monotonic() < end and not (sim.finished.is_set() and len(got) >= n - sim.stats.imu_dropped):
            block = src.read_block()
            if block.lost.total:
                carrying += 1
                assert len(block) and len(got) and block.lost.gap == sim.stats.imu_dropped  # the loss opens a block
            got.extend(block.samples()) if len(block) else time.sleep(0.005)
    finally:
        sim.stop()
        src.close()
    assert len(got) == n - sim.stats.imu_dropped and carrying == 1
    assert src.diagnostics.lost.gap == sim.stats.imu_dropped > 100
    assert link.stats.losses == 1 and link.stats.recoveries == 1 and link.stats.read_errors == 0
    assert len(sim.stats.interval_requests) >= 2  # again after the link came back
    t = np.array([s.t_ns for s in got])
    steps = np.diff(t)
    assert np.all(steps > 0)
    assert np.count_nonzero(steps != period_us * 1000) == 1  # the one gap, the autopilot's length
    assert steps[steps != period_us * 1000][0] == (sim.stats.imu_dropped + 1) * period_us * 1000


def test_scaled_imu_units():
    msg = mavlink2.MAVLink_scaled_imu_message(1234, 0, 0, -1000, 100, -200, 300, 200, 0, 450, 2512)
    r = decode_scaled(msg)
    assert r.remote_us == 1_234_000
    assert np.allclose(r.acc, [0, 0, -9.80665]) and np.allclose(r.gyr, [0.1, -0.2, 0.3])
    assert np.allclose(r.mag, [20.0, 0.0, 45.0]) and r.temperature_c == pytest.approx(25.12)


def test_raw_imu_counts_take_the_configured_scale_and_scaled2_decodes_like_scaled():
    from ahrs_service.protocols.mavlink.imu_source import RawScale, decode_raw, parse_raw_scale

    raw = mavlink2.MAVLink_raw_imu_message(5_000_123, 0, 0, -4096, 100, 0, -100, 300, 0, 0, 0, 0)
    r = decode_raw(raw, RawScale(acc=9.80665 / 4096, gyr=0.001, mag=0.15))  # a 4096 LSB/g part
    assert r.remote_us == 5_000_123
    assert np.allclose(r.acc, [0, 0, -9.80665]) and np.allclose(r.gyr, [0.1, 0, -0.1]) and np.allclose(r.mag, [45, 0, 0])
    # unset keys: ArduPilot's RAW_IMU (= SCALED_IMU units, GCS_MAVLINK::send_raw_imu)
    assert parse_raw_scale({"acc": 0.5}) == RawScale(acc=0.5, gyr=1e-3, mag=0.1)
    with pytest.raises(ValueError, match="source.mavlink_raw_scale.gyro: unknown"):
        parse_raw_scale({"gyro": 1.0})
    two = mavlink2.MAVLink_scaled_imu2_message(1234, 0, 0, -1000, 100, -200, 300, 200, 0, 450, 0)
    r2 = decode_scaled(two)
    assert np.allclose(r2.acc, [0, 0, -9.80665]) and r2.temperature_c is None  # 0: not sent


# ---------------------------------------------------------------------- the monitor on its own


class _FakeLink:
    """What the monitor uses of a link: subscribe, and a timeline."""

    def __init__(self) -> None:
        self.timeline = RemoteTimeline()
        self.timeline.offset_ns = 7_000_000_000  # local = remote + 7 s
        self.sink = None

    def subscribe(self, names, sink, autopilot_only=True):
        self.sink = sink


def _att(time_ms: int, q) -> object:
    return mavlink2.MAVLink_attitude_quaternion_message(time_ms, *map(float, q), 0.0, 0.0, 0.0)


def _run_monitor(offset_deg: float, seconds: float, hold_s: float = 2.0, noise_deg: float = 0.0):
    link = _FakeLink()
    mon = AttitudeMonitor(link, threshold_deg=5.0, hold_s=hold_s)
    rng = np.random.default_rng(3)
    events = []
    yaw_rate = math.radians(30.0)
    for k in range(int(seconds * 200)):  # estimates at 200 Hz: a turn at 30°/s
        t_local = 7_000_000_000 + k * 5_000_000
        mon.add_estimate(t_local, quat_from_euler(0.1, -0.05, yaw_rate * k * 0.005))
        if k % 4 == 2:  # the autopilot's attitude at 50 Hz, between two estimates
            t_ms = (k * 5 + 2)  # 2 ms after estimate k: interpolated
            yaw = yaw_rate * t_ms * 1e-3 + math.radians(offset_deg + rng.normal(0, noise_deg))
            link.sink(_att(t_ms, quat_from_euler(0.1, -0.05, yaw)), 0)
        if k % 20 == 0:
            events += mon.update()[1]
    events += mon.update()[1]
    return mon, events


def test_monitor_warns_after_hold_time_and_not_before():
    mon, events = _run_monitor(10.0, seconds=1.9)  # 10° off, but for less than hold_s
    assert mon.warnings == 0 and mon.compared > 80
    assert mon.latest.total_deg == pytest.approx(10.0, abs=1e-6)
    assert mon.latest.heading_deg == pytest.approx(10.0, abs=1e-6)
    assert mon.latest.inclination_deg == pytest.approx(0.0, abs=1e-6)
    mon, events = _run_monitor(10.0, seconds=3.0)
    assert mon.warnings == 1 and [e.severity for e in events if e.severity == 4] == [4]


def test_monitor_quiet_when_attitudes_agree_within_noise():
    mon, events = _run_monitor(0.0, seconds=5.0, noise_deg=0.5)
    assert mon.warnings == 0 and not events
    assert mon.compared > 200


def test_disagreement_angles():
    q = quat_from_euler(0.2, 0.0, 1.0)  # no pitch: body x is horizontal, so a turn about it tilts "down" fully
    tilted = quat_mul(q, quat_from_euler(math.radians(3.0), 0.0, 0.0))  # 3° about the body x axis
    d = Disagreement.between(0, tilted, q)
    assert d.total_deg == pytest.approx(3.0, abs=1e-9)
    assert d.inclination_deg == pytest.approx(3.0, abs=1e-9)
    wrapped = Disagreement.between(0, quat_from_euler(0, 0, math.radians(179.0)), quat_from_euler(0, 0, math.radians(-179.0)))
    assert wrapped.heading_deg == pytest.approx(-2.0, abs=1e-9)


def test_estimate_history_interpolates_and_refuses_outside():
    h = EstimateHistory(size=8)
    for k in range(10):  # the ring keeps the last 8
        h.add(k * 10, quat_from_euler(0.0, 0.0, 0.1 * k))
    assert h.at(5) is None  # dropped from the ring
    assert h.at(95) is None  # newer than the newest
    # the ring wrapped (70 sits last, 80 first): each side of the seam, and across it
    for when in (55, 75, 85):
        q = h.at(when)
        assert Disagreement.between(0, q, quat_from_euler(0, 0, when / 100)).total_deg == pytest.approx(0.0, abs=1e-9)


def test_estimate_history_takes_blocks_like_single_estimates():
    one, block = EstimateHistory(size=8), EstimateHistory(size=8)
    t = np.arange(13, dtype=np.int64) * 10
    q = np.array([quat_from_euler(0.0, 0.0, 0.1 * k) for k in range(13)])
    for k in range(13):
        one.add(int(t[k]), q[k])
    block.add_many(t[:3], q[:3])
    block.add_many(t[3:], q[3:])  # longer than the ring: the newest 8 stay
    for when in (45, 50, 55, 115, 120):
        assert one.at(when) == block.at(when)
    assert one.at(45) is None and block.n == one.n == 13


def test_remote_timeline_holds_its_offset_within_the_deadband():
    tl = RemoteTimeline(deadband_ns=1_000_000, slew_ppm=100.0, step_ns=50_000_000)
    tl.arrival(1_000, 5_000_000_000 + 1_000_000 + 400_000)  # 400 µs of latency
    assert tl.to_local_ns(1_000) == 5_001_400_000
    tl.arrival(2_000, 5_000_000_000 + 2_000_000 + 100_000)  # a faster arrival: within the deadband
    assert tl.to_local_ns(2_000) == 5_002_400_000  # the held offset: the autopilot's spacing kept
    assert tl.offset_ns == 5_000_400_000
    # the estimate moves to 3 ms earlier: the held offset slews at most 100 ppm of the remote
    # time that passed (100 µs per remote second here) until it is within the deadband again
    moves = []
    for k in range(3, 60):
        tl.arrival(k * 1_000_000, 5_000_000_000 + k * 1_000_000_000 - 3_000_000)
        before = tl.offset_ns
        tl.to_local_ns(k * 1_000_000)
        moves.append(before - tl.offset_ns)
    assert moves[0] <= 100e-6 * (3_000_000_000 - 2_000_000)  # since the mapping at 2 ms
    assert max(moves[1:]) <= 100_000 and min(moves) >= 0
    assert tl.offset_ns - 4_997_000_000 <= 1_000_000  # within the deadband of the estimate
    assert sum(moves) == 5_000_400_000 - tl.offset_ns > 2_000_000
    assert tl.steps == 0
    # a jump beyond step_ns (the autopilot's clock was set) steps at once
    for k in range(70, 75):  # four seconds of arrivals: the older latency floor leaves the window
        tl.arrival(k * 1_000_000, 5_000_000_000 + k * 1_000_000_000 + 200_000_000)
    assert tl.to_local_ns(70_000_000) == 5_000_000_000 + 70_000_000_000 + 200_000_000
    assert tl.steps == 1


def test_config_checks_the_autopilot_keys():
    base = {"source": {"type": "mavlink", "mavlink_connection": "/dev/ttyAMA0,921600"}}
    cfg = config_mod.validate(base)
    assert cfg.source["mavlink_imu"] == "highres" and cfg.monitor["threshold_deg"] == 5.0
    with pytest.raises(config_mod.ConfigError, match=r"^source.mavlink_imu: 'fast' is not one of"):
        config_mod.validate({"source": {"type": "mavlink", "mavlink_imu": "fast"}})
    with pytest.raises(config_mod.ConfigError, match=r"^source.mavlink_raw_scale.acc: -1"):
        config_mod.validate({"source": {"type": "mavlink", "mavlink_raw_scale": {"acc": -1}}})
    with pytest.raises(config_mod.ConfigError, match=r"^source.mavlink_connection"):
        config_mod.validate({"source": {"type": "mavlink", "mavlink_connection": "udpin:127.0.0.1:99999"}})


# ---------------------------------------------------------------------- behind a real MAVProxy


def test_behind_mavproxy_between_a_serial_autopilot_and_a_ground_station(tmp_path, broad_segment):
    """The vehicle's usual set-up: the autopilot on a serial port (a pty pair here), MAVProxy
    on the companion routing it to the service and to a ground station over UDP; the
    service's own telemetry enters MAVProxy on a second link and reaches the ground station."""
    import subprocess

    rec = broad_segment
    script = Path(sys.executable).with_name("mavproxy.py")
    if not script.exists():
        pytest.skip("mavproxy not installed (pip install -e '.[test]')")
    pty = PtyTransport(tmp_path)
    service_in, service_out = free_udp_port(), free_udp_port()
    gcs, gcs_port = make_gcs()
    proxy = subprocess.Popen(
        [sys.executable, str(script), f"--master={pty.url}", f"--master=udpin:127.0.0.1:{service_out}",
         f"--out=udpout:127.0.0.1:{service_in}", f"--out=udpout:127.0.0.1:{gcs_port}", "--daemon",
         "--non-interactive", "--default-modules=link", "--streamrate=-1", "--no-state", "--nodtr"],
        cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    messages: list = []
    stop = threading.Event()
    listener = threading.Thread(target=drain, args=(gcs, messages, stop), daemon=True)
    listener.start()
    svc = thread = sim = None
    try:
        cfg = service_config(tmp_path, f"udpin:127.0.0.1:{service_in}", service_out, rec.period_us,
                             mavlink={"identity": "companion", "system_id": 1, "endpoints": [f"udpout:127.0.0.1:{service_out}"]})
        svc = Service(cfg, duration_s=90.0)
        svc.start()
        thread = threading.Thread(target=svc.run, daemon=True)
        thread.start()
        # a bounded wait for MAVProxy to start (its imports take seconds on a loaded host)
        sim = SimAutopilot(pty, rec, time_limit_s=60.0).start()
        assert sim.join(90.0)
        n = len(rec.rel_us)
        end = time.monotonic() + 10.0
        while svc.pipeline.samples + svc.source.diagnostics.lost.total < n and time.monotonic() < end:
            time.sleep(0.02)
        time.sleep(0.5)
        assert svc.source.autopilot_link.autopilot.kind == "px4"
        # the stream request went through MAVProxy to the autopilot
        assert (mavlink2.MAVLINK_MSG_ID_HIGHRES_IMU, 3500.0) in sim.stats.interval_requests
        assert svc.pipeline.samples + svc.source.diagnostics.lost.total == n
        assert svc.pipeline.samples > 0.9 * n
    finally:
        if svc is not None:
            svc.request_stop()
            thread.join(10)
            svc.close()
        if sim is not None:
            sim.stop()
        proxy.terminate()
        try:
            proxy.wait(10)
        except subprocess.TimeoutExpired:
            proxy.kill()
            proxy.wait(5)
        stop.set()
        listener.join(2)
        gcs.close()
    ours = [m for m in messages if m.get_type() == "ATTITUDE" and m.get_srcComponent() == mavlink2.MAV_COMP_ID_IMU]
    autopilot = [m for m in messages if m.get_type() == "HIGHRES_IMU" and m.get_srcComponent() == 1]
    assert len(ours) >= 10  # the service's ATTITUDE, through MAVProxy
    assert len(autopilot) > 0.5 * len(rec.rel_us)  # the autopilot's own stream, routed beside it
    assert _named(messages, "ATT_DIFF")


def test_link_port_in_use_is_one_clear_error(tmp_path):
    blocker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blocker.bind(("127.0.0.1", 0))
    port = blocker.getsockname()[1]
    try:
        svc = Service(service_config(tmp_path, f"udpin:127.0.0.1:{port}", free_udp_port(), 5000))
        with pytest.raises(OSError, match=rf"cannot open MAVLink endpoint 'udpin:127.0.0.1:{port}'"):
            svc.start()
        svc.close()
    finally:
        blocker.close()


def test_reload_applies_the_monitor_settings(tmp_path):
    port = free_udp_port()
    path = tmp_path / "ahrs.toml"

    def write(threshold: float, enabled: bool = True) -> None:
        path.write_text(f"""
[source]
type = "mavlink"
mavlink_connection = "udpin:127.0.0.1:{port}"
[mavlink]
endpoints = ["udpout:127.0.0.1:{free_udp_port()}"]
[log]
enabled = false
[monitor]
enabled = {str(enabled).lower()}
threshold_deg = {threshold}
""")

    write(5.0)
    svc = Service(config_mod.load(path))
    svc.start()
    try:
        first = svc.monitor
        assert first.threshold_deg == 5.0
        write(12.5)
        svc.reload()
        assert svc.monitor is not first and svc.monitor.threshold_deg == 12.5
        # the autopilot's attitude reaches the new monitor, no longer the replaced one
        ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        sock.sendto(mavlink2.MAVLink_heartbeat_message(2, 12, 0, 0, 4, 3).pack(ap), ("127.0.0.1", port))
        sock.sendto(_att(10, (1.0, 0.0, 0.0, 0.0)).pack(ap), ("127.0.0.1", port))
        sock.close()
        end = time.monotonic() + 5.0
        while svc.monitor.received == 0 and time.monotonic() < end:
            time.sleep(0.01)
        assert svc.monitor.received == 1 and first.received == 0
        write(12.5, enabled=False)
        svc.reload()
        assert svc.monitor is None
    finally:
        svc.close()


def test_scaled_imu_from_a_1khz_recording_at_the_rate_asked_for():
    """SCALED_IMU (mG, mrad/s, mgauss, ms times) asked for at 500 Hz from an autopilot whose
    IMU runs at 1 kHz: it sends every other sample, and the source measures that rate."""
    n, period_us = 2000, 1000
    rng = np.random.default_rng(2)
    gyr = rng.normal(0, 0.5, (n, 3))
    acc = np.array([0.0, 0.0, -9.81]) + rng.normal(0, 0.3, (n, 3))
    rec = Recording.uniform(gyr, acc, np.tile([20.0, 1.0, 45.0], (n, 1)), np.tile([1.0, 0, 0, 0], (n, 1)), period_us)
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    src = MavlinkImuSource(link, message="scaled", rate_hz=500.0)
    src.open()
    sim = SimAutopilot(UdpTransport(port), rec, kind="ardupilot").start()
    got = []
    try:
        end = time.monotonic() + 20.0
        while time.monotonic() < end and len(got) < n // 2:
            block = src.read_block()
            got.extend(block.samples()) if len(block) else time.sleep(0.005)
    finally:
        sim.stop()
        src.close()
    assert sim.stats.interval_requests[0] == (mavlink2.MAVLINK_MSG_ID_SCALED_IMU, 2000.0)
    assert sim.stats.imu_sent["SCALED_IMU"] == n // 2 == len(got)
    assert src.diagnostics.lost.total == 0
    assert set(np.diff([s.t_ns for s in got]).tolist()) == {2_000_000}
    sent = slice(0, n, 2)
    # the wire's integers: mG, mrad/s, mgauss, back in SI
    want_acc = np.round(rec.acc[sent].astype(float) / 9.80665 * 1000) * 9.80665e-3
    want_gyr = np.round(rec.gyr[sent].astype(float) * 1000) * 1e-3
    assert np.allclose([s.acc for s in got], want_acc, rtol=0, atol=1e-12)
    assert np.allclose([s.gyr for s in got], want_gyr, rtol=0, atol=1e-12)
    assert np.allclose([s.mag for s in got], [20.0, 1.0, 45.0], rtol=0, atol=0.05)
    assert got[0].temperature_c == pytest.approx(25.0)


def test_udpout_link_announces_itself_so_a_listening_autopilot_answers():
    """``udpout:`` to an autopilot (or router) that only listens: our HEARTBEAT tells it
    where we are; its stream follows the request."""
    n = 400
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), 5000)
    transport = UdpTransport(free_udp_port())  # nobody there: it hears from us first
    link = AutopilotLink(f"udpout:127.0.0.1:{transport.sock.getsockname()[1]}")
    src = MavlinkImuSource(link, rate_hz=200.0)
    src.open()
    sim = SimAutopilot(transport, rec).start()
    got = 0
    try:
        end = time.monotonic() + 15.0
        while time.monotonic() < end and got < n:
            block = src.read_block()
            got += len(block)
            if not len(block):
                time.sleep(0.005)
    finally:
        sim.stop()
        src.close()
    assert sim.stats.received.get("HEARTBEAT", 0) >= 1
    assert link.autopilot is not None and got == n


def test_autopilot_reboot_starts_a_new_timeline_without_counting_losses():
    """The autopilot restarts (its clock starts again from zero): no samples are counted lost
    for the jump back, the stream is asked for again, our times keep increasing."""
    n, period_us = 300, 5000
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), period_us)
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    src = MavlinkImuSource(link, rate_hz=200.0)
    src.open()
    got = []

    def take(until: int) -> None:
        end = time.monotonic() + 15.0
        while time.monotonic() < end and len(got) < until:
            block = src.read_block()
            got.extend(block.samples()) if len(block) else time.sleep(0.005)

    try:
        first = SimAutopilot(UdpTransport(port), rec).start()
        take(n)
        first.stop()
        rebooted = SimAutopilot(UdpTransport(port), rec).start()  # boots now: its clock is near zero
        take(2 * n)
        rebooted.stop()
    finally:
        src.close()
    assert len(got) == 2 * n
    assert src.timeline_resets == 1 and src.diagnostics.lost.total == 0
    assert rebooted.stats.interval_requests  # asked again: the stream restarted
    t = np.array([s.t_ns for s in got])
    assert np.all(np.diff(t) > 0)


def test_a_refused_stream_request_is_counted_named_and_asked_again():
    n = 50
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), 5000)
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    src = MavlinkImuSource(link, rate_hz=250.0)
    src.open()
    sim = SimAutopilot(UdpTransport(port), rec, refuse_streams=True, time_limit_s=2.5).start()
    try:
        end = time.monotonic() + 10.0
        while time.monotonic() < end and src.refusals < 2:
            assert src.read() is None
            time.sleep(0.01)
        sim.stop()  # no more answers: the counters settle
        time.sleep(0.2)
        assert src.read() is None  # the source's diagnostics are refreshed as it is read
    finally:
        sim.stop()
        src.close()
    assert src.refusals >= 2 and len(sim.stats.interval_requests) >= 2
    assert src.diagnostics.last_error == "autopilot refused HIGHRES_IMU at 250 Hz: MAV_RESULT_DENIED"
    assert src.diagnostics.extra["stream_refusals"] == src.refusals


def test_serial_device_missing_at_start_is_waited_for(tmp_path):
    n = 200
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), 5000)
    pty = PtyTransport(tmp_path)
    pty.unplug()  # not there yet: the flight controller is still booting
    link = AutopilotLink(pty.url, reopen_s=0.2)
    src = MavlinkImuSource(link, rate_hz=200.0)
    src.open()  # no error: a serial device is waited for
    got = 0
    try:
        end = time.monotonic() + 5.0
        while time.monotonic() < end and link.stats.open_failures < 2:
            assert src.read() is None
            time.sleep(0.01)
        assert src.diagnostics.device_lost and "No such file" in src.diagnostics.last_error
        pty.plug()
        sim = SimAutopilot(pty, rec).start()
        end = time.monotonic() + 15.0
        while time.monotonic() < end and got < n:
            block = src.read_block()
            got += len(block)
            if not len(block):
                time.sleep(0.005)
        sim.stop()
    finally:
        src.close()
    assert got == n and link.stats.reopens == 1 and not src.diagnostics.device_lost


def test_live_view_shows_the_autopilot_body_and_the_disagreement(tmp_path, broad_segment):
    """A Foxglove client of the live view gets frame ``autopilot`` on /tf beside ``body`` and
    the comparison on /monitor while a 10°-off autopilot streams."""
    pytest.importorskip("foxglove")
    websockets = pytest.importorskip("websockets")
    import asyncio
    import json

    from ahrs_service.logs.schemas import CHANNELS, validate
    from tests.test_live_view import SUBPROTOCOLS, _messages, _ops
    from tests.test_live_view import free_port as free_tcp_port

    rec = broad_segment
    port = free_udp_port()
    rig = Rig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}", attitude_offset_deg=10.0,
              sections={"live": {"enabled": True, "port": free_tcp_port(), "rate_hz": 20}})

    async def session():
        async with websockets.connect(f"ws://127.0.0.1:{rig.service.live.port}", subprotocols=SUBPROTOCOLS) as ws:
            channels: dict = {}
            while not {"/monitor", "/tf", "/autopilot/attitude"} <= channels.keys():
                for ch in (await _ops(ws, "advertise"))["channels"]:
                    channels[ch["topic"]] = ch
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/monitor"]["id"]}, {"id": 2, "channelId": channels["/tf"]["id"]},
                {"id": 3, "channelId": channels["/autopilot/attitude"]["id"]}]}))
            return await _messages(ws, {1: "/monitor", 2: "/tf", 3: "/autopilot/attitude"}, count=3, seconds=20.0)

    try:
        got = asyncio.run(session())
    finally:
        rig.close()
    for topic in ("/monitor", "/tf", "/autopilot/attitude"):
        assert len(got[topic]) >= 3, topic
        for _, msg in got[topic]:
            assert validate(msg, CHANNELS[topic][1]) == []
    assert {m["child_frame_id"] for _, m in got["/tf"]} == {"body", "autopilot"}
    assert all(8.0 < m["total_deg"] < 12.0 for _, m in got["/monitor"])
    assert {m["estimator"] for _, m in got["/autopilot/attitude"]} == {"autopilot"}


def test_send_time_stamps_are_smoothed_and_their_gaps_counted_exactly():
    """ArduPilot-like SCALED_IMU: each message stamped in whole ms when sent, 0–3 ms after its
    sample. The sample clock puts the samples back on a steady 5 ms line and counts the
    dropped ones exactly, though consecutive stamps step anywhere from 1 to 9 ms (a step
    counted from the previous stamp would call some of them a lost sample)."""
    n, period_us = 1200, 5000
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), period_us)
    drop = frozenset({300, 301, 700, 1000})
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    src = MavlinkImuSource(link, message="scaled", rate_hz=200.0)
    src.open()
    sim = SimAutopilot(UdpTransport(port), rec, kind="ardupilot", drop=drop, send_jitter_us=3000, seed=5).start()
    got = []
    try:
        end = time.monotonic() + 20.0
        while time.monotonic() < end and len(got) < n - len(drop):
            block = src.read_block()
            got.extend(block.samples()) if len(block) else time.sleep(0.005)
    finally:
        sim.stop()
        src.close()
    assert len(got) == n - len(drop)
    assert src.diagnostics.lost.gap == len(drop)
    def steady_steps(times_ms):
        steps = np.diff(times_ms)
        return steps[(steps > 0.5) & (steps < 9.5)]  # not the gaps (10 ms and more, on the line)

    recovered = steady_steps(np.array([s.t_ns for s in got]) / 1e6)
    stamped = steady_steps(np.array(sim.stats.imu_stamps_us) / 1e3)
    assert len(recovered) == len(got) - 1 - 3  # three gaps (one of two samples)
    # the stamps as sent step 1..9 ms; the recovered times stay on the 5 ms line
    assert np.ptp(stamped) >= 6.0 and np.std(stamped) > 0.8
    assert np.ptp(recovered) < np.ptp(stamped) / 5 and np.std(recovered) < np.std(stamped) / 20
    steady = recovered
    assert abs(np.mean(steady) - 5.0) < 0.01
