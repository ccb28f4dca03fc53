"""Beside a real autopilot: ArduPilot SITL's ArduCopter (tests/sitl.py), the service on its
SERIAL2 over UDP on 127.0.0.1, a pymavlink ground station on SERIAL0 taking the simulated
truth (SIMSTATE). Skipped, with the reason, where ../shared/sitl (or $AHRS_SITL_DIR) has no
SITL. Figures: SITL's copter on the ground, disarmed (level, still), so these check the link,
the time base, the frames and ArduPilot's own behaviour, not accuracy in flight.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from ahrs_service.core.quaternion import quat_to_euler

from tests.sitl import GroundStation, Sitl, binary, service_beside, wait_until
from tests.test_autopilot import free_udp_port

pytestmark = pytest.mark.timeout(300)

#: EKF3 fuses ODOMETRY's yaw (docs/autopilot.md, "ArduPilot"): external navigation as the yaw source
EKF3_ON_OUR_YAW = {"VISO_TYPE": 1, "EK3_SRC1_YAW": 6}


def test_arducopter_sitl_streams_to_the_service_and_ekf3_fuses_our_heading(tmp_path):
    from ahrs_service.service import Service

    binary("arducopter")  # skips where SITL is absent
    ground = GroundStation({"SIMSTATE": 50.0})  # the truth
    service_port = free_udp_port()
    cfg = service_beside(service_port, free_udp_port(), tmp_path / "logs", odometry={"rate_hz": 30.0, "rules": "ardupilot"})
    service = Service(cfg, duration_s=240.0)
    service.start()
    runner = threading.Thread(target=service.run, daemon=True)
    runner.start()
    try:
        with Sitl("arducopter", tmp_path, {0: ground.port, 2: service_port}, EKF3_ON_OUR_YAW):
            link = service.source.autopilot_link
            # ArduPilot streams HIGHRES_IMU once asked; the samples' times wait for TIMESYNC
            assert wait_until(lambda: service.pipeline.samples > 2000, 90.0), service.pipeline.samples
            assert link.autopilot is not None and link.autopilot.kind == "ardupilot"
            assert link.timesync.synced
            # ArduPilot streams no attitude unless asked: the monitor asked, and compares
            monitor = service.monitor
            assert wait_until(lambda: monitor.compared >= 50, 30.0), (monitor.compared, monitor.stream_requests)
            # EKF3 took our ODOMETRY as its yaw source
            assert wait_until(lambda: any("yaw aligned" in t for t in ground.texts), 60.0), ground.texts[-20:]
            samples_before, lost_before = service.pipeline.samples, service.source.diagnostics.lost.total
            t_from = time.monotonic()
            assert wait_until(lambda: time.monotonic() - t_from > 5.0, 10.0)
            q = service.mavlink.latest().q
            roll, pitch, _ = quat_to_euler(q)
            truth = [(float(m.roll), float(m.pitch)) for t, m in ground.received["SIMSTATE"] if t >= t_from]
            samples = service.pipeline.samples - samples_before
            lost = service.source.diagnostics.lost.total - lost_before
            odometry = service.mavlink.odometry.stats
            latest = monitor.latest
    finally:
        service.request_stop()
        runner.join(30)
        service.close()
        ground.close()
    assert len(truth) > 100
    true_roll, true_pitch = np.median([r for r, _ in truth]), np.median([p for _, p in truth])
    # on the ground, still: our roll and pitch are SITL's truth within 0.5° (its IMU's noise and
    # the estimator's start-up are all there is between them)
    assert abs(math.degrees(roll - true_roll)) < 0.5 and abs(math.degrees(pitch - true_pitch)) < 0.5
    # 5 s of the 200 Hz stream (HIGHRES_IMU follows ArduPilot's loop: 400 Hz / 2), none lost
    assert samples > 0.9 * 5 * 200 and lost <= 0.01 * samples
    assert odometry.sent > 100 and odometry.send_errors == 0
    # EKF3's attitude and ours agree (its heading is ours now)
    assert latest is not None and latest.total_deg < 2.0
