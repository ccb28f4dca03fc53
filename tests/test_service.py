"""The service end to end: simulated GY-80 → estimator → MAVLink over real UDP → pymavlink GCS.

The service runs in a background thread of this process (its real scheduler, real sockets,
real MCAP writer); the ground station is a pymavlink connection on 127.0.0.1.
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from ahrs_service import config as config_mod  # noqa: E402
from ahrs_service import estimators  # noqa: E402
from ahrs_service.calibration import live as live_mod  # noqa: E402
from ahrs_service.calibration.magnetometer import MagCalibrationResult  # noqa: E402
from ahrs_service.calibration.storage import calibration_from_config_dict  # noqa: E402
from ahrs_service.core.quaternion import (  # noqa: E402
    euler_from_quat_array,
    quat_angle_array,
    quat_conj_array,
    quat_mul_array,
    quat_rotate_array,
)
from ahrs_service.logs.reader import read_log  # noqa: E402
from ahrs_service.service import Service  # noqa: E402

pytestmark = pytest.mark.timeout(120)
KEY_HEX = "a5" * 32
G = 9.80665  # m/s², the simulator's gravity


def make_gcs():
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=255, srcComponent=190)
    gcs.mav.robust_parsing = True
    return gcs, gcs.port.getsockname()[1]


def collect(gcs, seconds: float, until=None) -> list:
    """Messages received for at most ``seconds`` (or until ``until(msg)`` is true)."""
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = gcs.recv_match(blocking=True, timeout=0.05)
        if m is None or m.get_type() == "BAD_DATA":
            continue
        out.append(m)
        if until is not None and until(m):
            break
    return out


class RunningService:
    """A Service on a background thread for the duration of a test."""

    def __init__(self, cfg: config_mod.Config, duration_s: float = 30.0):
        self.service = Service(cfg, duration_s=duration_s)
        self.service.start()
        self.thread = threading.Thread(target=self.service.run, daemon=True)
        self.thread.start()

    def stop(self) -> None:
        self.service.request_stop()
        self.thread.join(10)
        self.service.close()


def assert_stream_on_schedule(t_ms, hz: float) -> None:
    """Messages of a stream scheduled at ``hz``, judged by their own timestamps (time_boot_ms).

    A stream sends at most one message per slot of its schedule, each before the next slot
    begins, so n messages span more than (n − 2) periods: a stream any faster than ``hz``,
    or one that bursts to catch up, fails. How close to ``hz`` it comes is the machine's
    business: a loop that is starved (a loaded CI host, a CPU quota) skips slots. The
    schedule itself is checked exactly by ``test_mavlink``, against a simulated clock."""
    t_ms = np.asarray(t_ms, dtype=float)
    assert len(t_ms) >= 10 and np.all(np.diff(t_ms) > 0)
    assert len(t_ms) < (t_ms[-1] - t_ms[0]) * hz / 1e3 + 2


def service_config(tmp_path, port: int, **sections) -> config_mod.Config:
    data = {
        # ideal sensor models: the register devices still quantise, nothing else
        "source": {"type": "simulated_i2c", "board": "gy80", "profile": "validation", "sensor_errors": False},
        "rates": {"estimation_hz": 200, "attitude_hz": 20, "attitude_quaternion_hz": 25, "heartbeat_hz": 1},
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"]},
        "log": {"directory": str(tmp_path / "logs")},
    }
    for name, values in sections.items():
        data.setdefault(name, {}).update(values)
    return config_mod.validate(data)


def test_streams_publish_the_estimate_and_the_sensor_axes_match_truth(tmp_path, gcs):
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port))
    try:
        msgs = collect(conn, 6.0)
    finally:
        run.stop()
    by_type: dict[str, list] = {}
    for m in msgs:
        by_type.setdefault(m.get_type(), []).append(m)
    assert {"HEARTBEAT", "ATTITUDE", "ATTITUDE_QUATERNION", "SYS_STATUS"} <= set(by_type)
    for name, hz in (("ATTITUDE", 20), ("ATTITUDE_QUATERNION", 25)):
        assert run.service.mavlink.component.rates[name] == hz  # the [rates] section, in force
        assert_stream_on_schedule([m.time_boot_ms for m in by_type[name]], hz)
    hb = by_type["HEARTBEAT"][0]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)

    log = read_log(run.service.log_writer.files[0])
    assert log.truth is not None and log.damage is None

    # each ATTITUDE_QUATERNION is the estimate of a recorded sample, changed by nothing but the
    # message's float32
    published = np.array([[m.q1, m.q2, m.q3, m.q4] for m in by_type["ATTITUDE_QUATERNION"]])
    distance = np.abs(published[:, None, :] - log.attitudes[None, :, :]).max(axis=2)
    assert len(published) >= 10 and distance.min(axis=1).max() < 1e-7
    assert np.abs(np.linalg.norm(published, axis=1) - 1).max() < 1e-6

    # The sensors' axes and units through the real drivers and the pipeline, against the
    # simulator's truth in the log, where the IMU holds still: there neither lost samples nor
    # the order in which the parts are read can change a reading. (A starved loop loses
    # samples, as a sensor read without its FIFO does; how well the estimator tracks motion
    # from the samples it gets is tested deterministically: test_i2c_sim, test_robust.)
    rows, truth, t_s = log.rows, log.truth, (log.t_ns - log.t_ns[0]) * 1e-9
    moved = np.concatenate([[0], np.cumsum(np.any(truth[1:] != truth[:-1], axis=1))])
    # still: the same truth from a sample at least 50 ms before to the next sample
    since = np.maximum(np.searchsorted(t_s, t_s - 0.05, side="right") - 1, 0)
    still = np.append(moved[1:] == moved[since[:-1]], False) & (t_s >= 0.05)
    assert np.ptp(np.degrees(euler_from_quat_array(truth[still])), axis=0).max() > 80  # at two attitudes
    # the accelerometer reads −g along down, the gyroscope nothing (ideal sensors: ±1 count)
    np.testing.assert_allclose(rows[still, 3:6], quat_rotate_array(quat_conj_array(truth[still]), [0.0, 0.0, -G]), atol=0.1)
    np.testing.assert_allclose(rows[still, 0:3], 0.0, atol=math.radians(0.2))
    # the magnetometer sees one field in the earth frame, whichever way the IMU is turned
    field = quat_rotate_array(truth[still], rows[still, 6:9])
    np.testing.assert_allclose(field, np.broadcast_to(np.median(field, axis=0), field.shape), atol=0.5)
    # between the holds the gyroscope turned the IMU +90° about x (sign and axis; the sum over
    # the samples a starved loop kept is coarse)
    second_hold = moved[still & (moved > 0)].min()
    turning = (moved > 0) & (moved <= second_hold)
    turned = np.degrees(np.sum(rows[turning, 0:3] * rows[turning, 9:10], axis=0))
    assert 60 < turned[0] < 120 and np.abs(turned[1:]).max() < 30, turned
    # and before the first turn, the estimate is the truth: NED, [w, x, y, z], body to earth
    first_rest = still & (moved == 0)
    error = quat_angle_array(quat_mul_array(log.attitudes[first_rest], quat_conj_array(truth[first_rest])))
    assert np.count_nonzero(first_rest) >= 10 and np.degrees(error).max() < 1.0


def test_no_attitude_is_published_before_the_first_estimate(tmp_path, gcs):
    """The estimator waits for the magnetometer's first reading; until a sample is estimated
    the ground station gets HEARTBEAT in state BOOT, not a made-up attitude."""
    conn, port = gcs
    svc = Service(service_config(tmp_path, port, log={"enabled": False}))
    svc.start()  # the loop is not run: this test steps the source, pipeline and MAVLink by hand
    try:
        svc.mavlink.tick(time.monotonic_ns())
        before = collect(conn, 0.5)
        assert [m.get_type() for m in before] == ["HEARTBEAT"]
        assert before[0].system_status == mavlink2.MAV_STATE_BOOT

        deadline = time.monotonic() + 10.0
        while svc.pipeline.last_sample is None and time.monotonic() < deadline:
            sample = svc.source.read()
            if sample is not None:
                svc.pipeline.process(sample)
            time.sleep(0.002)
        assert svc.pipeline.last_sample is not None
        svc.mavlink.tick(time.monotonic_ns() + 2_000_000_000)  # every stream is due again
        after = {m.get_type(): m for m in collect(conn, 0.5)}
        assert after["HEARTBEAT"].system_status == mavlink2.MAV_STATE_ACTIVE
        q = after["ATTITUDE_QUATERNION"]
        assert np.allclose([q.q1, q.q2, q.q3, q.q4], svc.pipeline.published_quaternion(), atol=1e-7)
    finally:
        svc.close()


def _first(conn, wanted, seconds=10.0):
    """The first message for which ``wanted(msg)`` is true, within ``seconds`` (else None)."""
    return next((m for m in collect(conn, seconds, until=wanted) if wanted(m)), None)


def _param_names(conn, seconds: float = 15.0) -> set[str]:
    """The names of a PARAM_REQUEST_LIST's answers: collects until the last index came."""
    def last(m) -> bool:
        return m.get_type() == "PARAM_VALUE" and m.param_index == m.param_count - 1

    return {m.param_id for m in collect(conn, seconds, until=last) if m.get_type() == "PARAM_VALUE"}


