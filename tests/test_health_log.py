"""Health events on /log (foxglove.Log) in a real run's MCAP, and the estimator's diagnostics
in /attitude at the configured rate."""

from __future__ import annotations

import time

import pytest

from ahrs_service.logs.reader import MessageSource
from ahrs_service.logs.schemas import CHANNELS, LOG_LEVEL_OF_SEVERITY, decode, log_level, validate
from tests.test_foxglove_layout import free_port
from tests.test_service import RunningService, service_config

pytestmark = pytest.mark.timeout(120)


def _wait(condition, seconds: float = 20.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


def test_statustext_severities_map_onto_foxglove_levels():
    # EMERGENCY ALERT CRITICAL -> FATAL, ERROR -> ERROR, WARNING -> WARNING, NOTICE INFO -> INFO, DEBUG
    assert [log_level(s) for s in range(8)] == [5, 5, 5, 4, 3, 2, 2, 1] == list(LOG_LEVEL_OF_SEVERITY)
    assert log_level(8) == log_level(-1) == 0  # unknown


def test_a_forced_sensor_fault_is_on_the_log_channel(tmp_path):
    run = RunningService(service_config(tmp_path, free_port(), source={"profile": "figure8"}, log={"diagnostics_hz": 20}),
                         duration_s=60.0)
    svc = run.service
    gyro = svc.source.parts["gyro"].address
    try:
        assert _wait(lambda: svc.pipeline.samples > 50)
        svc.source.bus.set_present(gyro, False)  # the gyro stops answering on the simulated bus
        assert _wait(lambda: svc.health_report.last_lost)
        svc.source.bus.set_present(gyro, True)
        assert _wait(lambda: not svc.health_report.last_lost)
    finally:
        run.stop()
    (path,) = (tmp_path / "logs").glob("*.mcap")
    logs, attitudes = [], []
    for topic, log_time, _, data in MessageSource(path):
        if topic == "/log":
            logs.append((log_time, decode(data)))
        elif topic == "/attitude":
            attitudes.append(decode(data))
    for _, msg in logs:
        assert validate(msg, CHANNELS["/log"][1]) == []
    texts = [m["message"] for _, m in logs]
    lost = next(i for i, t in enumerate(texts) if t.startswith("sensor lost"))
    back = next(i for i, t in enumerate(texts) if t == "sensor back")
    assert lost < back
    assert logs[lost][1]["level"] == 4 and logs[back][1]["level"] == 2  # severity 3 ERROR, 6 INFO
    assert logs[lost][1]["timestamp"]["sec"] * 10**9 + logs[lost][1]["timestamp"]["nsec"] == logs[lost][0]
    # the diagnostics ride on a subset of /attitude messages, not all of them
    with_diag = [a["diagnostics"] for a in attitudes if a["diagnostics"]]
    assert 0 < len(with_diag) < len(attitudes) / 5
    assert {"rest", "mag_disturbed", "reduced", "initialised"} <= with_diag[0].keys()
