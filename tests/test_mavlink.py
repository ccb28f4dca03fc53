"""MAVLink component against a real pymavlink ground station over UDP on 127.0.0.1.

The ground station (GCS) listens with ``udpin:127.0.0.1:0`` (the OS picks a free port); the
component sends to it with ``udpout`` and the GCS's commands flow back over the same UDP
association. Publishing is driven with a simulated monotonic clock, so rates and schedules
are checked by counting messages, never by timing the machine.
"""

from __future__ import annotations

import math
import os
import random
import time

import pytest

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from ahrs_service.protocols.mavlink import (  # noqa: E402
    Identity,
    MavlinkComponent,
    ParameterTable,
    SensorStatus,
    Telemetry,
)
from ahrs_service.protocols.mavlink.attitude import (  # noqa: E402
    attitude_frame,
    attitude_quaternion_frame,
    encode_attitude,
    encode_attitude_quaternion,
)
from ahrs_service.protocols.mavlink.health import split_statustext  # noqa: E402

pytestmark = pytest.mark.timeout(60)

KEY = bytes(range(32))
STEP_NS = 5_000_000  # simulated publish loop: 200 Hz


# ------------------------------------------------------------------------------ helpers
def make_gcs(system_id: int = 255, component_id: int = 190):
    """A pymavlink ground station listening on a free loopback port; returns (conn, port)."""
    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=system_id, source_component=component_id)
    # a MAVLink 2 common parser whatever dialect another test left mavutil set to
    gcs.mav = mavlink2.MAVLink(gcs, srcSystem=system_id, srcComponent=component_id)
    gcs.mav.robust_parsing = True
    gcs.first_byte = False
    gcs.WIRE_PROTOCOL_VERSION = "2.0"
    return gcs, gcs.port.getsockname()[1]


def drain(gcs, limit: int = 10_000) -> list:
    out = []
    for _ in range(limit):
        m = gcs.recv_msg()
        if m is None:
            break
        if m.get_type() != "BAD_DATA":
            out.append(m)
    return out


def telemetry(t_ms: int, q=(1.0, 0.0, 0.0, 0.0), **kw) -> Telemetry:
    return Telemetry.from_quaternion(t_ms, q, kw.pop("body_rate", (0.01, -0.02, 0.03)), **kw)


def run(comp, gcs, seconds: float, start_ns: int = 0, step_ns: int = STEP_NS, tel=None) -> list:
    """Publishes over ``seconds`` of simulated time (telemetry time = simulated time); returns
    everything the GCS received."""
    got = []
    steps = int(round(seconds * 1e9 / step_ns))
    for i in range(steps):
        now = start_ns + i * step_ns
        comp.publish(now, tel(now) if tel else telemetry(now // 1_000_000))
        comp.poll()
        if i % 10 == 0:
            got += drain(gcs)
    deadline = time.monotonic() + 1.0
    while time.monotonic() < deadline:  # bounded wait for the last datagrams
        more = drain(gcs)
        got += more
        if not more:
            time.sleep(0.02)
            if not (more := drain(gcs)):
                break
            got += more
    return got


def exchange(comp, gcs, want, timeout: float = 3.0, n: int = 1) -> list:
    """Polls the component and drains the GCS until ``n`` messages satisfying ``want`` arrived
    (bounded by ``timeout``); returns everything received."""
    got = []
    deadline = time.monotonic() + timeout
    for _ in range(10_000):
        comp.poll()
        got += drain(gcs)
        if sum(1 for m in got if want(m)) >= n or time.monotonic() > deadline:
            break
        time.sleep(0.005)
    return got


def settle(comp, gcs, seconds: float = 0.3) -> list:
    """Polls and drains for a short bounded while (to show that *no* answer comes)."""
    got = []
    deadline = time.monotonic() + seconds
    for _ in range(1000):
        comp.poll()
        got += drain(gcs)
        if time.monotonic() > deadline:
            break
        time.sleep(0.01)
    return got


def of(msgs, name):
    return [m for m in msgs if m.get_type() == name]


def connect(comp, gcs) -> None:
    """One heartbeat from the component so the GCS knows where to send its requests."""
    comp.send_now("HEARTBEAT")
    got = exchange(comp, gcs, lambda m: m.get_type() == "HEARTBEAT")
    assert of(got, "HEARTBEAT")


@pytest.fixture
def gcs():
    conn, port = make_gcs()
    yield conn, port
    conn.close()


@pytest.fixture
def store():
    return {"beta": 0.1, "rate": 200, "mag": 1.0}


@pytest.fixture
def params(store):
    changes = []
    table = ParameterTable()
    table.add("AHRS_BETA", lambda: store["beta"], lambda v: store.__setitem__("beta", v), minimum=0.0, maximum=1.0,
              on_change=lambda n, v: changes.append((n, v)))
    table.add("AHRS_RATE_HZ", lambda: store["rate"], lambda v: store.__setitem__("rate", v), param_type="INT32",
              minimum=10, maximum=1000)
    table.add("AHRS_VERSION", lambda: 3, param_type="INT32")  # read-only
    table.changes = changes
    return table


@pytest.fixture
def comp(gcs, params):
    _, port = gcs
    c = MavlinkComponent([f"udpout:127.0.0.1:{port}"], Identity(), params=params)
    yield c
    c.close()


# ------------------------------------------------------------------------------ rates
def test_default_rates_over_a_simulated_window(comp, gcs):
    conn, _ = gcs
    got = run(comp, conn, 2.0)
    # 2 s of simulated time: 50 Hz → 100, 1 Hz → 2; HIGHRES_IMU is off by default
    assert len(of(got, "ATTITUDE")) == 100
    assert len(of(got, "ATTITUDE_QUATERNION")) == 100
    assert len(of(got, "HEARTBEAT")) == 2
    assert len(of(got, "SYS_STATUS")) == 2
    assert of(got, "HIGHRES_IMU") == []
    assert comp.stats.sent["ATTITUDE"] == 100


def test_absolute_schedule_does_not_drift(gcs, params):
    conn, port = gcs
    # 30 Hz (period 33.3 ms) from a 7 ms loop: a "next = now + period" schedule would lose up
    # to 7 ms per message; the absolute one keeps every message within one loop step
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], rates={"ATTITUDE": 30, "ATTITUDE_QUATERNION": 0,
                                                               "SYS_STATUS": 0}) as c:
        got = run(c, conn, 3.0, step_ns=7_000_000)
    times = sorted(m.time_boot_ms for m in of(got, "ATTITUDE"))
    assert len(times) in (90, 91)
    errors = [t - k * 1000.0 / 30.0 for k, t in enumerate(times)]
    assert min(errors) >= 0.0
    assert max(errors) < 7.0


def test_late_loop_sends_each_stream_at_most_once_per_call(gcs):
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"]) as c:
        got = run(c, conn, 1.0, step_ns=50_000_000)  # a 20 Hz loop cannot carry 50 Hz
    assert len(of(got, "ATTITUDE")) == 20


def test_set_rate_changes_stream_and_rejects_bad_values(gcs):
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], rates={"HIGHRES_IMU": 25}) as c:
        c.set_rate("ATTITUDE", 10)
        got = run(c, conn, 1.0)
        with pytest.raises(ValueError):
            c.set_rate("GPS_RAW_INT", 5)
        with pytest.raises(ValueError):
            c.set_rate("ATTITUDE", -1)
    assert len(of(got, "ATTITUDE")) == 10
    assert len(of(got, "HIGHRES_IMU")) == 25