def _param_value(conn, name, seconds=10.0):
    return _first(conn, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name, seconds)


def test_parameters_change_the_running_estimator(tmp_path, gcs):
    conn, port = gcs
    # moving from the first sample: a gain change shows in the attitude at once
    run = RunningService(service_config(tmp_path, port, estimator={"name": "madgwick"}, source={"profile": "figure8"}))
    try:
        collect(conn, 1.0, until=lambda m: m.get_type() == "HEARTBEAT")
        assert _wait_until(lambda: run.service.pipeline.samples >= 100)  # the change comes mid-log
        conn.mav.param_request_list_send(1, 1)
        names = _param_names(conn)
        assert {"EST_BETA", "MAG_DECL_DEG", "RATE_ATT_HZ", "LOOP_RATE_HZ"} <= names

        conn.mav.param_request_read_send(1, 1, b"EST_BETA", -1)
        # the default (the tuned preset), as a float32 on the wire
        beta0 = float(np.float32(estimators.create("madgwick").get_params()["beta"]))
        assert _param_value(conn, "EST_BETA").param_value == pytest.approx(beta0)

        conn.mav.param_set_send(1, 1, b"EST_BETA", 0.033, mavlink2.MAV_PARAM_TYPE_REAL32)
        ack = _param_value(conn, "EST_BETA")
        assert ack.param_value == pytest.approx(0.033)
        assert run.service.estimator.get_params()["beta"] == pytest.approx(0.033)  # in force when acknowledged
        changed_at = run.service.pipeline.samples
        assert _wait_until(lambda: run.service.pipeline.samples >= changed_at + 100)

        conn.mav.param_set_send(1, 1, b"RATE_ATT_HZ", 500.0, mavlink2.MAV_PARAM_TYPE_REAL32)  # above 200: refused
        assert _param_value(conn, "RATE_ATT_HZ").param_value == pytest.approx(20.0)
    finally:
        run.stop()
    # the live change is in the log at the sample index where it took effect ...
    log = read_log(run.service.log_writer.files[0])
    changes = [c for c in log.param_changes if c["name"] == "beta"]
    assert len(changes) == 1 and changes[0]["new"] == pytest.approx(0.033)
    assert 0 < changes[0]["sample_index"] < len(log.t_ns)
    # ... so replaying the log reproduces every recorded attitude bit for bit
    from ahrs_service.replay import replay

    assert np.array_equal(replay(log), log.attitudes)
    assert not np.array_equal(replay(log, follow_param_changes=False), log.attitudes)


