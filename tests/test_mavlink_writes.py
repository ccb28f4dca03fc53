"""What a MAVLink peer may change, and the record of what it changed (docs/mavlink.md, "Security").

A pymavlink ground station talks to the service's MAVLink side over real UDP on 127.0.0.1:
the component alone, or the bridge built with a hand-made ``ServiceLink`` over a real
estimation pipeline (fed still or turning samples), a real ``AutopilotLink`` to a pymavlink
"autopilot" that beats armed or disarmed, and a real flight log read back with the mcap library.
"""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from mcap.reader import make_reader  # noqa: E402
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from ahrs_service import config as config_mod  # noqa: E402
from ahrs_service import estimators  # noqa: E402
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, ImuSample  # noqa: E402
from ahrs_service.core.vibration import VibrationMonitor  # noqa: E402
from ahrs_service.logs.writer import FlightLogWriter  # noqa: E402
from ahrs_service.mavlink_bridge import LinkHealth, MavlinkBridge, ServiceLink  # noqa: E402
from ahrs_service.pipeline import EstimationPipeline  # noqa: E402
from ahrs_service.protocols.mavlink import Identity, MavlinkComponent  # noqa: E402
from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink  # noqa: E402

pytestmark = pytest.mark.timeout(90)

KEY_HEX = "5c" * 32
G = 9.80665
PERIOD_NS = 5_000_000  # the pipeline's samples: 200 Hz
CAL = mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION
INTERVAL = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
GYRO_CAL = (1, 0, 0, 0, 0, 0, 0)  # param1 = 1
MAG_CAL = (0, 1, 0, 0, 0, 0, 0)  # param2 = 1
HEARTBEAT_ID = mavlink2.MAVLINK_MSG_ID_HEARTBEAT
QUATERNION_ID = mavlink2.MAVLINK_MSG_ID_ATTITUDE_QUATERNION


# ------------------------------------------------------------------------------ helpers
def make_gcs(system_id: int = 255, component_id: int = 190):
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=system_id, source_component=component_id)
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=system_id, srcComponent=component_id)
    gcs.mav.robust_parsing = True
    return gcs, gcs.port.getsockname()[1]


def free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(drive, gcs, wanted, seconds: float = 10.0):
    """Calls ``drive()`` and reads the ground station until it got a message ``wanted``
    accepts (bounded by ``seconds``); returns it, or None."""
    end = time.monotonic() + seconds
    for _ in range(100_000):
        drive()
        m = gcs.recv_match(blocking=True, timeout=0.002)
        if m is not None and m.get_type() != "BAD_DATA" and wanted(m):
            return m
        if time.monotonic() > end:
            return None
    return None


def connect(drive, gcs) -> None:
    """Waits for the service's first HEARTBEAT: from then on the ground station knows where
    to send (a ``udpin`` peer answers the address it heard from)."""
    assert wait_for(drive, gcs, lambda m: m.get_type() == "HEARTBEAT") is not None


def statustext(drive, gcs) -> str:
    """The next STATUSTEXT, its chunks joined (a text over 50 characters comes in several
    messages of one id; the last is shorter than 50)."""
    parts = []
    for _ in range(20):
        m = wait_for(drive, gcs, lambda m: m.get_type() == "STATUSTEXT")
        assert m is not None, f"no STATUSTEXT after {parts}"
        parts.append(m.text)
        if len(m.text) < 50:
            break
    return "".join(parts)


def ack(drive, gcs, command: int):
    return wait_for(drive, gcs, lambda m: m.get_type() == "COMMAND_ACK" and m.command == command)


def until(condition, seconds: float = 10.0) -> bool:
    end = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > end:
            return False
        time.sleep(0.01)
    return True


class Imu:
    """Feeds a real estimation pipeline samples 5 ms apart on its own clock."""

    def __init__(self, pipeline: EstimationPipeline, seed: int) -> None:
        self.pipeline, self.k, self.rng = pipeline, 0, np.random.default_rng(seed)

    def _feed(self, gyr: np.ndarray, acc: np.ndarray) -> None:
        self.k += 1
        self.pipeline.process(ImuSample(self.k * PERIOD_NS, gyr, acc, flags=GYR_VALID | ACC_VALID))

    def still(self, seconds: float) -> None:
        """A level IMU at rest, with the noise of a consumer MEMS part."""
        for _ in range(int(seconds * 1e9 / PERIOD_NS)):
            self._feed(self.rng.normal(0.0, 0.003, 3), np.array([0.0, 0.0, -G]) + self.rng.normal(0.0, 0.05, 3))

    def rocking(self, seconds: float) -> None:
        """An IMU rocked about x, ±0.5 rad/s at 1 Hz: a vehicle in motion."""
        for _ in range(int(seconds * 1e9 / PERIOD_NS)):
            rate = 0.5 * math.sin(2 * math.pi * self.k * PERIOD_NS / 1e9)
            self._feed(np.array([rate, 0.0, 0.0]), np.array([0.0, 0.0, -G]))