# ------------------------------------------------------------------------------ values
def test_attitude_values_round_trip(comp, gcs):
    conn, _ = gcs
    roll, pitch, yaw = 0.3, -0.2, 2.5
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    q = (cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
         cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy)
    tel = Telemetry.from_quaternion(987_654, q, (0.5, -0.25, 1.5))
    assert tel.roll == pytest.approx(roll, abs=1e-12) and tel.yaw == pytest.approx(yaw, abs=1e-12)
    comp.send_now("ATTITUDE", tel)
    comp.send_now("ATTITUDE_QUATERNION", tel)
    got = exchange(comp, conn, lambda m: m.get_type() == "ATTITUDE_QUATERNION")
    att, aq = of(got, "ATTITUDE")[0], of(got, "ATTITUDE_QUATERNION")[0]
    assert att.time_boot_ms == 987_654 and aq.time_boot_ms == 987_654
    # float32 on the wire
    assert (att.roll, att.pitch, att.yaw) == pytest.approx((roll, pitch, yaw), abs=1e-6)
    assert (att.rollspeed, att.pitchspeed, att.yawspeed) == pytest.approx((0.5, -0.25, 1.5), abs=1e-6)
    assert (aq.q1, aq.q2, aq.q3, aq.q4) == pytest.approx(q, abs=1e-6)
    assert (aq.rollspeed, aq.pitchspeed, aq.yawspeed) == pytest.approx((0.5, -0.25, 1.5), abs=1e-6)
    assert list(aq.repr_offset_q) == [1.0, 0.0, 0.0, 0.0]


def test_streamed_attitude_frames_are_byte_identical_to_pymavlink():
    """The pre-packed ATTITUDE/ATTITUDE_QUATERNION frames the streams send equal pymavlink's
    own packing over values, sequence numbers, ids, clock wrap and trailing-zero trimming."""
    rng = random.Random(20261122)
    cases = [
        telemetry(0, (1.0, 0.0, 0.0, 0.0), body_rate=(0.0, 0.0, 0.0)),  # ATTITUDE payload all zero: 1 byte kept
        telemetry(2**32 + 5, (0.0, 0.0, 0.0, 1.0), body_rate=(0.0, 0.0, 1e-3)),  # time wraps; yaw = π
        telemetry(7, (math.nan, 0.0, 0.0, 0.0), body_rate=(math.inf, -math.inf, 0.0)),
    ]
    for _ in range(200):
        q = [rng.gauss(0, 1) for _ in range(4)]
        n = math.sqrt(sum(c * c for c in q))
        cases.append(telemetry(rng.randrange(2**32), [c / n for c in q],
                               body_rate=[rng.uniform(-30, 30) for _ in range(3)]))
    for i, tel in enumerate(cases):
        mav = mavlink2.MAVLink(None, srcSystem=rng.randrange(1, 256), srcComponent=rng.randrange(256))
        mav.seq = i % 256
        assert attitude_frame(tel).pack(mav) == encode_attitude(tel).pack(mav), i
        assert attitude_quaternion_frame(tel).pack(mav) == encode_attitude_quaternion(tel).pack(mav), i
    assert len(attitude_frame(cases[0]).pack(mav)) == 10 + 1 + 2  # header, one payload byte, CRC
    mav.signing.sign_outgoing = True
    with pytest.raises(RuntimeError, match="signed"):
        attitude_frame(cases[0]).pack(mav)


def test_signed_component_signs_the_attitude_streams(gcs):
    conn, port = gcs
    conn.setup_signing(KEY, sign_outgoing=False)
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], signing_key=KEY,
                          rates={"ATTITUDE": 100.0, "ATTITUDE_QUATERNION": 100.0}) as c:
        got = run(c, conn, 0.1)
    streams = of(got, "ATTITUDE") + of(got, "ATTITUDE_QUATERNION")
    assert len(streams) == 20
    assert all(m.get_signed() for m in streams)  # verified with the key on the GCS side


def test_highres_imu_units_and_update_bits(comp, gcs):
    conn, _ = gcs
    full = telemetry(1000, gyr=(0.1, -0.2, 0.3), acc=(0.5, -0.4, -9.81), mag=(20.0, -5.0, 43.0), temperature_c=31.5,
                     time_usec=1_000_123)
    no_mag = telemetry(1010, gyr=(0.1, -0.2, 0.3), acc=(0.5, -0.4, -9.81))
    comp.send_now("HIGHRES_IMU", full)
    comp.send_now("HIGHRES_IMU", no_mag)
    got = exchange(comp, conn, lambda m: m.get_type() == "HIGHRES_IMU" and m.time_usec == 1_010_000)
    a, b = of(got, "HIGHRES_IMU")
    assert a.time_usec == 1_000_123
    assert (a.xacc, a.yacc, a.zacc) == pytest.approx((0.5, -0.4, -9.81), abs=1e-6)
    assert (a.xgyro, a.ygyro, a.zgyro) == pytest.approx((0.1, -0.2, 0.3), abs=1e-6)
    assert (a.xmag, a.ymag, a.zmag) == pytest.approx((0.20, -0.05, 0.43), abs=1e-6)  # gauss = µT / 100
    assert a.temperature == pytest.approx(31.5)
    assert a.fields_updated == 0x003F | 0x01C0 | 0x1000
    assert b.fields_updated == 0x003F
    assert b.xmag == 0.0


def test_sys_status_bits_and_load(comp, gcs):
    conn, _ = gcs
    gyro, accel, mag = (mavlink2.MAV_SYS_STATUS_SENSOR_3D_GYRO, mavlink2.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
                        mavlink2.MAV_SYS_STATUS_SENSOR_3D_MAG)
    ahrs = mavlink2.MAV_SYS_STATUS_AHRS
    tel = telemetry(5, mag_status=SensorStatus(True, True, False), reduced_mode=True, load_percent=37.54,
                    accel=SensorStatus(True, True, False), comm_errors=7, overruns=70_000, sensor_faults=3)
    comp.send_now("SYS_STATUS", tel)
    comp.send_now("HEARTBEAT", tel)
    got = exchange(comp, conn, lambda m: m.get_type() == "HEARTBEAT")
    s = of(got, "SYS_STATUS")[0]
    assert s.onboard_control_sensors_present == gyro | accel | mag | ahrs
    assert s.onboard_control_sensors_enabled == gyro | accel | ahrs  # reduced mode: mag not used
    assert s.onboard_control_sensors_health == gyro | ahrs  # accel and mag unhealthy
    assert s.load == 375
    assert (s.errors_comm, s.errors_count1, s.errors_count2) == (7, 65535, 3)
    assert (s.voltage_battery, s.current_battery, s.battery_remaining) == (65535, -1, -1)
    assert of(got, "HEARTBEAT")[0].system_status == mavlink2.MAV_STATE_CRITICAL


def test_statustext_short_and_chunked(comp, gcs):
    conn, _ = gcs
    long_text = "gyro calibration done: bias " + ", ".join(f"{v:.6f}" for v in (0.001234, -0.000321, 0.0042)) * 3
    assert len(long_text) > 100
    comp.statustext(mavlink2.MAV_SEVERITY_INFO, "short")
    comp.statustext(mavlink2.MAV_SEVERITY_NOTICE, long_text)
    n_chunks = len(long_text) // 50 + 1
    got = exchange(comp, conn, lambda m: m.get_type() == "STATUSTEXT" and m.chunk_seq == n_chunks - 1)
    texts = of(got, "STATUSTEXT")
    assert (texts[0].text, texts[0].id, texts[0].chunk_seq, texts[0].severity) == ("short", 0, 0, 6)
    chunks = texts[1:]
    assert [c.chunk_seq for c in chunks] == list(range(n_chunks))
    assert len({c.id for c in chunks}) == 1 and chunks[0].id != 0
    assert "".join(c.text for c in chunks) == long_text