def test_a_ground_station_write_is_in_the_log_once_with_its_sender(tmp_path, gcs):
    """The declination set twice (the second a no-op) and a stream rate: each accepted change
    once on /params and /log with who sent it; the no-op nowhere; replay is unaffected."""
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, estimator={"name": "madgwick"}))
    try:
        collect(conn, 1.0, until=lambda m: m.get_type() == "HEARTBEAT")
        assert _wait_until(lambda: run.service.pipeline.samples >= 100)  # the changes come mid-log
        for _ in range(2):
            conn.mav.param_set_send(1, 1, b"MAG_DECL_DEG", 5.0, mavlink2.MAV_PARAM_TYPE_REAL32)
            assert _param_value(conn, "MAG_DECL_DEG").param_value == pytest.approx(5.0)
        conn.mav.param_set_send(1, 1, b"RATE_ATT_HZ", 10.0, mavlink2.MAV_PARAM_TYPE_REAL32)
        assert _param_value(conn, "RATE_ATT_HZ").param_value == pytest.approx(10.0)
        assert run.service.pipeline.declination_deg == pytest.approx(5.0)
    finally:
        run.stop()
    log = read_log(run.service.log_writer.files[0])
    sender = "mavlink 255/190 unsigned"
    decl = [c for c in log.param_changes if c["name"] == "MAG_DECL_DEG"]
    rate = [c for c in log.param_changes if c["name"] == "RATE_ATT_HZ"]
    assert len(decl) == 1 and decl[0]["new"] == pytest.approx(5.0) and decl[0]["source"] == sender
    assert len(rate) == 1 and rate[0]["new"] == pytest.approx(10.0) and rate[0]["source"] == sender
    texts = [m for f in run.service.log_writer.files for _, m in _log_lines(f)]
    assert sum(t.startswith("MAG_DECL_DEG:") and sender in t for t in texts) == 1
    # the estimator's parameters are not these: its replay is bit for bit as before
    from ahrs_service.replay import replay

    assert np.array_equal(replay(log), log.attitudes)


def _log_lines(path) -> list[tuple[int, str]]:
    from tests.test_demo_accuracy import _log_events

    return _log_events(path)


def test_unwritable_log_directory_is_reported_and_publishing_goes_on(tmp_path, gcs):
    conn, port = gcs
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("a file where the log directory should be")
    run = RunningService(service_config(tmp_path, port, log={"directory": str(blocker / "logs")}))
    seen = {"report": False, "attitude": 0}

    def enough(m) -> bool:
        seen["report"] |= m.get_type() == "STATUSTEXT" and m.text.startswith("flight log stopped:")
        seen["attitude"] += m.get_type() == "ATTITUDE"
        return seen["report"] and seen["attitude"] >= 10

    try:
        msgs = collect(conn, 30.0, until=enough)  # a generous bound: stops as soon as both came
    finally:
        run.stop()
    texts = [m.text for m in msgs if m.get_type() == "STATUSTEXT"]
    assert any(t.startswith("flight log stopped:") for t in texts), texts
    # publishing goes on, on its 20 Hz schedule
    t_ms = [m.time_boot_ms for m in msgs if m.get_type() == "ATTITUDE"]
    assert_stream_on_schedule(t_ms, 20)
    # each ATTITUDE is the estimate of a distinct sample
    assert run.service.pipeline.samples >= len(t_ms)


def _ack(conn, command, seconds=10.0):
    return _first(conn, lambda m: m.get_type() == "COMMAND_ACK" and m.command == command, seconds)