class FakeService:
    """The service's side of a ServiceLink: estimator parameters, declination, calibrations
    that start, and the flight log they are recorded in (as ``Service.set_estimator_param``
    records a change: /params and /log)."""

    def __init__(self, writer: FlightLogWriter | None = None) -> None:
        self.params = {"beta": 0.1}
        self.declination = 0.0
        self.calibrations: list[str] = []
        self.writer = writer

    def record(self, name, old, new, source) -> None:
        if self.writer is not None:
            now = time.monotonic_ns()
            self.writer.write_param_change(now, None, name, old, new, source)
            self.writer.write_log(now, 6, f"parameter {name}: {old} -> {new} ({source})")

    def set_param_from(self, name: str, value: float, source: str) -> float:
        old, self.params[name] = self.params[name], value
        self.record(name, old, value, source)
        return value

    def link(self, autopilot=None) -> ServiceLink:
        return ServiceLink(
            boot_ns=0, estimator="madgwick", param_names=["beta"],
            health=lambda: LinkHealth(True, True, False, False, 0, 0.0, 0, 0, 0),
            get_param=lambda n: self.params[n], set_param=lambda n, v: self.set_param_from(n, v, "mavlink"),
            get_declination=lambda: self.declination,
            set_declination=lambda d: setattr(self, "declination", d),
            loop_rate_hz=lambda: 200.0,
            calibrate_gyro=lambda: (self.calibrations.append("gyro"), (True, "gyro bias set"))[1],
            start_calibration=lambda kind: (self.calibrations.append(kind), (True, f"{kind} cal started"))[1],
            vibration=VibrationMonitor().levels,
            set_param_from=self.set_param_from, record_write=self.record, autopilot=autopilot,
        )


def bridge_config(port: int, **mavlink) -> config_mod.Config:
    return config_mod.validate({"mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"], **mavlink},
                                "rates": {"estimation_hz": 200}})


def make_imu(seed: int) -> Imu:
    """A madgwick pipeline (without magnetometer readings) and 2 s of its IMU at rest."""
    imu = Imu(EstimationPipeline(estimators.create("madgwick"), use_mag=False, nominal_dt=PERIOD_NS / 1e9), seed)
    imu.still(2.0)
    return imu


