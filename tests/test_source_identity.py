"""Who the autopilot link listens to: the configured flight controller only, never one heard
first by chance, and not a second sender using the autopilot's ids.

Over real UDP on 127.0.0.1: the service's autopilot link (``udpin``) and simulated flight
controllers (tests/sim_autopilot.py, pymavlink peers on their own sockets), one of them
hostile: another system speaking first, or a second sender with the autopilot's system and
component id and another clock (2 200 s ahead) streaming beside it.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ahrs_service import config as config_mod
from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink
from ahrs_service.protocols.mavlink.imu_source import MavlinkImuSource
from ahrs_service.sources import make_mavlink_source
from tests.test_autopilot import free_udp_port

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim_autopilot import Recording, SimAutopilot, UdpTransport, mavlink  # noqa: E402

pytestmark = pytest.mark.timeout(120)

PERIOD_US = 5000


def _still(n: int) -> Recording:
    return Recording.uniform(np.tile([0.01, 0.0, 0.0], (n, 1)), np.tile([0.0, 0.0, -9.81], (n, 1)),
                             np.tile([20.0, 0.0, 45.0], (n, 1)), np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), PERIOD_US)


class _Intruder(SimAutopilot):
    """A flight controller that streams HIGHRES_IMU unasked, its clock ``ahead_us`` ahead of the
    genuine one's (IMU stamps and TIMESYNC replies alike)."""

    def __init__(self, *args, ahead_us: int = 0, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.ahead_us = int(ahead_us)
        self.intervals[mavlink.MAVLINK_MSG_ID_HIGHRES_IMU] = float(PERIOD_US)

    def now_us(self) -> int:
        return super().now_us() + self.ahead_us


def _wait(condition, seconds: float) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def _read_all(src: MavlinkImuSource, sim: SimAutopilot, n: int, seconds: float = 20.0) -> list:
    """Samples handed out until ``n`` came, or the sender finished and 0.3 s passed quietly."""
    got: list = []
    end = time.monotonic() + seconds
    last = time.monotonic()
    while time.monotonic() < end and len(got) < n:
        block = src.read_block()
        if len(block):
            got.extend(block.samples())
            last = time.monotonic()
            continue
        if sim.join(0.0) and time.monotonic() - last > 0.3:
            break
        time.sleep(0.005)
    return got


@pytest.mark.parametrize("configured_by", ["source.mavlink_autopilot_system_id", "mavlink.identity companion"])
def test_the_configured_autopilot_is_listened_to_when_another_system_speaks_first(configured_by):
    """One HEARTBEAT of system 7 used to capture the link for good, and the configured
    autopilot (system 1) was ignored: 0 samples. The configured one is adopted (named in
    [source], or the system id a companion shares with its autopilot); system 7 is counted and
    reported once, its stream never used."""
    n = 300
    port = free_udp_port()
    source = {"type": "mavlink", "mavlink_connection": f"udpin:127.0.0.1:{port}", "mavlink_imu_hz": 1e6 / PERIOD_US}
    if configured_by.startswith("source"):
        cfg = config_mod.validate({"source": {**source, "mavlink_autopilot_system_id": 1}})
    else:
        cfg = config_mod.validate({"source": source, "mavlink": {"identity": "companion", "system_id": 1}})
    src = make_mavlink_source(cfg.source, cfg.mavlink["system_id"], cfg.mavlink["identity"] == "companion")
    link = src.link
    src.open()
    foreign = _Intruder(UdpTransport(port), _still(2 * n), system_id=7, ahead_us=10**9).start()
    genuine = None
    try:
        assert _wait(lambda: link.stats.other_autopilots >= 1, 10.0), "system 7 was not heard"
        assert link.autopilot is None
        genuine = SimAutopilot(UdpTransport(port), _still(n)).start()
        got = _read_all(src, genuine, n)
        notices = link.take_notices()
    finally:
        foreign.stop()
        if genuine is not None:
            genuine.stop()
        src.close()
    assert link.autopilot is not None and (link.autopilot.system_id, link.autopilot.component_id) == (1, 1)
    assert len(got) == n and src.diagnostics.lost.total == 0 and src.timeline_resets == 0
    assert np.all(np.diff([s.t_ns for s in got]) > 0)
    assert link.stats.other_autopilots >= 2  # system 7 kept beating: counted every time …
    assert link.stats.other_system_messages > n  # … its IMU stream too …
    said = [text for _, text in notices if "system 7" in text]
    assert said == ["autopilot link: ignoring px4 system 7 component 1: listening to system 1"]  # … reported once
    assert src.diagnostics.extra["other_autopilots"] == link.stats.other_autopilots


def test_without_a_configured_system_a_later_autopilot_is_counted_never_adopted():
    n = 200
    port = free_udp_port()
    src = MavlinkImuSource(AutopilotLink(f"udpin:127.0.0.1:{port}"), rate_hz=1e6 / PERIOD_US)
    link = src.link
    src.open()
    genuine = SimAutopilot(UdpTransport(port), _still(n)).start()
    other = None
    try:
        assert _wait(lambda: link.autopilot is not None, 10.0)
        other = _Intruder(UdpTransport(port), _still(n), system_id=9, kind="ardupilot").start()
        got = _read_all(src, genuine, n)
        assert _wait(lambda: link.stats.other_autopilots >= 1, 5.0)
    finally:
        genuine.stop()
        if other is not None:
            other.stop()
        src.close()
    assert link.autopilot.system_id == 1 and len(got) == n
    said = [text for _, text in link.take_notices() if "system 9" in text]
    assert said == ["autopilot link: ignoring ardupilot system 9 component 1: listening to px4 system 1 component 1"]


def test_a_second_sender_with_the_autopilots_ids_is_a_conflict_not_thousands_of_timelines():
    """Before: a second sender with the autopilot's ids (its clock 2 200 s ahead) made 8 142
    timeline resets and ODOMETRY's time jump between 0 and 2.2e9 µs. The autopilot's address is
    pinned: the second one's messages are counted and reported once as a conflict, and the
    genuine stream is handed out whole, on one timeline."""
    n = 400
    port = free_udp_port()
    src = MavlinkImuSource(AutopilotLink(f"udpin:127.0.0.1:{port}"), rate_hz=1e6 / PERIOD_US)
    link = src.link
    src.open()
    genuine = SimAutopilot(UdpTransport(port), _still(n)).start()
    twin = None
    try:
        assert _wait(lambda: link.autopilot is not None, 10.0)
        twin = _Intruder(UdpTransport(port), _still(2 * n), ahead_us=2_200 * 10**6).start()
        got = _read_all(src, genuine, n)
        with link.timesync_lock:
            drift_ppm = link.timesync.drift_ppm
    finally:
        genuine.stop()
        if twin is not None:
            twin.stop()
        src.close()
    assert src.timeline_resets == 0 and link.timeline.steps == 0
    assert len(got) == n and src.out_of_order == 0 and src.diagnostics.lost.total == 0
    t = np.array([s.t_ns for s in got])
    assert np.all(np.diff(t) > 0) and np.diff(t).max() < 0.1e9
    assert link.stats.identity_conflicts > 100  # its IMU stream, its HEARTBEATs, its TIMESYNC replies
    assert abs(drift_ppm) < 1000.0
    said = [text for _, text in link.take_notices() if "second sender" in text]
    assert len(said) == 1 and "uses the autopilot's ids (system 1 component 1" in said[0]
    assert src.diagnostics.extra["identity_conflicts"] == link.stats.identity_conflicts


def test_config_names_a_bad_autopilot_id():
    with pytest.raises(config_mod.ConfigError, match=r"^source\.mavlink_autopilot_system_id: "):
        config_mod.validate({"source": {"mavlink_autopilot_system_id": 256}})
    with pytest.raises(config_mod.ConfigError, match=r"^source\.mavlink_autopilot_component_id: "):
        config_mod.validate({"source": {"mavlink_autopilot_component_id": -1}})