def test_message_interval_and_gyro_calibration_commands(tmp_path, gcs):
    conn, port = gcs
    # static: the IMU is at rest, so gyro calibration is accepted; the simulated L3G4200D has
    # its datasheet-sized zero-rate offset
    run = RunningService(service_config(tmp_path, port, source={"profile": "static", "sensor_errors": True}))
    try:
        collect(conn, 1.5)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, 100_000, 0, 0, 0, 0, 0)
        assert _ack(conn, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED
        collect(conn, 0.3)
        att = [m for m in collect(conn, 3.0) if m.get_type() == "ATTITUDE"]
        assert run.service.mavlink.component.rates["ATTITUDE"] == pytest.approx(10.0)
        assert_stream_on_schedule([m.time_boot_ms for m in att], 10)

        pipeline = run.service.pipeline
        assert _wait_until(lambda: pipeline.samples >= pipeline.rest_window)  # a full rest window
        residual_before = np.linalg.norm(pipeline.recent_gyro_mean())
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
        calibrated_at = pipeline.samples
        # the rest window refills with calibrated rates
        assert _wait_until(lambda: pipeline.samples >= calibrated_at + pipeline.rest_window)
        residual_after = np.linalg.norm(pipeline.recent_gyro_mean())
        assert residual_before > 5e-3  # rad/s: the offset was there ...
        assert residual_after < 0.1 * residual_before  # ... and calibration removed it
    finally:
        run.stop()


def test_gyro_calibration_refused_while_moving(tmp_path, gcs):
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, source={"profile": "figure8"}))
    try:
        collect(conn, 2.0)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0)
        ack = _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION)
        assert ack.result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
    finally:
        run.stop()


def test_signed_mode_rejects_unsigned_parameter_writes(tmp_path, gcs):
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, estimator={"name": "madgwick"}, mavlink={"signing_key": KEY_HEX}))
    try:
        collect(conn, 1.0)
        conn.mav.param_set_send(1, 1, b"EST_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        assert _wait_until(lambda: run.service.mavlink.stats()["unsigned_rejected"] >= 1)
        assert run.service.estimator.get_params()["beta"] == estimators.create("madgwick").get_params()["beta"]  # the default kept

        conn.setup_signing(bytes.fromhex(KEY_HEX), sign_outgoing=True)
        conn.mav.param_set_send(1, 1, b"EST_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        assert _param_value(conn, "EST_BETA").param_value == pytest.approx(0.5)
        assert run.service.estimator.get_params()["beta"] == pytest.approx(0.5)
    finally:
        run.stop()


def test_companion_identity(tmp_path, gcs):
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, mavlink={"identity": "companion", "system_id": 7}))
    try:
        hb = [m for m in collect(conn, 2.5, until=lambda m: m.get_type() == "HEARTBEAT") if m.get_type() == "HEARTBEAT"]
    finally:
        run.stop()
    assert hb and (hb[0].get_srcSystem(), hb[0].get_srcComponent()) == (7, 200)
    assert hb[0].type == mavlink2.MAV_TYPE_IMU and hb[0].autopilot == mavlink2.MAV_AUTOPILOT_INVALID


def test_magnetometer_calibration_collects_and_refuses_a_second_start(tmp_path, gcs):
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, source={"profile": "validation"}))
    try:
        collect(conn, 1.0)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 1, 0, 0, 0, 0, 0)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
        assert run.service.live_calibration.active
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 1, 0, 0, 0, 0, 0)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
        assert _first(conn, lambda m: m.get_type() == "STATUSTEXT" and "mag" in m.text.lower()) is not None
        # collecting: each new magnetometer reading is kept (HMC5883L at 75 Hz)
        assert _wait_until(lambda: run.service.live_calibration.samples > 100, 30.0)
    finally:
        run.stop()


def test_declination_from_the_world_magnetic_model(tmp_path, gcs):
    from ahrs_service.calibration.declination import declination_deg

    conn, port = gcs
    cfg = service_config(tmp_path, port, location={"latitude_deg": 52.5, "longitude_deg": 13.4})
    run = RunningService(cfg)
    try:
        collect(conn, 1.0)
    finally:
        run.stop()
    pipeline = run.service.pipeline
    assert pipeline.declination_deg == pytest.approx(declination_deg(52.5, 13.4))
    assert abs(pipeline.declination_deg) > 1.0  # Berlin: several degrees east
    # the published yaw is the estimator's magnetic heading turned by the declination
    from ahrs_service.core.quaternion import quat_to_euler

    yaw_magnetic = quat_to_euler(tuple(pipeline.estimator.state[:4]))[2]
    diff = (pipeline.published_euler()[2] - yaw_magnetic + math.pi) % (2 * math.pi) - math.pi
    assert math.degrees(diff) == pytest.approx(pipeline.declination_deg, abs=1e-6)