def test_statustext_split_rules():
    assert split_statustext("x" * 50) == [b"x" * 50]
    assert split_statustext("x" * 100) == [b"x" * 50, b"x" * 50, b""]  # empty chunk marks the end
    parts = split_statustext("é" * 40)  # 80 bytes of 2-byte characters
    assert [len(p) for p in parts] == [50, 30]
    assert b"".join(parts).decode("utf-8") == "é" * 40
    odd = split_statustext("a" + "é" * 40)
    assert all(len(p) <= 50 for p in odd)
    # no character is cut in two: every chunk decodes on its own, and together they are the text
    assert "".join(p.decode("utf-8") for p in odd) == "a" + "é" * 40


# ------------------------------------------------------------------------------ parameters
def test_param_list_read_and_set(comp, gcs, params, store):
    conn, _ = gcs
    connect(comp, conn)
    conn.mav.param_request_list_send(1, 1)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE" and m.param_index == 2)
    values = {m.param_id: m for m in of(got, "PARAM_VALUE")}
    assert set(values) == {"AHRS_BETA", "AHRS_RATE_HZ", "AHRS_VERSION"}
    assert all(m.param_count == 3 for m in values.values())
    assert [values[n].param_index for n in ("AHRS_BETA", "AHRS_RATE_HZ", "AHRS_VERSION")] == [0, 1, 2]
    assert values["AHRS_BETA"].param_value == pytest.approx(0.1, abs=1e-7)
    assert values["AHRS_BETA"].param_type == mavlink2.MAV_PARAM_TYPE_REAL32
    rate = values["AHRS_RATE_HZ"]
    assert (rate.param_value, rate.param_type) == (200.0, mavlink2.MAV_PARAM_TYPE_INT32)

    conn.mav.param_request_read_send(1, 1, b"AHRS_RATE_HZ", -1)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert [(m.param_id, m.param_index) for m in of(got, "PARAM_VALUE")] == [("AHRS_RATE_HZ", 1)]
    conn.mav.param_request_read_send(1, 1, b"", 2)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert [m.param_id for m in of(got, "PARAM_VALUE")] == ["AHRS_VERSION"]

    conn.mav.param_set_send(1, 1, b"AHRS_BETA", 0.25, mavlink2.MAV_PARAM_TYPE_REAL32)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert of(got, "PARAM_VALUE")[0].param_value == pytest.approx(0.25)
    assert store["beta"] == pytest.approx(0.25) and params.get("AHRS_BETA") == pytest.approx(0.25)
    assert params.changes == [("AHRS_BETA", pytest.approx(0.25))]

    conn.mav.param_set_send(1, 1, b"AHRS_RATE_HZ", 400.0, mavlink2.MAV_PARAM_TYPE_INT32)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert of(got, "PARAM_VALUE")[0].param_value == 400.0 and store["rate"] == 400
    assert isinstance(store["rate"], int)


@pytest.mark.parametrize("name, value, reason", [
    (b"AHRS_BETA", 1.5, "above maximum"),
    (b"AHRS_BETA", float("nan"), "not a finite number"),
    (b"AHRS_RATE_HZ", 250.5, "not an integer"),
    (b"AHRS_VERSION", 4.0, "read-only"),
])
def test_param_set_rejected_answers_current_value(comp, gcs, store, name, value, reason):
    conn, _ = gcs
    connect(comp, conn)
    before = dict(store)
    conn.mav.param_set_send(1, 1, name, value, mavlink2.MAV_PARAM_TYPE_REAL32)
    got = exchange(comp, conn, lambda m: m.get_type() == "STATUSTEXT")
    answer = of(got, "PARAM_VALUE")
    assert len(answer) == 1 and answer[0].param_id == name.decode()
    current = {"AHRS_BETA": before["beta"], "AHRS_RATE_HZ": before["rate"], "AHRS_VERSION": 3}[name.decode()]
    assert answer[0].param_value == pytest.approx(current)
    assert store == before
    text = "".join(m.text for m in of(got, "STATUSTEXT"))
    assert f"{name.decode()} rejected" in text and reason in text


def test_param_requests_for_other_targets_are_ignored(comp, gcs, store):
    conn, _ = gcs
    connect(comp, conn)
    conn.mav.param_set_send(2, 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)  # other system
    conn.mav.param_set_send(0, 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)  # broadcast write
    conn.mav.param_request_list_send(1, 5)  # other component
    got = settle(comp, conn)
    assert of(got, "PARAM_VALUE") == []
    assert store["beta"] == 0.1
    assert comp.stats.not_for_us == 3
    conn.mav.param_request_read_send(0, 0, b"AHRS_BETA", -1)  # broadcast read is answered
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert [m.param_id for m in of(got, "PARAM_VALUE")] == ["AHRS_BETA"]


def test_param_set_unknown_name_and_refusing_setter(gcs):
    conn, port = gcs
    changes = []

    def refuse(v):
        raise ValueError("estimator is running")

    table = ParameterTable()
    table.add("AHRS_MODE", lambda: 1, refuse, param_type="INT32", on_change=lambda n, v: changes.append(v))
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], params=table) as c:
        connect(c, conn)
        conn.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, mavlink2.MAV_PARAM_TYPE_REAL32)
        got = exchange(c, conn, lambda m: m.get_type() == "STATUSTEXT")
        assert of(got, "PARAM_VALUE") == []
        assert "unknown parameter NO_SUCH_PARAM" in of(got, "STATUSTEXT")[0].text
        conn.mav.param_set_send(1, 1, b"AHRS_MODE", 2.0, mavlink2.MAV_PARAM_TYPE_INT32)
        got = exchange(c, conn, lambda m: m.get_type() == "STATUSTEXT")
        assert [m.param_value for m in of(got, "PARAM_VALUE")] == [1.0]
        assert "estimator is running" in "".join(m.text for m in of(got, "STATUSTEXT"))
        assert changes == []


