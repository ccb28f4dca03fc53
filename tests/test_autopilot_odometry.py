"""Beside a simulated autopilot (tests/sim_autopilot.py, over UDP): the service's ODOMETRY is
stamped in the autopilot's clock through the link's TIMESYNC, and the TIMESYNC estimate is
logged on /timesync."""

from __future__ import annotations

import numpy as np
import pytest

from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.schemas import decode
from ahrs_service.protocols.mavlink.odometry import COV_YAW
from ahrs_service.service import Service
from test_autopilot import Rig, broad_segment, free_udp_port, service_config  # noqa: F401  (fixture)
from sim_autopilot import UdpTransport

pytestmark = pytest.mark.timeout(300)


class OdometryRig(Rig):
    """Rig with [mavlink.odometry] on (the ODOMETRY goes to the listening ground station)."""

    def __init__(self, tmp_path, rec, transport, connection: str) -> None:
        import threading

        from test_autopilot import SimAutopilot, drain, make_gcs

        self.gcs, gcs_port = make_gcs()
        self.gcs_messages: list = []
        self._stop = threading.Event()
        self._gcs_thread = threading.Thread(target=drain, args=(self.gcs, self.gcs_messages, self._stop), daemon=True)
        self._gcs_thread.start()
        cfg = service_config(tmp_path, connection, gcs_port, rec.period_us,
                             mavlink={"odometry": {"rate_hz": 30, "rules": "ardupilot"}})
        self.service = Service(cfg, duration_s=60.0)
        self.service.start()
        self.thread = threading.Thread(target=self.service.run, daemon=True)
        self.thread.start()
        self.sim = SimAutopilot(transport, rec).start()
        self.expected = len(rec.rel_us)


def test_odometry_in_the_autopilot_clock_and_timesync_logged(tmp_path, broad_segment):  # noqa: F811
    rec = broad_segment
    port = free_udp_port()
    rig = OdometryRig(tmp_path, rec, UdpTransport(port), f"udpin:127.0.0.1:{port}")
    try:
        rig.run_to_end()
        link = rig.service.source.autopilot_link
        assert link.timesync.synced
        # on the autopilot link as well as on the endpoints
        assert rig.sim.stats.received.get("ODOMETRY", 0) >= 10
        boot_ns = rig.sim.boot_ns
    finally:
        rig.close()
    log = rig.log()
    odo = [m for m in rig.gcs_messages if m.get_type() == "ODOMETRY"]
    synced = [m for m in odo if m.time_usec < 10**9]  # the autopilot's µs since its boot, not ours
    assert len(synced) >= 10
    for m in synced:
        # the estimate of one logged sample; its time on the autopilot's clock within 2 ms
        i = int(np.argmin(np.abs(log.attitudes - np.asarray(m.q)).max(axis=1)))
        assert np.abs(log.attitudes[i] - np.asarray(m.q)).max() < 1e-7
        assert abs(m.time_usec - (int(log.t_ns[i]) - boot_ns) // 1000) <= 2000
        assert np.isfinite(m.pose_covariance[COV_YAW])
    # the estimate on /timesync: offset = autopilot − our clock = −(its boot time on ours)
    records = [decode(data) for topic, _, _, data in MessageSource(log.path) if topic == "/timesync"]
    assert len(records) >= 5 and records[-1]["synced"]
    assert abs(records[-1]["offset_ns"] + boot_ns) < 2_000_000
    assert all(r["rtt_ns"] <= 10_000_000 for r in records)
