"""The fallback on companion loss, against a real autopilot: ArduPilot SITL's ArduCopter
(tests/sitl.py) fusing the service's ODOMETRY heading (``EK3_SRC1_YAW 6``) with its compass as
source set 2 (``EK3_SRC2_YAW 1``, the other sources as set 1's: docs/autopilot.md, "Fallback
when the companion stops"). The service is stopped cleanly; ArduPilot must be on set 2 within
a second, shown by its COMMAND_ACK and by its own records: the source-set event in its
DataFlash log and EKF3 re-aligning its yaw (STATUSTEXT). Skipped, with the reason, where SITL
is absent.
"""

from __future__ import annotations

import threading
import time

import pytest


from tests.sitl import GroundStation, Sitl, binary, service_beside, wait_until
from tests.test_autopilot import free_udp_port

pytestmark = pytest.mark.timeout(300)

#: set 1: GPS position and velocity, baro height, our heading (ExtNav); set 2: the same with the
#: compass heading. LOG_DISARMED: the DataFlash log (its source-set events) on the ground too
FALLBACK_PARAMS = {
    "VISO_TYPE": 1, "EK3_SRC1_YAW": 6,
    "EK3_SRC2_POSXY": 3, "EK3_SRC2_VELXY": 3, "EK3_SRC2_POSZ": 1, "EK3_SRC2_VELZ": 3, "EK3_SRC2_YAW": 1,
    "LOG_DISARMED": 1,
}
#: ArduPilot's LogEvent ids (libraries/AP_Logger/AP_Logger.h): EKF_YAW_RESET, EK3_SOURCES_SET_TO_PRIMARY, _SECONDARY
EVENT_YAW_RESET, EVENT_SOURCES_PRIMARY, EVENT_SOURCES_SECONDARY = 62, 85, 86


def dataflash(workdir) -> tuple[list[tuple[int, int]], list[int]]:
    """From SITL's DataFlash logs in ``workdir``/logs: the events (TimeUS, EV id) and the times
    of the ODOMETRY messages EKF3 took (VISP records, TimeUS), both on the autopilot's clock."""
    from pymavlink import DFReader

    events, odometry = [], []
    for path in sorted((workdir / "logs").glob("*.BIN")):
        log = DFReader.DFReader_binary(str(path))
        for _ in range(5_000_000):  # bounded: a minute of log holds far fewer records
            m = log.recv_match(type=["EV", "VISP"])
            if m is None:
                break
            if m.get_type() == "EV":
                events.append((int(m.TimeUS), int(m.Id)))
            else:
                odometry.append(int(m.TimeUS))
    return events, odometry


def test_a_clean_stop_switches_arducopter_to_its_compass_within_a_second(tmp_path):
    from ahrs_service.service import Service

    binary("arducopter")  # skips where SITL is absent
    ground = GroundStation()  # the autopilot's STATUSTEXTs
    service_port = free_udp_port()
    # source sets 1 and 2: the defaults
    cfg = service_beside(service_port, free_udp_port(), tmp_path / "logs", odometry={"rate_hz": 30.0, "rules": "ardupilot"})
    service = Service(cfg, duration_s=240.0)
    service.start()
    runner = threading.Thread(target=service.run, daemon=True)
    runner.start()
    closed = False
    try:
        with Sitl("arducopter", tmp_path, {0: ground.port, 2: service_port}, FALLBACK_PARAMS):
            switch = service.source_switch
            assert switch is not None and (switch.primary_set, switch.fallback_set) == (1, 2)
            # EKF3 fuses our heading; the service, trusting it, confirmed the primary set once
            assert wait_until(lambda: any("yaw aligned" in t for t in ground.texts), 90.0), ground.texts[-20:]
            assert wait_until(lambda: switch.stats.accepted >= 1, 30.0), (switch.stats, service.heading_trust(
                time.monotonic_ns()))
            assert switch.stats.asked == 1 and service.mavlink.odometry.stats.sent > 100
            t_stop_ns = time.monotonic_ns()
            service.request_stop()  # what SIGTERM / SIGINT do
            runner.join(30)
            service.close()
            closed = True

            def switched_and_reset() -> bool:  # SITL's logger thread writes its records out in its own time
                ids = [i for _, i in dataflash(tmp_path)[0]]
                return EVENT_SOURCES_SECONDARY in ids and EVENT_YAW_RESET in ids[ids.index(EVENT_SOURCES_SECONDARY):]

            assert wait_until(switched_and_reset, 20.0, step=0.5), dataflash(tmp_path)[0]
            events, odometry = dataflash(tmp_path)
    finally:
        service.request_stop()
        runner.join(30)
        if not closed:
            service.close()
        ground.close()
    st = switch.stats
    # ArduPilot accepted set 2, its COMMAND_ACK here within a second of the stop
    assert (st.requests, st.accepted, st.refused, st.unanswered, st.asked) == (2, 2, 0, 0, 2), st
    assert st.last_result == "set 2 accepted"
    assert 0 < switch.last_ack_ns - t_stop_ns < 1_000_000_000, (switch.last_ack_ns - t_stop_ns) / 1e9
    # ArduPilot's own record (no STATUSTEXT: 4.7 sends none for a set switch, nor for the yaw reset
    # on the ground): the switch to set 2 after the service's last ODOMETRY reached EKF3, then EKF3
    # taking its heading anew from the compass
    ids = [i for _, i in events]
    assert EVENT_SOURCES_PRIMARY in ids and EVENT_SOURCES_SECONDARY in ids, events
    t_secondary = events[ids.index(EVENT_SOURCES_SECONDARY)][0]
    assert ids.index(EVENT_SOURCES_PRIMARY) < ids.index(EVENT_SOURCES_SECONDARY), events
    assert len(odometry) > 50
    assert 0 <= t_secondary - odometry[-1] < 1_000_000, (t_secondary, odometry[-3:])
    resets = [t for t, i in events if i == EVENT_YAW_RESET and t > t_secondary]
    assert resets and resets[0] - t_secondary < 1_000_000, events