def test_poll_handles_at_most_max_messages(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    for _ in range(5):
        conn.mav.param_request_read_send(1, 1, b"AHRS_BETA", -1)
    # poll until all five requests are handled (bounded): never more than two per call
    handled = []
    deadline = time.monotonic() + 5.0
    while sum(handled) < 5 and time.monotonic() < deadline:
        before = comp.stats.received.get("PARAM_REQUEST_READ", 0)
        handled.append(comp.poll(max_messages=2))
        assert comp.stats.received.get("PARAM_REQUEST_READ", 0) - before == handled[-1] <= 2
        if not handled[-1]:
            time.sleep(0.005)
    # loopback queues each datagram before sendto returns, so a call finds more than two
    # waiting: the cap is reached (and it held: the five took at least three calls)
    assert sum(handled) == 5 and max(handled) == 2
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE", n=5)
    assert len(of(got, "PARAM_VALUE")) == 5
    assert comp.stats.received["PARAM_REQUEST_READ"] == 5


def test_parameter_table_validation():
    table = ParameterTable()
    with pytest.raises(ValueError):
        table.add("A_NAME_LONGER_THAN_16", lambda: 1.0)
    table.add("OK", lambda: 1.0)
    with pytest.raises(ValueError):
        table.add("OK", lambda: 2.0)
    with pytest.raises(ValueError):
        table.add("BAD_TYPE", lambda: 1, param_type="UINT8")


def test_bytewise_int_encoding_round_trips():
    import struct
    n = {"v": 123456789}
    table = ParameterTable(encoding="bytewise")
    table.add("BIG", lambda: n["v"], lambda v: n.__setitem__("v", v), param_type="INT32")
    p = next(iter(table))
    wire = table.encode_value(p)
    assert struct.unpack("<i", struct.pack("<f", wire))[0] == 123456789
    assert table.decode_value(p, struct.unpack("<f", struct.pack("<i", -42))[0], mavlink2.MAV_PARAM_TYPE_INT32) == -42


# ------------------------------------------------------------------------------ commands
def ack_of(got, command):
    acks = [m for m in of(got, "COMMAND_ACK") if m.command == command]
    assert len(acks) == 1, got
    return acks[0]


def test_set_message_interval_changes_observed_rate(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    cmd = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 100_000, 0, 0, 0, 0, 0)  # ATTITUDE every 100 ms
    conn.mav.command_long_send(1, 1, cmd, 0, 31, -1, 0, 0, 0, 0, 0)  # ATTITUDE_QUATERNION off
    conn.mav.command_long_send(1, 1, cmd, 0, 105, 20_000, 0, 0, 0, 0, 0)  # HIGHRES_IMU at 50 Hz
    got = exchange(comp, conn, lambda m: m.get_type() == "COMMAND_ACK", n=3)
    acks = of(got, "COMMAND_ACK")
    assert [(a.command, a.result) for a in acks] == [(cmd, mavlink2.MAV_RESULT_ACCEPTED)] * 3
    assert (acks[0].target_system, acks[0].target_component) == (255, 190)
    assert comp.rates["ATTITUDE"] == pytest.approx(10.0)
    got = run(comp, conn, 2.0, start_ns=10_000_000_000)
    assert len(of(got, "ATTITUDE")) == 20
    assert of(got, "ATTITUDE_QUATERNION") == []
    assert len(of(got, "HIGHRES_IMU")) == 100

    conn.mav.command_long_send(1, 1, cmd, 0, 30, 0, 0, 0, 0, 0, 0)  # back to the default rate
    conn.mav.command_long_send(1, 1, cmd, 0, 33, 100_000, 0, 0, 0, 0, 0)  # GLOBAL_POSITION_INT: not ours
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 100, 0, 0, 0, 0, 0)  # 10 kHz: too fast
    got = exchange(comp, conn, lambda m: m.get_type() == "COMMAND_ACK", n=3)
    assert [a.result for a in of(got, "COMMAND_ACK")] == [mavlink2.MAV_RESULT_ACCEPTED, mavlink2.MAV_RESULT_DENIED,
                                                         mavlink2.MAV_RESULT_DENIED]
    got = run(comp, conn, 1.0, start_ns=20_000_000_000)
    assert len(of(got, "ATTITUDE")) == 50


def test_get_message_interval(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 31, 0, 0, 0, 0, 0, 0)
    conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 105, 0, 0, 0, 0, 0, 0)
    got = exchange(comp, conn, lambda m: m.get_type() == "MESSAGE_INTERVAL" and m.message_id == 105)
    intervals = {m.message_id: m.interval_us for m in of(got, "MESSAGE_INTERVAL")}
    assert intervals == {31: 20_000, 105: -1}


def test_request_message(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    cmd = mavlink2.MAV_CMD_REQUEST_MESSAGE
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 0, 0, 0, 0, 0, 0)  # no estimate yet
    got = exchange(comp, conn, lambda m: m.get_type() == "COMMAND_ACK")
    assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
    assert of(got, "ATTITUDE") == []

    comp.set_rate("ATTITUDE", 0)
    comp.publish(0, telemetry(4242))
    drain(conn)
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 0, 0, 0, 0, 0, 0)
    got = exchange(comp, conn, lambda m: m.get_type() == "ATTITUDE")
    assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_ACCEPTED
    assert [m.time_boot_ms for m in of(got, "ATTITUDE")] == [4242]
    assert got.index(of(got, "COMMAND_ACK")[0]) < got.index(of(got, "ATTITUDE")[0])  # ACK first

    conn.mav.command_long_send(1, 1, cmd, 0, 148, 0, 0, 0, 0, 0, 0)
    got = exchange(comp, conn, lambda m: m.get_type() == "AUTOPILOT_VERSION")
    caps = of(got, "AUTOPILOT_VERSION")[0].capabilities
    assert caps & mavlink2.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert caps & mavlink2.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST

    conn.mav.command_long_send(1, 1, cmd, 0, 24, 0, 0, 0, 0, 0, 0)  # GPS_RAW_INT: no GPS here
    got = exchange(comp, conn, lambda m: m.get_type() == "COMMAND_ACK")
    assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_DENIED


def test_an_attitude_only_telemetry_serves_the_attitude_streams_alone(gcs):
    """The bridge builds the full snapshot (health, readings, vibration) only when a stream
    other than ATTITUDE / ATTITUDE_QUATERNION is due: the component says when, publishes an
    attitude-only one on those two streams, refuses it when another is due (sending nothing),
    and answers a request from a full snapshot of now (``current_telemetry``)."""
    conn, port = gcs
    now_counters = {"lost_samples": 41}

    def current() -> Telemetry:
        return telemetry(777, **now_counters)

    rates = {"HEARTBEAT": 1, "ATTITUDE": 100, "ATTITUDE_QUATERNION": 100, "SYS_STATUS": 1, "VIBRATION": 0}
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], rates=rates, current_telemetry=current) as c:
        light = Telemetry.from_quaternion(5, (1.0, 0.0, 0.0, 0.0), (0.1, 0.2, 0.3), attitude_only=True)
        assert not c.only_attitude_due(0)  # the first call starts every stream: HEARTBEAT, SYS_STATUS due
        with pytest.raises(ValueError, match="attitude-only"):
            c.publish(0, light)
        assert c.stats.sent == {}  # refused before anything went out
        assert c.publish(0, telemetry(0, lost_samples=3)) == 4
        assert c.only_attitude_due(10_000_000)  # 10 ms on: ATTITUDE and ATTITUDE_QUATERNION alone
        assert c.publish(10_000_000, light) == 2
        assert not c.only_attitude_due(1_000_000_000)  # 1 s on: HEARTBEAT and SYS_STATUS again
        got = drain(conn) + settle(c, conn, 0.1)
        assert [m.rollspeed for m in of(got, "ATTITUDE") if m.time_boot_ms == 5] == [pytest.approx(0.1)]
        assert [m.errors_count3 for m in of(got, "SYS_STATUS")] == [3]  # from the full snapshot only
        connect(c, conn)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_REQUEST_MESSAGE, 0, 1, 0, 0, 0, 0, 0, 0)  # SYS_STATUS
        got = exchange(c, conn, lambda m: m.get_type() == "SYS_STATUS")
        assert [m.errors_count3 for m in of(got, "SYS_STATUS")] == [41]  # now's, not the last published


