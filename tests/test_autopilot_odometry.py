"""Beside a simulated autopilot (tests/sim_autopilot.py, over UDP): the link's TIMESYNC
estimate is logged on /timesync after each accepted sample, and ODOMETRY under the ArduPilot
rules goes to the autopilot on its link. (ODOMETRY's time stamps on the link: test_autopilot.)"""

from __future__ import annotations

import dataclasses

import pytest

from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.schemas import decode
from sim_autopilot import UdpTransport
from test_autopilot import Rig, broad_segment, free_udp_port  # noqa: F401  (fixture)

pytestmark = pytest.mark.timeout(300)


def test_timesync_logged_and_ardupilot_odometry_on_the_link(tmp_path, broad_segment):  # noqa: F811
    rec = broad_segment
    port = free_udp_port()
    rig = Rig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}", kind="ardupilot",
              sections={"mavlink": {"odometry": {"rate_hz": 30.0, "rules": "ardupilot"}}})
    try:
        rig.run_to_end()
        link = rig.service.source.autopilot_link
        assert link.timesync.synced
        accepted = link.timesync.counters.accepted
        boot_ns = rig.sim.boot_ns
    finally:
        rig.close()
    assert rig.sim.stats.received.get("ODOMETRY", 0) >= 10
    assert rig.service.mavlink.odometry.stats.sent >= rig.sim.stats.received["ODOMETRY"]
    # the log's own counters show that ODOMETRY flowed: the last /loop (written at close) has them all
    loops = [decode(data) for topic, _, _, data in MessageSource(rig.log().path) if topic == "/loop"]
    assert loops[-1]["odometry"] == dataclasses.asdict(rig.service.mavlink.odometry.stats)
    assert loops[-1]["odometry"]["sent"] >= rig.sim.stats.received["ODOMETRY"] and loops[-1]["odometry"]["send_errors"] == 0
    stats = rig.service.mavlink.odometry.stats  # and the final summary line says so
    assert rig.service.odometry_summary() == (f"ODOMETRY: sent {stats.sent} ({stats.not_synced} before TIMESYNC synced), "
                                              f"heading resets {stats.resets}, send errors 0")
    records = [decode(data) for topic, _, _, data in MessageSource(rig.log().path) if topic == "/timesync"]
    # one record per accepted sample the loop saw (it may see two between its ticks as one)
    assert 5 <= len(records) <= accepted and records[-1]["synced"]
    # offset = autopilot − our clock = −(its boot time on ours), within 2 ms
    assert abs(records[-1]["offset_ns"] + boot_ns) < 2_000_000
    assert all(0 <= r["rtt_ns"] <= 10_000_000 for r in records)
    assert [r["t_ns"] for r in records] == sorted(r["t_ns"] for r in records)
