"""MAV_CMD_SET_EKF_SOURCE_SET out (protocols/mavlink/ekf_source.py) over the real autopilot link
(UDP on 127.0.0.1) to a pymavlink peer that answers the way ArduPilot 4.7 does (sets 1..3
ACCEPTED, anything else DENIED, checked against SITL), refuses, stays silent, or is PX4."""

from __future__ import annotations

import threading
import time

import pytest

from ahrs_service import config as config_mod
from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink
from ahrs_service.protocols.mavlink.ekf_source import MAV_CMD_SET_EKF_SOURCE_SET, EkfSourceSwitch
from tests.sitl import wait_until
from tests.test_autopilot import free_udp_port

pytestmark = pytest.mark.timeout(60)


class Peer:
    """An autopilot on ``udpout`` to the link's port: HEARTBEAT every 0.1 s; every
    MAV_CMD_SET_EKF_SOURCE_SET it receives is recorded as (monotonic s, param1) and answered
    per ``answer``: "ardupilot", "deny" or "silent"."""

    def __init__(self, port: int, answer: str = "ardupilot", autopilot: str = "ardupilot") -> None:
        from pymavlink import mavutil

        self.mavutil = mavutil
        self.answer = answer
        self.kind = (mavutil.mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if autopilot == "ardupilot"
                     else mavutil.mavlink.MAV_AUTOPILOT_PX4)
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        self.commands: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        mav = self.mavutil.mavlink
        next_heartbeat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_QUADROTOR, self.kind, 0, 0, mav.MAV_STATE_STANDBY)
                next_heartbeat = now + 0.1
            msg = self.conn.recv_match(type="COMMAND_LONG", blocking=True, timeout=0.02)
            if msg is None or msg.command != MAV_CMD_SET_EKF_SOURCE_SET:
                continue
            self.commands.append((time.monotonic(), float(msg.param1)))
            if self.answer == "silent":
                continue
            ok = self.answer == "ardupilot" and msg.param1 in (1.0, 2.0, 3.0)
            result = mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_DENIED
            self.conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


@pytest.fixture
def rig():
    """(link, make_peer): the service's end of the autopilot link and a peer on it."""
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    link.open()
    peers: list[Peer] = []

    def make_peer(**kw) -> Peer:
        peer = Peer(port, **kw)
        peers.append(peer)
        assert wait_until(lambda: link.autopilot is not None, 10.0)
        return peer

    try:
        yield link, make_peer
    finally:
        for p in peers:
            p.close()
        link.close()


def test_a_clean_stop_asks_for_the_fallback_set_and_counts_the_accepted_ack(rig):
    link, make_peer = rig
    peer = make_peer()
    switch = EkfSourceSwitch(link, primary_set=1, fallback_set=2)
    t0 = time.monotonic()
    notices = switch.fall_back_at_stop()
    took = time.monotonic() - t0
    switch.close()
    assert [p for _, p in peer.commands] == [2.0]
    assert took < 0.5  # the ack waited for, not a timeout
    st = switch.stats
    assert (st.requests, st.accepted, st.refused, st.unanswered, st.send_errors, st.asked) == (1, 1, 0, 0, 0, 2)
    assert notices == [(5, "autopilot EKF source set 2 (fallback; the service is stopping): accepted")]
    assert switch.summary() == "EKF source set: 1 request (accepted 1, refused 0, no answer 0)"
    assert switch.fall_back_at_stop() == [] and len(peer.commands) == 1  # accepted already: not asked again


@pytest.mark.parametrize("answer, counted, text", [
    ("deny", "refused", "refused (DENIED)"),
    ("silent", "unanswered", "no answer after 2 tries"),
])
def test_a_refusal_and_silence_are_counted_and_reported_once(rig, answer, counted, text):
    link, make_peer = rig
    peer = make_peer(answer=answer)
    switch = EkfSourceSwitch(link, primary_set=1, fallback_set=3)
    t0 = time.monotonic()
    notices = switch.fall_back_at_stop(ack_timeout_s=0.3, tries=2)
    took = time.monotonic() - t0
    switch.close()
    st = switch.stats
    assert getattr(st, counted) == 1 and st.requests == 1 and st.accepted == 0
    assert st.refused + st.unanswered == 1
    assert notices == [(3, f"autopilot EKF source set 3 (fallback; the service is stopping): {text}")]
    if answer == "silent":  # sent again once, then given up within the stop's budget
        assert wait_until(lambda: len(peer.commands) == 2, 2.0) and [p for _, p in peer.commands] == [3.0, 3.0]
        assert 0.55 < took < 1.0
    else:
        assert [p for _, p in peer.commands] == [3.0] and took < 0.5