def test_preflight_calibration_callbacks(gcs):
    conn, port = gcs
    state = {"at_rest": True, "calls": []}

    def gyro(action):
        state["calls"].append(action)
        if not state["at_rest"]:
            return mavlink2.MAV_RESULT_TEMPORARILY_REJECTED, "gyro calibration: keep the vehicle still"
        return mavlink2.MAV_RESULT_ACCEPTED, "gyro calibration started"

    def accel(action):
        raise RuntimeError("accelerometer not responding")

    cmd = mavlink2.MAV_CMD_PREFLIGHT_CALIBRATION
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], gyro_calibration=gyro, accel_calibration=accel) as c:
        connect(c, conn)
        conn.mav.command_long_send(1, 1, cmd, 0, 1, 0, 0, 0, 0, 0, 0)
        got = exchange(c, conn, lambda m: m.get_type() == "STATUSTEXT")
        assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_ACCEPTED
        assert of(got, "STATUSTEXT")[0].text == "gyro calibration started"

        state["at_rest"] = False
        conn.mav.command_long_send(1, 1, cmd, 0, 1, 0, 0, 0, 0, 0, 0)
        got = exchange(c, conn, lambda m: m.get_type() == "STATUSTEXT")
        assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_TEMPORARILY_REJECTED
        assert "still" in of(got, "STATUSTEXT")[0].text
        assert state["calls"] == [1, 1]

        conn.mav.command_long_send(1, 1, cmd, 0, 0, 1, 0, 0, 0, 0, 0)  # mag: no callback
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_UNSUPPORTED

        conn.mav.command_long_send(1, 1, cmd, 0, 0, 0, 0, 0, 1, 0, 0)  # accel: callback raises
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_FAILED
        assert c.stats.handler_errors == 1

        conn.mav.command_long_send(1, 1, cmd, 0, 1, 0, 0, 0, 1, 0, 0)  # two sensors at once
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack_of(got, cmd).result == mavlink2.MAV_RESULT_DENIED
        assert state["calls"] == [1, 1]

        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0)
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack_of(got, mavlink2.MAV_CMD_DO_SET_MODE).result == mavlink2.MAV_RESULT_UNSUPPORTED

        conn.mav.command_int_send(1, 1, 0, mavlink2.MAV_CMD_REQUEST_MESSAGE, 0, 0, 30, 0, 0, 0, 0, 0, 0)
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert ack_of(got, mavlink2.MAV_CMD_REQUEST_MESSAGE).result == mavlink2.MAV_RESULT_COMMAND_LONG_ONLY


# ------------------------------------------------------------------------------ signing
def test_signing_rejects_unsigned_writes_and_accepts_signed(gcs, params, store):
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], params=params, signing_key=KEY) as c:
        connect(c, conn)
        conn.mav.param_set_send(1, 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, -1, 0, 0, 0, 0, 0)
        got = settle(c, conn)
        assert of(got, "PARAM_VALUE") == [] and of(got, "COMMAND_ACK") == []
        assert store["beta"] == 0.1 and c.rates["ATTITUDE"] == 50.0
        assert c.stats.unsigned_rejected == 2
        assert c.stats.malformed == 0  # rejected writes are not counted as malformed
        # outgoing messages carry a signature
        c.send_now("HEARTBEAT")
        hb = of(exchange(c, conn, lambda m: m.get_type() == "HEARTBEAT"), "HEARTBEAT")[0]
        assert hb.get_header().incompat_flags & mavlink2.MAVLINK_IFLAG_SIGNED

        # read-only requests are served unsigned
        conn.mav.param_request_read_send(1, 1, b"AHRS_BETA", -1)
        got = exchange(c, conn, lambda m: m.get_type() == "PARAM_VALUE")
        assert of(got, "PARAM_VALUE")[0].param_value == pytest.approx(0.1)

        # a wrong key is as good as none
        conn.setup_signing(bytes(32), sign_outgoing=True, link_id=1)
        conn.mav.param_set_send(1, 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        got = settle(c, conn)
        assert of(got, "PARAM_VALUE") == [] and store["beta"] == 0.1
        assert c.stats.unsigned_rejected == 3

        conn.setup_signing(KEY, sign_outgoing=True, link_id=2)
        conn.mav.param_set_send(1, 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, -1, 0, 0, 0, 0, 0)
        got = exchange(c, conn, lambda m: m.get_type() == "COMMAND_ACK")
        assert of(got, "PARAM_VALUE")[0].param_value == pytest.approx(0.5) and store["beta"] == 0.5
        assert of(got, "PARAM_VALUE")[0].get_signed()  # verified with the key on the GCS side
        assert ack_of(got, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL).result == mavlink2.MAV_RESULT_ACCEPTED
        assert c.rates["ATTITUDE"] == 0.0
        assert c.stats.unsigned_rejected == 3


def test_forged_future_timestamp_does_not_lock_out_the_real_sender(gcs, params, store):
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], params=params, signing_key=KEY) as c:
        connect(c, conn)
        peer = next(iter(conn.clients))
        # same link id and source as the real GCS, wrong key, timestamp ten years ahead
        # (signing timestamps count 10 µs units since 2015-01-01)
        future = int((time.time() - 1420070400 + 10 * 365 * 86400) * 1e5)
        forger = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        forger.signing.secret_key, forger.signing.sign_outgoing = bytes(32), True
        forger.signing.link_id, forger.signing.timestamp = 7, future
        forged = mavlink2.MAVLink_param_set_message(1, 1, b"AHRS_BETA", 0.9, mavlink2.MAV_PARAM_TYPE_REAL32)
        conn.port.sendto(forged.pack(forger), peer)
        assert of(settle(c, conn), "PARAM_VALUE") == [] and store["beta"] == 0.1
        conn.setup_signing(KEY, sign_outgoing=True, link_id=7)
        conn.mav.param_set_send(1, 1, b"AHRS_BETA", 0.3, mavlink2.MAV_PARAM_TYPE_REAL32)
        got = exchange(c, conn, lambda m: m.get_type() == "PARAM_VALUE")
        assert [m.param_value for m in of(got, "PARAM_VALUE")] == [pytest.approx(0.3)]
        assert store["beta"] == pytest.approx(0.3)
        assert c.stats.unsigned_rejected == 1


def test_signing_key_must_be_32_bytes(gcs):
    _, port = gcs
    with pytest.raises(ValueError):
        MavlinkComponent([f"udpout:127.0.0.1:{port}"], signing_key=b"short")


# ------------------------------------------------------------------------------ robustness
def test_garbage_and_truncated_input_is_counted_and_survived(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    peer = next(iter(conn.clients))
    raw = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)

    def packed(msg):
        return bytearray(msg.pack(raw))

    read = packed(mavlink2.MAVLink_param_request_read_message(1, 1, b"AHRS_BETA", -1))
    conn.port.sendto(b"\x00\x01garbage without a start byte\x7f" * 3, peer)
    conn.port.sendto(bytes(read[:12]), peer)  # truncated datagram ...
    conn.port.sendto(bytes(read), peer)  # ... must not spoil the good one after it
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert [m.param_id for m in of(got, "PARAM_VALUE")] == ["AHRS_BETA"]

    bad_crc = packed(mavlink2.MAVLink_param_request_read_message(1, 1, b"AHRS_BETA", -1))
    bad_crc[-1] ^= 0xFF
    conn.port.sendto(bytes(bad_crc), peer)
    unknown = bytes([0xFD, 2, 0, 0, 0, 255, 190, 0x39, 0x30, 0x00, 1, 2, 0, 0])  # msg id 12345
    conn.port.sendto(unknown, peer)
    conn.port.sendto(bytes(read), peer)
    got = exchange(comp, conn, lambda m: m.get_type() == "PARAM_VALUE")
    assert [m.param_id for m in of(got, "PARAM_VALUE")] == ["AHRS_BETA"]
    assert comp.stats.malformed == 3  # garbage, truncated tail, bad CRC
    assert comp.stats.bad_crc == 1
    assert comp.stats.unknown_ids == 1
    assert comp.stats.received.get("PARAM_REQUEST_READ") == 2
    got = run(comp, conn, 0.5, start_ns=50_000_000_000)
    assert len(of(got, "ATTITUDE")) == 25  # publishing carries on