@pytest.mark.parametrize("damage", [b"# caf\xe9\n", b"[estimator]\ndeclination_deg = nan\n"])
def test_a_reload_of_a_damaged_file_keeps_the_running_configuration(tmp_path, gcs, damage):
    """Issue 14: SIGHUP after the file gained a non-UTF-8 byte (or a NaN) is refused with one
    line; the service goes on with what it runs."""
    conn, port = gcs
    cfg_file = tmp_path / "ahrs.toml"
    text = (f'[source]\ntype = "simulated_i2c"\nsensor_errors = false\n\n[estimator]\nname = "madgwick"\n\n'
            f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\n').encode()
    cfg_file.write_bytes(text)
    run = RunningService(config_mod.load(cfg_file, {"log": {"enabled": False}}), duration_s=120.0)
    try:
        collect(conn, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        before = run.service.cfg
        cfg_file.write_bytes(text + damage)
        run.service.request_reload()
        got = collect(conn, 30.0, until=lambda m: m.get_type() == "STATUSTEXT" and "reload" in m.text)
        assert got and got[-1].text.startswith("reload refused")
        assert run.service.cfg is before and run.thread.is_alive()
        att = collect(conn, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        assert att and all(math.isfinite(v) for v in (att[-1].roll, att[-1].pitch, att[-1].yaw))
    finally:
        run.stop()


def test_reload_to_another_estimator_rebuilds_its_parameters_and_keeps_command_line_overrides(tmp_path, gcs):
    conn, port = gcs
    cfg_file = tmp_path / "ahrs.toml"

    def write(estimator: str) -> None:
        cfg_file.write_text(
            f'[source]\ntype = "simulated_i2c"\nboard = "gy80"\nsensor_errors = false\n\n'
            f'[estimator]\nname = "{estimator}"\n\n[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\n'
        )

    write("madgwick")
    # as `ahrs-service run --config ahrs.toml --no-log` does
    run = RunningService(config_mod.load(cfg_file, {"log": {"enabled": False}}), duration_s=120.0)
    try:
        collect(conn, 1.0, until=lambda m: m.get_type() == "HEARTBEAT")
        write("mahony_passive")
        run.service.request_reload()
        # the reload ends with this text from the new MAVLink component (its new socket is
        # where the GCS sends from now on); the new filter may first have to compile
        got = collect(conn, 90.0, until=lambda m: m.get_type() == "STATUSTEXT" and "reloaded" in m.text)
        assert "configuration reloaded" in got[-1].text
        assert run.service.estimator.name == "mahony_passive"
        assert run.service.log_writer is None  # --no-log survives the reload
        conn.mav.param_request_list_send(1, 1)
        names = _param_names(conn)
        assert "EST_KP" in names and "EST_BETA" not in names
    finally:
        run.stop()


def test_a_reload_to_an_endpoint_that_cannot_be_opened_is_refused_and_the_links_stay(tmp_path, gcs):
    """Issue 14 re-probe: SIGHUP after ``mavlink.endpoints`` gained a link that cannot be opened
    (here a TCP port that refuses: bound, not listening) ended the service with exit 2, its
    links already closed. The reload is refused with one line naming the key; the running
    configuration and links stay."""
    import socket

    conn, port = gcs
    held = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    held.bind(("127.0.0.1", 0))  # bound, never listening: a connection to it is refused
    cfg_file = tmp_path / "ahrs.toml"
    text = (f'[source]\ntype = "simulated_i2c"\nsensor_errors = false\n\n[estimator]\nname = "madgwick"\n\n'
            f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\n')
    cfg_file.write_text(text)
    run = RunningService(config_mod.load(cfg_file, {"log": {"enabled": False}}), duration_s=120.0)
    try:
        collect(conn, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        before = run.service.cfg
        cfg_file.write_text(text.replace(f'{port}"]', f'{port}", "tcp:127.0.0.1:{held.getsockname()[1]}"]'))
        run.service.request_reload()
        got = collect(conn, 30.0, until=lambda m: m.get_type() == "STATUSTEXT" and "reload" in m.text)
        assert got and got[-1].text.startswith("reload refused: mavlink.endpoints")
        assert run.service.cfg is before and run.thread.is_alive()
        assert collect(conn, 10.0, until=lambda m: m.get_type() == "ATTITUDE")[-1].get_type() == "ATTITUDE"
    finally:
        run.stop()
        held.close()


def test_the_summary_names_the_folder_the_files_are_in_after_a_reload_moved_the_log(tmp_path, gcs):
    """Issue 14 re-probe (h14): a reload moved [log] to a folder that could not be written (a
    full disk); the summary said "log: 4 files in <the new folder>", which held none."""
    conn, port = gcs
    (tmp_path / "blocker").write_text("a file where the new log folder's parent should be\n")
    cfg_file = tmp_path / "ahrs.toml"

    def write(folder) -> None:
        cfg_file.write_text(f'[source]\ntype = "simulated_i2c"\nsensor_errors = false\n\n[estimator]\n'
                            f'name = "madgwick"\n\n[log]\ndirectory = "{folder}"\n\n'
                            f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\n')

    write(tmp_path / "logs")
    run = RunningService(config_mod.load(cfg_file), duration_s=120.0)
    try:
        collect(conn, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        write(tmp_path / "blocker" / "logs")
        run.service.request_reload()
        got = collect(conn, 30.0, until=lambda m: m.get_type() == "STATUSTEXT" and "reload" in m.text)
        assert got and got[-1].text == "configuration reloaded"
    finally:
        run.stop()
    summary = run.service.log_summary()
    assert summary.startswith(f"log: 1 file in {tmp_path / 'logs'}"), summary
    assert "blocker" not in summary.partition(", not logged")[0], summary


# ------------------------------------------------------------------ live calibration: the fit off the loop
FITTED_HARD_IRON = np.array([1.0, 2.0, 3.0])  # µT, what the replaced fit "finds"
MAG_CAL = (mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 1, 0, 0, 0, 0, 0)  # param2 = 1: magnetometer
ACCEL_CAL = (mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 0, 0, 0, 0, 1, 0, 0)  # param5 = 1: accelerometer


class BlockingMagFit:
    """Stands in for ``fit_magnetometer``: records the thread it runs on, blocks until
    ``release`` is set, then raises ``error`` or returns an accepted fit."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.release = threading.Event()
        self.threads: list[tuple[int, str]] = []
        self.error: BaseException | None = None

    def __call__(self, mag: np.ndarray, **options) -> MagCalibrationResult:
        self.threads.append((threading.get_ident(), threading.current_thread().name))
        self.entered.set()
        if not self.release.wait(15.0):
            raise AssertionError("the test never released the fit")
        if self.error is not None:
            raise self.error
        return MagCalibrationResult(FITTED_HARD_IRON, np.eye(3), 49.3, 0.1, 0.002, 0.9, 1.0, len(mag), True, "ok")


@pytest.fixture
def blocking_mag_fit(monkeypatch):
    fit = BlockingMagFit()
    monkeypatch.setattr(live_mod, "fit_magnetometer", fit)
    monkeypatch.setitem(live_mod.DEFAULT_DURATION_S, "mag", 0.5)  # s of samples instead of a minute
    yield fit
    fit.release.set()  # a failed test must not leave the fit thread waiting


def _wait_until(condition, seconds: float = 10.0) -> bool:
    """Polls ``condition()`` until true or ``seconds`` pass (the bound only matters on failure)."""
    end = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


def _statustext(conn, fragment: str, seconds: float = 10.0):
    return _first(conn, lambda m: m.get_type() == "STATUSTEXT" and fragment in m.text, seconds)


def _config_file(tmp_path, port: int) -> tuple:
    """A configuration loaded from a file (so that accepted calibrations are saved into it)."""
    path = tmp_path / "ahrs.toml"
    path.write_text(config_mod.to_toml(service_config(tmp_path, port, source={"profile": "static"}).raw))
    return path, config_mod.load(path)


def _start_mag_fit(conn, run: RunningService, fit: BlockingMagFit) -> None:
    """Sends the magnetometer calibration command and waits until its (blocked) fit runs."""
    conn.mav.command_long_send(1, 1, *MAG_CAL)
    assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
    assert fit.entered.wait(10.0), "the collection did not end in a fit"


def test_live_calibration_fit_runs_off_the_loop_thread_and_is_applied_on_it(tmp_path, gcs, blocking_mag_fit):
    conn, port = gcs
    fit = blocking_mag_fit
    cfg_path, cfg = _config_file(tmp_path, port)
    run = RunningService(cfg)
    svc = run.service
    applied_on: list[int] = []
    record = svc.record_calibration

    def recording(kind: str) -> None:  # called right after the pipeline's calibration is swapped
        applied_on.append(threading.get_ident())
        record(kind)

    svc.record_calibration = recording
    try:
        collect(conn, 1.0)
        _start_mag_fit(conn, run, fit)
        [(fit_thread, fit_name)] = fit.threads
        assert fit_thread != run.thread.ident and fit_name == live_mod.FIT_THREAD_NAME
        # the fit is blocked: the loop goes on estimating, with the old calibration
        assert svc.live_calibration.state == "fitting"
        n0 = svc.pipeline.samples
        assert _wait_until(lambda: svc.pipeline.samples >= n0 + 100), "the loop stalled during the fit"
        assert np.array_equal(svc.pipeline.calibration.mag_hard_iron, np.zeros(3))
        assert _statustext(conn, "mag cal: fitting") is not None  # housekeeping says why nothing happens yet

        fit.release.set()
        done = _statustext(conn, "mag cal done")
        assert done is not None and done.severity == mavlink2.MAV_SEVERITY_INFO
        assert np.array_equal(svc.pipeline.calibration.mag_hard_iron, FITTED_HARD_IRON)  # swapped before the text
        assert _wait_until(lambda: applied_on) and applied_on == [run.thread.ident]
        assert svc.live_calibration.state == "idle"
        n1 = svc.pipeline.samples
        assert _wait_until(lambda: svc.pipeline.samples > n1)
    finally:
        run.stop()
    # saved and logged as before
    assert np.array_equal(calibration_from_config_dict(config_mod.load(cfg_path).raw).mag_hard_iron, FITTED_HARD_IRON)
    logged = [c for c in read_log(svc.log_writer.files[-1]).configs if c.get("reason") == "calibration:mag"]
    assert len(logged) == 1
    assert calibration_from_config_dict(logged[0]["config"]).mag_hard_iron.tolist() == FITTED_HARD_IRON.tolist()


def test_live_calibration_fit_that_raises_is_reported_and_the_service_goes_on(tmp_path, gcs, blocking_mag_fit):
    conn, port = gcs
    fit = blocking_mag_fit
    fit.error = np.linalg.LinAlgError("singular matrix")
    fit.release.set()
    run = RunningService(service_config(tmp_path, port, source={"profile": "static"}))
    svc = run.service
    try:
        collect(conn, 1.0)
        _start_mag_fit(conn, run, fit)
        failed = _statustext(conn, "mag cal failed")
        assert failed is not None and "LinAlgError" in failed.text
        assert failed.severity == mavlink2.MAV_SEVERITY_WARNING
        assert run.thread.is_alive()
        n0 = svc.pipeline.samples
        assert _wait_until(lambda: svc.pipeline.samples >= n0 + 100)
        assert np.array_equal(svc.pipeline.calibration.mag_hard_iron, np.zeros(3))
        # the calibrator is idle again: a new calibration is accepted
        assert svc.live_calibration.state == "idle"
        conn.mav.command_long_send(1, 1, *MAG_CAL)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
    finally:
        run.stop()


def test_live_calibration_command_during_a_running_fit_is_refused(tmp_path, gcs, blocking_mag_fit):
    conn, port = gcs
    fit = blocking_mag_fit
    run = RunningService(service_config(tmp_path, port, source={"profile": "static"}))
    svc = run.service
    try:
        collect(conn, 1.0)
        _start_mag_fit(conn, run, fit)
        for command in (MAG_CAL, ACCEL_CAL):
            conn.mav.command_long_send(1, 1, *command)
            assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
        assert _statustext(conn, "still being fitted") is not None  # the reason, sent with the ACK
        assert svc.live_calibration.state == "fitting" and not svc.live_calibration.active

        fit.release.set()
        assert _statustext(conn, "mag cal done") is not None
        conn.mav.command_long_send(1, 1, *ACCEL_CAL)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
    finally:
        run.stop()


def test_stop_during_a_running_fit_abandons_it_without_waiting_for_it(tmp_path, gcs, blocking_mag_fit, caplog):
    conn, port = gcs
    fit = blocking_mag_fit
    cfg_path, cfg = _config_file(tmp_path, port)
    run = RunningService(cfg)
    collect(conn, 1.0)
    try:
        _start_mag_fit(conn, run, fit)
    except BaseException:
        run.stop()
        raise
    stopper = threading.Thread(target=run.stop, daemon=True)
    with caplog.at_level("WARNING", logger="ahrs_service"):
        stopper.start()
        stopper.join(10.0)  # close() waits LIVE_FIT_CLOSE_WAIT_S for the fit, not for the release
        assert not stopper.is_alive(), "stopping waited for the blocked fit"
    assert not fit.release.is_set()
    assert any("still running at shutdown" in r.getMessage() for r in caplog.records)
    assert np.array_equal(run.service.pipeline.calibration.mag_hard_iron, np.zeros(3))
    assert np.array_equal(calibration_from_config_dict(config_mod.load(cfg_path).raw).mag_hard_iron, np.zeros(3))


def test_gyro_calibration_during_a_running_fit_is_kept_when_the_fit_is_applied(tmp_path, gcs, blocking_mag_fit):
    conn, port = gcs
    fit = blocking_mag_fit
    # at rest, with the simulated gyro's zero-rate offset: the gyro command is accepted
    run = RunningService(service_config(tmp_path, port, source={"profile": "static", "sensor_errors": True}))
    svc = run.service
    try:
        collect(conn, 1.5)
        _start_mag_fit(conn, run, fit)
        assert _wait_until(lambda: svc.pipeline.samples >= svc.pipeline.rest_window)  # a full rest window
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION, 0, 1, 0, 0, 0, 0, 0, 0)
        assert _ack(conn, mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION).result == mavlink2.MAV_RESULT_ACCEPTED
        gyro_bias = svc.pipeline.calibration.gyro_bias.copy()
        assert np.linalg.norm(gyro_bias) > 0

        fit.release.set()
        assert _statustext(conn, "mag cal done") is not None
        # the fit started from the calibration before the gyro command; only its mag terms are applied
        assert np.array_equal(svc.pipeline.calibration.mag_hard_iron, FITTED_HARD_IRON)
        assert np.array_equal(svc.pipeline.calibration.gyro_bias, gyro_bias)
    finally:
        run.stop()


def _sys_status(conn, seconds: float = 10.0):
    return _first(conn, lambda m: m.get_type() == "SYS_STATUS", seconds)


def test_health_per_sensor_and_no_fresh_looking_attitude_without_a_gyroscope(tmp_path, gcs):
    """Issue 14: a lost magnetometer is a magnetometer fault (reduced mode), not an IMU fault;
    a lost gyroscope stops the attitude streams (HEARTBEAT CRITICAL, SYS_STATUS goes on) until
    it returns."""
    conn, port = gcs
    run = RunningService(service_config(tmp_path, port, log={"enabled": False},
                                        rates={"sys_status_hz": 5, "heartbeat_hz": 5}))
    svc = run.service
    bus = svc.source.bus
    gyro_bit, mag_bit = mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO, mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG
    try:
        collect(conn, 30.0, until=lambda m: m.get_type() == "ATTITUDE")
        bus.set_present(0x1E, False)  # HMC5883L
        assert _wait_until(lambda: "mag" in svc.source.lost and svc.pipeline.reduced)
        collect(conn, 0.5)  # what was sent before the loss
        st = _sys_status(conn)
        assert st.onboard_control_sensors_health & gyro_bit and not st.onboard_control_sensors_health & mag_bit
        hb = _first(conn, lambda m: m.get_type() == "HEARTBEAT", 10.0)
        assert hb.system_status == mavlink2.MAV_STATE_ACTIVE
        assert collect(conn, 10.0, until=lambda m: m.get_type() == "ATTITUDE")[-1].get_type() == "ATTITUDE"

        withheld = svc.mavlink.component.stats.stale_withheld
        bus.set_present(0x69, False)  # L3G4200D
        assert _wait_until(lambda: svc.mavlink.component.stats.stale_withheld > withheld)
        collect(conn, 0.3)
        got = collect(conn, 1.0)
        assert not [m for m in got if m.get_type() in ("ATTITUDE", "ATTITUDE_QUATERNION", "VIBRATION")]
        assert any(m.get_type() == "HEARTBEAT" and m.system_status == mavlink2.MAV_STATE_CRITICAL for m in got)
        ahrs_bit = mavlink2.MAV_SYS_STATUS_AHRS
        assert any(m.get_type() == "SYS_STATUS" and not m.onboard_control_sensors_health & (gyro_bit | ahrs_bit)
                   for m in got)

        samples_at_return = svc.pipeline.samples
        bus.set_present(0x69, True)
        att = collect(conn, 10.0, until=lambda m: m.get_type() == "ATTITUDE")
        assert att and att[-1].get_type() == "ATTITUDE" and math.isfinite(att[-1].roll)
        assert svc.pipeline.samples > samples_at_return  # published from new estimates
        back = collect(conn, 10.0, until=lambda m: m.get_type() == "SYS_STATUS")
        assert back[-1].get_type() == "SYS_STATUS" and back[-1].onboard_control_sensors_health & (gyro_bit | ahrs_bit) \
            == gyro_bit | ahrs_bit
    finally:
        run.stop()


def test_a_periodic_job_that_raises_is_reported_and_the_service_goes_on(tmp_path, gcs):
    """Issue 14: an exception in one of the loop's periodic jobs (here the diagnostics job, 10
    times a second) is counted and reported at its 1st, 2nd, 4th … failure; estimation and
    ATTITUDE go on."""
    conn, port = gcs
    service = Service(service_config(tmp_path, port, log={"enabled": False}), duration_s=30.0)
    service.start()

    def hostile(now_ns: int) -> None:
        raise ZeroDivisionError("float division by zero")

    service._diagnostics_due = hostile  # what the job list binds (Service._periodic_jobs)
    thread = threading.Thread(target=service.run, daemon=True)
    thread.start()
    try:
        texts: list[str] = []
        chunks: dict[int, str] = {}  # a long STATUSTEXT comes in 50-character chunks of one id
        attitudes_after_failure = 0
        end = time.monotonic() + 20.0
        while time.monotonic() < end and not (attitudes_after_failure >= 20 and any("(4 times" in t for t in texts)):
            m = conn.recv_match(blocking=True, timeout=0.05)
            if m is None:
                continue
            if m.get_type() == "STATUSTEXT":
                text = chunks.pop(m.id, "") + m.text
                if len(m.text) == 50 and m.id:
                    chunks[m.id] = text
                elif text.startswith("log diagnostics failed"):
                    texts.append(text)
            elif m.get_type() == "ATTITUDE" and texts:
                attitudes_after_failure += 1
        samples = service.pipeline.samples
    finally:
        service.request_stop()
        thread.join(10)
        service.close()
    assert not thread.is_alive()
    assert texts[:3] == [f"log diagnostics failed ({n} {'time' if n == 1 else 'times'} so far), the service goes on: "
                         "ZeroDivisionError: float division by zero" for n in (1, 2, 4)], texts
    assert attitudes_after_failure >= 20 and samples > 0



def test_close_gives_back_the_signal_handlers_the_service_replaced(tmp_path, gcs):
    """A service run in-process (the CLI's ``run``, an embedding program) installs its own
    SIGTERM/SIGINT/SIGHUP handlers; once closed, a signal goes to what was there before —
    not to the stopped service's request_stop, which would swallow a Ctrl-C."""
    conn, port = gcs
    signals = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)

    def embedding_programs_handler(*_):
        pass

    before = {sig: signal.signal(sig, embedding_programs_handler) for sig in signals}
    try:
        svc = Service(service_config(tmp_path, port, log={"enabled": False}), duration_s=0.3)
        svc.install_signal_handlers()
        assert signal.getsignal(signal.SIGINT) == svc.request_stop
        assert signal.getsignal(signal.SIGHUP) == svc.request_reload
        svc.start()
        svc.run()
        svc.close()
        assert [signal.getsignal(sig) for sig in signals] == [embedding_programs_handler] * 3
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