def test_the_heading_health_switches_with_hysteresis_and_never_twice_within_the_interval(rig):
    link, make_peer = rig
    peer = make_peer()
    interval_s, hold_s = 0.6, 0.8
    switch = EkfSourceSwitch(link, primary_set=1, fallback_set=2, min_interval_s=interval_s, trusted_hold_s=hold_s)
    notices: list[tuple[int, str]] = []

    def run(seconds: float, trusted) -> None:
        """update() every 20 ms for ``seconds`` (bounded), ``trusted(k)`` at the k-th call."""
        end = time.monotonic() + seconds
        for k in range(int(seconds / 0.02) + 1):
            if time.monotonic() >= end:
                break
            notices.extend(switch.update(time.monotonic_ns(), trusted(k), "attitude diverged"))
            time.sleep(0.02)

    run(0.5, lambda k: False)  # the estimator starting: never trusted yet, nothing asked
    assert peer.commands == []
    t_trusted = time.monotonic()
    run(1.5, lambda k: True)  # trusted for longer than the hold: the primary set, once
    assert wait_until(lambda: len(peer.commands) == 1, 2.0) and peer.commands[0][1] == 1.0
    assert peer.commands[0][0] - t_trusted >= hold_s - 0.05
    run(1.5, lambda k: k % 4 < 2)  # flickering: the fallback at once, then never the primary (no hold)
    run(0.3, lambda k: False)
    assert [p for _, p in peer.commands] == [1.0, 2.0]
    run(interval_s + hold_s + 0.8, lambda k: True)  # steady again: the primary after the hold
    assert wait_until(lambda: len(peer.commands) == 3, 2.0)
    notices.extend(switch.update(time.monotonic_ns(), True))
    switch.close()
    assert [p for _, p in peer.commands] == [1.0, 2.0, 1.0]
    times = [t for t, _ in peer.commands]
    assert all(b - a >= interval_s - 0.05 for a, b in zip(times, times[1:]))
    st = switch.stats
    assert (st.requests, st.accepted, st.refused, st.unanswered) == (3, 3, 0, 0)
    assert [text for _, text in notices] == [
        "autopilot EKF source set 1 (primary; our heading is trustworthy): accepted",
        "autopilot EKF source set 2 (fallback; our heading is not trustworthy: attitude diverged): accepted",
        "autopilot EKF source set 1 (primary; our heading is trustworthy): accepted",
    ]


def test_a_px4_autopilot_is_never_asked_and_told_once(rig):
    link, make_peer = rig
    peer = make_peer(autopilot="px4")
    switch = EkfSourceSwitch(link, primary_set=1, fallback_set=2)
    first = switch.fall_back_at_stop(ack_timeout_s=0.1, tries=1)
    second = switch.fall_back_at_stop(ack_timeout_s=0.1, tries=1)
    switch.close()
    time.sleep(0.2)  # a command would have arrived by now (loopback: well under 1 ms)
    assert peer.commands == [] and switch.stats.requests == 0
    assert first == [(4, "EKF source set 2 not asked: the autopilot is px4, MAV_CMD_SET_EKF_SOURCE_SET is ArduPilot's")]
    assert second == []


def test_the_source_set_keys_are_checked_with_one_line_naming_the_key():
    cfg = config_mod.validate({})
    assert (cfg.mavlink["odometry"]["primary_source_set"], cfg.mavlink["odometry"]["fallback_source_set"]) == (1, 2)
    for odometry, message in [
        ({"fallback_source_set": 4}, "mavlink.odometry.fallback_source_set: 4 is out of range"),
        ({"primary_source_set": 1.5}, "mavlink.odometry.primary_source_set: 1.5 is not an integer"),
        ({"fallback_source_set": 1}, "mavlink.odometry.fallback_source_set: 1 is also primary_source_set"),
    ]:
        with pytest.raises(config_mod.ConfigError) as err:
            config_mod.validate({"mavlink": {"odometry": odometry}})
        assert str(err.value).startswith(message) and "\n" not in str(err.value)
    off = config_mod.validate({"mavlink": {"odometry": {"fallback_source_set": 0, "primary_source_set": 0}}})
    assert off.mavlink["odometry"]["fallback_source_set"] == 0


def test_the_service_asks_at_its_stop_and_reports_the_outcome_once_in_log_and_loop(tmp_path):
    """The wiring: a service beside a (simulated) ArduPilot that never answers the command —
    asked at the stop all the same, the outcome one /log line and the counters on /loop."""
    import numpy as np

    from ahrs_service.logs.reader import MessageSource
    from ahrs_service.logs.schemas import decode
    from tests.sim_autopilot import Recording, UdpTransport
    from tests.test_autopilot import Rig

    n = 600  # 3 s at 200 Hz, level and still in a steady field
    rec = Recording.uniform(np.zeros((n, 3)), np.tile([0.0, 0.0, -9.81], (n, 1)), np.tile([20.0, 0.0, 45.0], (n, 1)),
                            np.tile([1.0, 0, 0, 0], (n, 1)), 5000)
    port = free_udp_port()
    rig = Rig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}", kind="ardupilot",
              sections={"mavlink": {"odometry": {"rate_hz": 30.0, "rules": "ardupilot", "fallback_source_set": 3}}})
    try:
        switch = rig.service.source_switch
        assert switch is not None and (switch.primary_set, switch.fallback_set) == (1, 3)
        rig.run_to_end()
        assert rig.service.heading_trust(time.monotonic_ns())[1] == "no IMU samples"  # the stream ended
    finally:
        rig.close()
    st = switch.stats
    assert st.asked == 3 and st.requests >= 1 and st.unanswered == st.requests and st.accepted == st.refused == 0
    plural = "s" if st.requests > 1 else ""
    assert rig.service.source_set_summary() == (f"EKF source set: {st.requests} request{plural} "
                                                f"(accepted 0, refused 0, no answer {st.requests})")
    records = [(topic, decode(data)) for topic, _, _, data in MessageSource(rig.log().path)
               if topic in ("/log", "/loop")]
    lines = [r["message"] for topic, r in records if topic == "/log" and "EKF source set" in r["message"]]
    assert len(lines) == st.requests and lines[-1].startswith("autopilot EKF source set 3 (fallback; ")
    assert all(" no answer after " in line for line in lines), lines
    loops = [r for topic, r in records if topic == "/loop"]
    assert loops[-1]["ekf_source_set"]["unanswered"] == st.unanswered and loops[-1]["ekf_source_set"]["asked"] == 3