def test_streams_due_together_share_one_datagram(params):
    """What is due in one publish goes out as one UDP datagram per endpoint (as autopilots
    send), frames back to back with consecutive sequence numbers, and pymavlink splits it."""
    import socket

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(2.0)
    try:
        with MavlinkComponent([f"udpout:127.0.0.1:{sock.getsockname()[1]}"], params=params) as c:
            built = c.publish(0, telemetry(0))  # every stream is due at the start
            datagram = sock.recv(65536)
            parser = mavlink2.MAVLink(None)
            frames = parser.parse_buffer(datagram)
            names = [m.get_type() for m in frames]
            assert {"HEARTBEAT", "ATTITUDE", "ATTITUDE_QUATERNION"} <= set(names)
            assert len(names) == built >= 3
            seqs = [m.get_seq() for m in frames]
            assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
            assert sum(len(m.get_msgbuf()) for m in frames) == len(datagram)  # nothing else in it
    finally:
        sock.close()


def test_two_endpoints_and_a_failing_one(params, store):
    g1, p1 = make_gcs()
    g2, p2 = make_gcs(254, 191)
    try:
        # port 0 cannot be sent to: every send on that link fails, the others must not notice
        with MavlinkComponent(["udpout:127.0.0.1:0", f"udpout:127.0.0.1:{p1}", f"udpout:127.0.0.1:{p2}"],
                              params=params) as c:
            got1, got2 = [], []
            for i in range(40):
                c.publish(i * STEP_NS, telemetry(i * 5))
            deadline = time.monotonic() + 2.0
            for _ in range(1000):
                got1 += drain(g1)
                got2 += drain(g2)
                if (len(of(got1, "ATTITUDE")) >= 10 and len(of(got2, "ATTITUDE")) >= 10) or time.monotonic() > deadline:
                    break
                time.sleep(0.01)
            assert len(of(got1, "ATTITUDE")) == len(of(got2, "ATTITUDE")) == 10
            assert len(of(got1, "HEARTBEAT")) == len(of(got2, "HEARTBEAT")) == 1
            assert c.stats.send_errors["udpout:127.0.0.1:0"] == 22  # 10 + 10 + heartbeat + sys_status
            assert c.stats.sent["ATTITUDE"] == 20

            g2.mav.command_long_send(1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, 200_000, 0, 0, 0, 0, 0)
            got2 = exchange(c, g2, lambda m: m.get_type() == "COMMAND_ACK")
            assert ack_of(got2, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL).target_system == 254
            assert of(drain(g1), "COMMAND_ACK") == []  # the ACK goes back where the command came from

            g1.mav.param_set_send(1, 1, b"AHRS_BETA", 0.75, mavlink2.MAV_PARAM_TYPE_REAL32)
            got1 = exchange(c, g1, lambda m: m.get_type() == "PARAM_VALUE")
            got2 = exchange(c, g2, lambda m: m.get_type() == "PARAM_VALUE")
            # a new value is broadcast to every ground station
            assert of(got1, "PARAM_VALUE")[0].param_value == pytest.approx(0.75)
            assert of(got2, "PARAM_VALUE")[0].param_value == pytest.approx(0.75)
    finally:
        g1.close()
        g2.close()


# ------------------------------------------------------------------------------ identity
def test_standalone_identity(gcs):
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], Identity(system_id=42)) as c:
        c.publish(0, None)
        got = exchange(c, conn, lambda m: m.get_type() == "HEARTBEAT")
    hb = of(got, "HEARTBEAT")[0]
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (42, mavlink2.MAV_COMP_ID_AUTOPILOT1)
    assert (hb.type, hb.autopilot) == (mavlink2.MAV_TYPE_GENERIC, mavlink2.MAV_AUTOPILOT_GENERIC)
    assert (hb.system_status, hb.mavlink_version, hb.base_mode) == (mavlink2.MAV_STATE_BOOT, 3, 0)
    assert len(got) == 1  # without telemetry only the heartbeat goes out


def test_companion_identity_and_targeting(gcs, params):
    conn, port = gcs
    ident = Identity.companion(7)
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], ident, params=params) as c:
        c.publish(0, telemetry(0))
        got = exchange(c, conn, lambda m: m.get_type() == "ATTITUDE")
        hb = of(got, "HEARTBEAT")[0]
        assert (hb.get_srcSystem(), hb.get_srcComponent()) == (7, 200)
        assert (hb.type, hb.autopilot) == (mavlink2.MAV_TYPE_IMU, mavlink2.MAV_AUTOPILOT_INVALID)
        assert hb.system_status == mavlink2.MAV_STATE_ACTIVE
        assert of(got, "ATTITUDE")[0].get_srcComponent() == 200

        conn.mav.param_request_list_send(7, 1)  # the autopilot's parameters, not ours
        assert of(settle(c, conn), "PARAM_VALUE") == []
        conn.mav.param_request_list_send(7, 200)
        got = exchange(c, conn, lambda m: m.get_type() == "PARAM_VALUE" and m.param_index == 2)
        assert len(of(got, "PARAM_VALUE")) == 3


def test_identity_validation():
    with pytest.raises(ValueError):
        Identity(mode="autopilot")
    with pytest.raises(ValueError):
        Identity(system_id=0)
    assert Identity.standalone(3, mav_type=mavlink2.MAV_TYPE_SUBMARINE).mav_type == mavlink2.MAV_TYPE_SUBMARINE


def test_tcp_server_endpoint(params):
    import socket

    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    with MavlinkComponent([f"tcpin:127.0.0.1:{port}"], params=params) as c:
        gcs = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=255, source_component=190, retries=0)
        gcs.mav = mavlink2.MAVLink(gcs, srcSystem=255, srcComponent=190)
        gcs.mav.robust_parsing = True
        gcs.first_byte = False
        try:
            c.poll()  # accepts the connection
            gcs.mav.param_request_read_send(1, 1, b"AHRS_RATE_HZ", -1)
            got = []
            deadline = time.monotonic() + 3.0
            for i in range(1000):
                c.publish(i * STEP_NS, telemetry(i * 5))
                c.poll()
                got += drain(gcs)
                if (of(got, "PARAM_VALUE") and len(of(got, "ATTITUDE")) >= 5) or time.monotonic() > deadline:
                    break
                time.sleep(0.005)
            assert [m.param_value for m in of(got, "PARAM_VALUE")] == [200.0]
            times = [m.time_boot_ms for m in of(got, "ATTITUDE")]
            assert len(times) >= 5 and times == sorted(times)
        finally:
            gcs.close()