# ------------------------------------------------------------------------------ HEARTBEAT
def test_heartbeat_cannot_be_switched_off_or_slowed_below_1_hz_over_the_air():
    """PX4 refuses SET_MESSAGE_INTERVAL(HEARTBEAT, -1): a ground station would lose the vehicle."""
    gcs, port = make_gcs()
    try:
        with MavlinkComponent([f"udpout:127.0.0.1:{port}"], Identity()) as comp:
            drive = comp.poll
            comp.send_now("HEARTBEAT")
            assert wait_for(drive, gcs, lambda m: m.get_type() == "HEARTBEAT") is not None
            for interval_us in (-1, 10_000_000):  # off; one every 10 s
                gcs.mav.command_long_send(1, 1, INTERVAL, 0, HEARTBEAT_ID, interval_us, 0, 0, 0, 0, 0)
                answer = ack(drive, gcs, INTERVAL)
                assert answer is not None and answer.result == mavlink2.MAV_RESULT_DENIED
                assert comp.rates["HEARTBEAT"] == 1.0
            assert comp.stats.writes_refused == 2 and comp.stats.writes_accepted == 0
            # still beating at 1 Hz: 3 s of the component's clock, one HEARTBEAT a second
            sent = comp.stats.sent.get("HEARTBEAT", 0)
            for k in range(600):
                comp.publish(10_000_000_000 + k * PERIOD_NS, None)
            assert comp.stats.sent["HEARTBEAT"] - sent == 3
            # faster, and back to the configured rate, are fine
            gcs.mav.command_long_send(1, 1, INTERVAL, 0, HEARTBEAT_ID, 500_000, 0, 0, 0, 0, 0)
            assert ack(drive, gcs, INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED
            assert comp.rates["HEARTBEAT"] == 2.0
            gcs.mav.command_long_send(1, 1, INTERVAL, 0, HEARTBEAT_ID, 0, 0, 0, 0, 0, 0)
            assert ack(drive, gcs, INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED
            assert comp.rates["HEARTBEAT"] == 1.0
            assert comp.stats.writes_accepted == 2 and comp.stats.writes_refused == 2
    finally:
        gcs.close()


# ------------------------------------------------------------------------------ calibration
def test_a_calibration_starts_only_while_the_imu_is_at_rest():
    gcs, port = make_gcs()
    fake = FakeService()
    imu = make_imu(7)
    bridge = MavlinkBridge(fake.link(), bridge_config(port), io_period_ns=PERIOD_NS, estimates=imu.pipeline)
    drive = lambda: bridge.tick(time.monotonic_ns())  # noqa: E731
    try:
        connect(drive, gcs)
        gcs.mav.command_long_send(1, 1, CAL, 0, *MAG_CAL)
        assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_ACCEPTED
        assert statustext(drive, gcs) == "mag cal started"
        assert fake.calibrations == ["mag"]

        imu.rocking(1.0)
        for params, sensor in ((MAG_CAL, "mag"), (GYRO_CAL, "gyro")):
            gcs.mav.command_long_send(1, 1, CAL, 0, *params)
            assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
            said = statustext(drive, gcs)  # it follows the ACK
            assert said.startswith(f"{sensor} calibration refused: not at rest (moving: gyro std "), said
        assert fake.calibrations == ["mag"]  # neither reached the service
        assert bridge.stats()["writes_refused"] == 2

        imu.still(1.0)  # put down again: one full rest window
        gcs.mav.command_long_send(1, 1, CAL, 0, *GYRO_CAL)
        assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_ACCEPTED
        assert fake.calibrations == ["mag", "gyro"]
    finally:
        bridge.close()
        gcs.close()


def test_no_calibration_starts_while_a_linked_autopilot_says_it_is_armed():
    """The autopilot's HEARTBEAT (base_mode MAV_MODE_FLAG_SAFETY_ARMED) on the AutopilotLink."""
    gcs, port = make_gcs()
    ap_port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{ap_port}")
    autopilot = mavutil.mavlink_connection(f"udpout:127.0.0.1:{ap_port}", source_system=1, source_component=1)
    autopilot.mav = mavlink2.MAVLink(autopilot, srcSystem=1, srcComponent=1)
    fake = FakeService()
    imu = make_imu(3)
    link.open()
    bridge = MavlinkBridge(fake.link(autopilot=link), bridge_config(port), io_period_ns=PERIOD_NS,
                           estimates=imu.pipeline)
    drive = lambda: bridge.tick(time.monotonic_ns())  # noqa: E731

    def beat(base_mode: int) -> None:
        autopilot.mav.heartbeat_send(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4, base_mode, 0,
                                     mavlink2.MAV_STATE_ACTIVE)

    armed = mavlink2.MAV_MODE_FLAG_SAFETY_ARMED | mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    try:
        connect(drive, gcs)
        assert until(lambda: (beat(armed), bridge.arming.armed)[1] is True)
        for params, sensor in ((GYRO_CAL, "gyro"), (MAG_CAL, "mag")):
            gcs.mav.command_long_send(1, 1, CAL, 0, *params)
            assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
            assert statustext(drive, gcs) == f"{sensor} calibration refused: the autopilot is armed"
        assert fake.calibrations == [] and bridge.stats()["writes_refused"] == 2

        assert until(lambda: (beat(mavlink2.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), bridge.arming.armed)[1] is False)
        gcs.mav.command_long_send(1, 1, CAL, 0, *GYRO_CAL)
        assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_ACCEPTED
        assert fake.calibrations == ["gyro"]
    finally:
        bridge.close()
        link.close()
        autopilot.close()
        gcs.close()


# ------------------------------------------------------------------------------ signing
def test_require_signing_for_writes_without_a_key_is_a_one_line_config_error():
    with pytest.raises(config_mod.ConfigError) as err:
        config_mod.validate({"mavlink": {"require_signing_for_writes": True}})
    text = str(err.value)
    assert "\n" not in text and "mavlink.require_signing_for_writes" in text and "mavlink.signing_key" in text
    assert config_mod.defaults()["mavlink"]["require_signing_for_writes"] is False


def test_require_signing_for_writes_refuses_and_counts_unsigned_writes():
    gcs, port = make_gcs()
    fake = FakeService()
    cfg = bridge_config(port, signing_key=KEY_HEX, require_signing_for_writes=True)
    bridge = MavlinkBridge(fake.link(), cfg, io_period_ns=PERIOD_NS)
    drive = lambda: bridge.tick(time.monotonic_ns())  # noqa: E731
    try:
        connect(drive, gcs)
        gcs.mav.param_set_send(1, 1, b"EST_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        gcs.mav.command_long_send(1, 1, INTERVAL, 0, mavlink2.MAVLINK_MSG_ID_ATTITUDE, -1, 0, 0, 0, 0, 0)
        assert until(lambda: (drive(), bridge.stats()["unsigned_rejected"])[1] >= 2)
        assert fake.params["beta"] == 0.1 and bridge.component.rates["ATTITUDE"] == 50.0
        assert bridge.stats()["writes_refused"] == 2

        gcs.setup_signing(bytes.fromhex(KEY_HEX), sign_outgoing=True)
        gcs.mav.param_set_send(1, 1, b"EST_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        value = wait_for(drive, gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "EST_BETA")
        assert value is not None and value.param_value == pytest.approx(0.5) and fake.params["beta"] == 0.5
        assert bridge.stats()["writes_accepted"] == 1 and bridge.stats()["unsigned_rejected"] == 2
    finally:
        bridge.close()
        gcs.close()


# ------------------------------------------------------------------------------ the record
def test_every_accepted_write_is_recorded_once_with_its_sender_and_no_op_writes_not_at_all(tmp_path):
    gcs, port = make_gcs(system_id=42, component_id=191)
    writer = FlightLogWriter(tmp_path, flush_interval_s=0.05, fsync=False)
    fake = FakeService(writer)
    imu = make_imu(5)
    bridge = MavlinkBridge(fake.link(), bridge_config(port), io_period_ns=PERIOD_NS, estimates=imu.pipeline)
    drive = lambda: bridge.tick(time.monotonic_ns())  # noqa: E731

    def param_set(name: bytes, value: float) -> None:
        gcs.mav.param_set_send(1, 1, name, value, mavlink2.MAV_PARAM_TYPE_REAL32)
        answer = wait_for(drive, gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == name.decode())
        assert answer is not None

    try:
        connect(drive, gcs)
        for _ in range(3):  # the first changes it; the same value again (float32 on the wire) does not
            param_set(b"EST_BETA", 0.25)
        param_set(b"EST_BETA", 0.1)
        param_set(b"EST_BETA", np.float32(0.1))  # the value in force, as PARAM_VALUE showed it
        param_set(b"MAG_DECL_DEG", 180.0)
        param_set(b"MAG_DECL_DEG", 180.0)
        param_set(b"RATE_ATT_HZ", 10.0)
        param_set(b"RATE_ATT_HZ", 500.0)  # above its maximum: refused
        gcs.mav.command_long_send(1, 1, INTERVAL, 0, QUATERNION_ID, 100_000, 0, 0, 0, 0, 0)
        assert ack(drive, gcs, INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED
        gcs.mav.command_long_send(1, 1, INTERVAL, 0, QUATERNION_ID, 100_000, 0, 0, 0, 0, 0)
        assert ack(drive, gcs, INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED  # in force already
        gcs.mav.command_long_send(1, 1, CAL, 0, *MAG_CAL)
        assert ack(drive, gcs, CAL).result == mavlink2.MAV_RESULT_ACCEPTED
        stats = bridge.stats()
    finally:
        bridge.close()
        gcs.close()
        writer.close()
    assert fake.declination == 180.0 and bridge.component.rates["ATTITUDE"] == 10.0

    params, logs = [], []
    with open(writer.files[0], "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/params", "/log"]):
            (params if channel.topic == "/params" else logs).append(json.loads(message.data))
    who = "mavlink 42/191 unsigned"
    assert [(p["name"], p["old"], p["new"], p["source"]) for p in params] == [
        ("beta", 0.1, 0.25, who),
        ("beta", 0.25, pytest.approx(0.1), who),
        ("MAG_DECL_DEG", 0.0, 180.0, who),
        ("RATE_ATT_HZ", 50.0, 10.0, who),
        ("ATTITUDE_QUATERNION rate Hz", 50.0, 10.0, who),
        ("calibration", None, "mag", who),
    ]
    assert len(logs) == len(params) and all(who in entry["message"] for entry in logs)
    assert stats["writes_accepted"] == 6 and stats["writes_refused"] == 1