def test_due_tells_when_publish_would_send(gcs):
    """The service builds its telemetry snapshot only when ``due``: it must never hide a deadline."""
    conn, port = gcs
    with MavlinkComponent([f"udpout:127.0.0.1:{port}"], rates={"HEARTBEAT": 1.0, "ATTITUDE": 100.0,
                                                              "ATTITUDE_QUATERNION": 0.0, "HIGHRES_IMU": 0.0,
                                                              "SYS_STATUS": 0.0}) as c:
        assert c.due(0)  # nothing published yet
        assert c.publish(0, telemetry(0)) == 2  # HEARTBEAT and ATTITUDE
        sent = 0
        for now in range(1_000_000, 1_000_000_000, 1_000_000):  # 1 ms steps over one second
            if c.due(now):
                sent += c.publish(now, telemetry(now // 1_000_000))
            else:
                assert c.publish(now, telemetry(now // 1_000_000)) == 0
        assert sent == 99  # ATTITUDE at 10, 20, … 990 ms; the next heartbeat is due at 1 s
        assert not c.due(999_000_000) and c.due(1_000_000_000)
        c.set_rate("ATTITUDE", 50.0)  # a new schedule starts at once
        assert c.due(999_000_000)


# ------------------------------------------------------------------------------ issue 14: edges
def test_message_interval_beyond_its_int32_field_is_denied_and_get_still_answers(comp, gcs):
    conn, _ = gcs
    connect(comp, conn)
    cmd = mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 2.0**31, 0, 0, 0, 0, 0)  # 35.8 min: too slow
    conn.mav.command_long_send(1, 1, cmd, 0, 30, 100_000_000, 0, 0, 0, 0, 0)  # 100 s: the slowest
    got = exchange(comp, conn, lambda m: m.get_type() == "COMMAND_ACK", n=2)
    assert [a.result for a in of(got, "COMMAND_ACK")] == [mavlink2.MAV_RESULT_DENIED, mavlink2.MAV_RESULT_ACCEPTED]
    assert comp.stats.rates_refused == 1
    conn.mav.command_long_send(1, 1, mavlink2.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 30, 0, 0, 0, 0, 0, 0)
    got = exchange(comp, conn, lambda m: m.get_type() == "MESSAGE_INTERVAL")
    assert [m.interval_us for m in of(got, "MESSAGE_INTERVAL")] == [100_000_000]
    with pytest.raises(ValueError, match="0 \\(off\\) or 0.01 Hz"):
        comp.set_rate("ATTITUDE", 1.9e-6)


@pytest.mark.parametrize("value", [3e38, 1.4e-45, -1.0, 2.0])
def test_param_set_outside_bounds_or_real32_range_is_refused_with_the_current_value(comp, gcs, store, value):
    conn, _ = gcs
    connect(comp, conn)
    conn.mav.param_set_send(1, 1, b"AHRS_BETA", value, mavlink2.MAV_PARAM_TYPE_REAL32)
    got = exchange(comp, conn, lambda m: m.get_type() == "STATUSTEXT")
    assert [m.param_value for m in of(got, "PARAM_VALUE")] == [pytest.approx(0.1)]
    assert store["beta"] == 0.1 and "AHRS_BETA rejected" in of(got, "STATUSTEXT")[0].text


def test_statustext_of_a_param_set_flood_is_rate_limited_and_summarised(comp, gcs, monkeypatch):
    """An unsigned PARAM_SET flood with unknown names: BURST texts, then none until the bucket
    refills, then one carrying the count (driven by a fake clock: no sleeping)."""
    from ahrs_service.protocols.mavlink import component as comp_mod
    from ahrs_service.protocols.mavlink import statustext_limit

    conn, _ = gcs
    now = [10**12]
    monkeypatch.setattr(comp_mod.time, "monotonic_ns", lambda: now[0])
    connect(comp, conn)
    for i in range(200):
        conn.mav.param_set_send(1, 1, f"NOPE_{i}".encode(), 1.0, mavlink2.MAV_PARAM_TYPE_REAL32)
    got = settle(comp, conn, 0.5)
    texts = [m.text for m in of(got, "STATUSTEXT")]
    assert len(texts) == statustext_limit.BURST
    assert comp.stats.statustext_suppressed == 200 - statustext_limit.BURST
    # the service's own reports are never limited
    comp.statustext(mavlink2.MAV_SEVERITY_INFO, "own report")
    assert [m.text for m in of(settle(comp, conn, 0.3), "STATUSTEXT")] == ["own report"]
    now[0] += int(statustext_limit.PERIOD_S * 1e9)
    conn.mav.param_set_send(1, 1, b"NOPE_LAST", 1.0, mavlink2.MAV_PARAM_TYPE_REAL32)
    texts = [m.text for m in of(settle(comp, conn, 0.3), "STATUSTEXT")]
    assert texts == [f"unknown parameter NOPE_LAST (+{200 - statustext_limit.BURST} more)"]


def test_estimator_parameter_bounds_keep_over_the_air_values_sane():
    from ahrs_service.mavlink_bridge import EST_RANGE_FACTOR, estimator_param_bounds

    assert estimator_param_bounds(0.1) == (0.0, pytest.approx(0.1 * EST_RANGE_FACTOR))
    assert estimator_param_bounds(-2.0) == (-2.0 * EST_RANGE_FACTOR, 0.0)
    assert estimator_param_bounds(0.0) == (-EST_RANGE_FACTOR, EST_RANGE_FACTOR)


def test_udpin_peers_are_well_formed_senders_capped_and_expired(params, monkeypatch):
    """Issue 14: a udpin link sends to those that sent a valid frame, at most MAX_PEERS of them,
    each forgotten PEER_TIMEOUT_S after its last frame (fake clock: no sleeping)."""
    import socket

    from ahrs_service.protocols.mavlink import endpoints as ep_mod

    now = [10**12]
    monkeypatch.setattr(ep_mod.time, "monotonic_ns", lambda: now[0])
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    c = MavlinkComponent([f"udpin:127.0.0.1:{port}"], Identity(), params=params)
    try:
        ep = c._endpoints[0]
        hb = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
        frame = hb.heartbeat_encode(6, 8, 0, 0, 0).pack(hb)
        spoofers = []
        for i in range(3 * ep_mod.MAX_PEERS):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.sendto(frame if i % 3 else b"\xfd\x09garbage", ("127.0.0.1", port))  # a third send garbage
            spoofers.append(s)
        gcs_conn, _ = make_gcs()
        gcs_conn.port.sendto(frame, ("127.0.0.1", port))  # the ground station speaks last
        valid = 2 * ep_mod.MAX_PEERS + 1  # the garbage datagrams parse to no message at all
        handled = 0
        for _ in range(400):
            handled += c.poll(1000)
            if handled >= valid:
                break
            time.sleep(0.005)
        assert handled == valid
        assert len(ep.peers) == ep_mod.MAX_PEERS
        assert ep.peers.evicted == 2 * ep_mod.MAX_PEERS + 1 - ep_mod.MAX_PEERS
        assert gcs_conn.port.getsockname() in ep.peers.live(now[0])
        c.send_now("HEARTBEAT")
        assert of(drain(gcs_conn), "HEARTBEAT")
        garbage_senders = {spoofers[i].getsockname() for i in range(0, len(spoofers), 3)}
        assert not garbage_senders & ep.peers.live(now[0])
        now[0] += int(ep_mod.PEER_TIMEOUT_S * 1e9) + 1
        c.send_now("HEARTBEAT")
        assert len(ep.peers) == 0 and ep.peers.expired == ep_mod.MAX_PEERS
        for s in spoofers:
            s.close()
        gcs_conn.close()
    finally:
        c.close()


def test_udpin_peers_a_flood_of_new_addresses_does_not_push_out_a_live_ground_station():
    """Issue 14 re-probe: with the cap replacing the least recently heard peer, 60 addresses
    sending in rounds starved a ground station beating at 1 Hz (2 of ~150 ATTITUDE reached it
    in 3 s). A newcomer now replaces a one-frame peer or one silent PEER_STALE_S, else it is
    not served (fake clock)."""
    from ahrs_service.protocols.mavlink import endpoints as ep_mod

    peers = ep_mod.UdpPeers()
    gcs, t = ("127.0.0.1", 14550), 10**12
    peers.heard(gcs, t)
    flood = [("127.0.0.1", 20000 + i) for i in range(60)]
    served = 0
    for step in range(1000):  # 10 s in 10 ms steps; each step every flooding address sends once
        t += 10_000_000
        if step % 100 == 0:
            peers.heard(gcs, t)
        for addr in flood:
            peers.heard(addr, t)
        live = peers.live(t)
        assert len(live) <= ep_mod.MAX_PEERS
        served += gcs in live
    assert served == 1000
    assert peers.evicted > 50_000  # the flood churns the other slots among itself
    # addresses that keep sending hold the slots they have; a newcomer is then not served
    held = ep_mod.UdpPeers(max_peers=2)
    held.heard(gcs, t), held.heard(flood[0], t), held.heard(gcs, t), held.heard(flood[0], t)
    held.heard(flood[1], t + 1)
    assert held.live(t + 1) == {gcs, flood[0]} and held.refused == 1
    # the ground station goes quiet: after PEER_STALE_S its slot goes to a newcomer
    t += int(ep_mod.PEER_STALE_S * 1e9)
    for addr in flood:
        peers.heard(addr, t)
    assert gcs not in peers.live(t)
    # one-frame senders are replaced at once: a new ground station gets in among them
    peers = ep_mod.UdpPeers()
    for i in range(3 * ep_mod.MAX_PEERS):
        peers.heard(("127.0.0.1", 30000 + i), t)
    peers.heard(gcs, t)
    assert gcs in peers.live(t) and peers.refused == 0


def _hostile_frames(rng: random.Random, n: int) -> list[bytes]:
    """Random bytes, truncated and bad-CRC frames, and valid frames with hostile contents
    (non-finite or out-of-range PARAM_SET values, unknown names, impossible intervals, NaN
    command parameters, other targets)."""
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    bad = [float("nan"), float("inf"), float("-inf"), 3e38, 1.4e-45, -1.0, 2.0, 1e9]
    intervals = [float("nan"), float("inf"), 2.0**31, 2.0**40, -5.0, 1.0, 3.5]
    out = []
    for i in range(n):
        kind = i % 6
        if kind == 0:
            out.append(bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 300))))
            continue
        pick = rng.randrange(5)
        if pick == 0:
            msg = mav.param_set_encode(1, 1, rng.choice([b"AHRS_BETA", b"AHRS_RATE_HZ", b"AHRS_VERSION",
                                                         f"X{rng.getrandbits(30)}".encode()]),
                                       rng.choice(bad), rng.choice([mavlink2.MAV_PARAM_TYPE_REAL32,
                                                                    mavlink2.MAV_PARAM_TYPE_INT32]))
        elif pick == 1:
            msg = mav.command_long_encode(1, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                          rng.choice([30.0, 31.0, 105.0, float("nan")]), rng.choice(intervals),
                                          0, 0, 0, 0, 0)
        elif pick == 2:
            msg = mav.command_long_encode(1, 1, rng.randrange(65536), rng.randrange(256),
                                          *(rng.choice(bad) for _ in range(7)))
        elif pick == 3:
            msg = mav.param_request_read_encode(1, 1, b"AHRS_BETA", rng.randrange(-32768, 32768))
        else:
            msg = mav.param_set_encode(rng.randrange(2, 256), 1, b"AHRS_BETA", 0.5, mavlink2.MAV_PARAM_TYPE_REAL32)
        frame = bytearray(msg.pack(mav))
        if kind == 1:
            frame = frame[: rng.randrange(1, len(frame))]  # truncated
        elif kind == 2:
            frame[-1] ^= 0xFF  # bad CRC
        out.append(bytes(frame))
    return out


def test_bounded_fuzz_keeps_the_schedule_the_values_and_the_parameters(comp, gcs, store):
    """Issue 14 acceptance: 12 000 hostile datagrams interleaved with 6 s of simulated
    publishing; from the component's own counters: every scheduled ATTITUDE sent, nothing
    non-finite received, no parameter changed, the STATUSTEXT flood held back."""
    conn, _ = gcs
    connect(comp, conn)
    comp_addr = next(iter(conn.clients))  # where the component sends from
    frames = _hostile_frames(random.Random(14), 12_000)
    before = {n: comp.params.get(n) for n in comp.params.names()}
    step_ns, batch = 5_000_000, 10  # 1200 publish calls, 10 datagrams between two of them
    t0 = 50_000_000_000
    received = []
    for i in range(0, len(frames), batch):
        for f in frames[i:i + batch]:
            conn.port.sendto(f, comp_addr)
        now = t0 + (i // batch) * step_ns
        comp.publish(now, telemetry(now // 1_000_000))
        comp.poll(1000)
        received += drain(conn)
    received += settle(comp, conn, 0.3)
    last = t0 + (len(frames) // batch - 1) * step_ns
    scheduled = (last - t0) * 50 // 1_000_000_000 + 1  # ATTITUDE at 50 Hz from t0 on
    assert comp.stats.sent["ATTITUDE"] == scheduled
    assert comp.rates["ATTITUDE"] == 50.0  # no hostile interval was taken
    assert {n: comp.params.get(n) for n in comp.params.names()} == before and store["beta"] == 0.1
    for m in received:
        for field in ("roll", "pitch", "yaw", "q1", "q2", "q3", "q4", "param_value"):
            value = getattr(m, field, None)
            if m.get_type() in ("ATTITUDE", "ATTITUDE_QUATERNION", "PARAM_VALUE") and value is not None:
                assert math.isfinite(value), (m.get_type(), field)
    assert comp.stats.malformed > 0 and comp.stats.statustext_suppressed > 0
    assert len(of(received, "STATUSTEXT")) < 200  # thousands were triggered


@pytest.mark.parametrize("scheme", ["udpin", "udp"])
def test_a_udp_port_another_program_holds_is_refused_not_shared(scheme):
    """Issue 14 re-probe (h14): a second ``ahrs-service run`` on the first one's ``udpin`` port
    started (exit 0): mavutil binds with SO_REUSEADDR, so the second socket took the ground
    station's datagrams meant for the first. The port is refused while another socket holds it,
    and free again once it is closed (a reload reopens its own endpoints)."""
    import socket

    holder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    holder.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as mavutil's udpin does
    holder.bind(("127.0.0.1", 0))
    port = holder.getsockname()[1]
    try:
        with pytest.raises(OSError, match=rf"^cannot open MAVLink endpoint '{scheme}:127.0.0.1:{port}': "
                                          rf".*UDP port {port} is in use by another program"):
            MavlinkComponent([f"{scheme}:127.0.0.1:{port}"])
    finally:
        holder.close()
    with MavlinkComponent([f"{scheme}:127.0.0.1:{port}"]):
        pass


def test_param_set_of_negative_zero_stores_zero():
    """Issue 14 re-probe (h14): PARAM_SET RATE_ATT_HZ = -0.0 was stored and echoed as -0.0
    (a rate of "-0 Hz" in the ground station); 0.0 is stored, as for +0.0."""
    store = {"rate": 50.0}
    table = ParameterTable()
    table.add("RATE_ATT_HZ", lambda: store["rate"], lambda v: store.__setitem__("rate", v), minimum=0.0, maximum=200.0)
    result = table.set("RATE_ATT_HZ", -0.0)
    assert result.accepted and store["rate"] == 0.0 and math.copysign(1.0, store["rate"]) == 1.0
    assert math.copysign(1.0, result.value) == 1.0
