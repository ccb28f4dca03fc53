"""``ahrs-service log info`` reports lost samples by cause, from a log a real service run wrote
while samples were lost to a vanished part (bus_error) and to a stalled loop (fifo_overflow)."""

from __future__ import annotations

import json
import time

import pytest

from ahrs_service.cli import main
from ahrs_service.core.samples import LossCounts
from ahrs_service.logs.loss import log_losses
from tests.test_service import RunningService, make_gcs, service_config

pytestmark = pytest.mark.timeout(120)
MPU = 0x68  # the MPU-9250 on the simulated bus


def _wait(pred, seconds: float = 30.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


def _stall_the_loop_once(svc, seconds: float) -> None:
    """The service's loop sleeps ``seconds`` once, inside its MAVLink tick (a host stall)."""
    tick = svc.mavlink.tick
    stalled = []

    def stall_once(now_ns):
        if not stalled:
            stalled.append(now_ns)
            time.sleep(seconds)
        tick(now_ns)

    svc.mavlink.tick = stall_once


def test_log_info_prints_the_loss_by_cause_of_a_real_run(tmp_path, capsys):
    conn, port = make_gcs()
    run = RunningService(service_config(tmp_path, port, source={"board": "mpu9250", "profile": "static"}))
    svc = run.service
    lost = svc.source.diagnostics.lost
    try:
        assert _wait(lambda: svc.pipeline.samples > 200)
        # a part that vanishes for a while: what it produced meanwhile is a bus_error loss
        svc.source.bus.set_present(MPU, False)
        assert _wait(lambda: "gyro" in svc.source.lost)
        time.sleep(0.3)
        svc.source.bus.set_present(MPU, True)
        assert _wait(lambda: lost.bus_error > 0)
        # the loop stalls once for 0.3 s, longer than the FIFO holds: fifo_overflow
        _stall_the_loop_once(svc, 0.3)
        assert _wait(lambda: lost.fifo_overflow > 0)
        seen = lost.copy()
        time.sleep(2.2)  # two housekeeping seconds: a /loop written after every injected loss
    finally:
        run.stop()
        conn.close()
    final = lost.copy()
    path = svc.log_writer.files[0]
    got = log_losses(path)
    # the log's last /loop: at least what was counted before it, at most the final counters
    for cause in ("fifo_overflow", "bus_error", "gap", "host_stall"):
        assert getattr(seen, cause) <= getattr(got.last, cause) <= getattr(final, cause), cause
    assert got.last.fifo_overflow > 0 and got.last.bus_error > 0 and got.loops >= 3

    assert main(["log", "info", str(path)]) == 0
    out = capsys.readouterr().out
    assert f"lost samples (source, since the service started): {got.last.summary()}" in out
    assert "fifo_overflow" in got.last.summary() and "bus_error" in got.last.summary()
    assert main(["log", "info", "--json", str(path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["lost_samples"] == got.last.as_dict() and info["not_logged_samples"] == 0


def test_the_logs_last_counters_cover_a_loss_just_before_the_stop(tmp_path):
    # /loop is written once a second; a loss in the last second before the stop (a loaded host
    # skipping ticks on its way out) must still reach the log: the service writes one more
    # /loop when it closes, so the log's last counters are the run's final ones
    conn, port = make_gcs()
    run = RunningService(service_config(tmp_path, port, source={"board": "mpu9250", "profile": "static"}))
    svc = run.service
    lost = svc.source.diagnostics.lost
    try:
        assert _wait(lambda: svc.pipeline.samples > 200)
        _stall_the_loop_once(svc, 0.3)  # longer than the MPU-9250's FIFO holds at 200 Hz with its drain
        assert _wait(lambda: lost.fifo_overflow > 0)
    finally:
        run.stop()  # at once: no housekeeping second after the loss
        conn.close()
    got = log_losses(svc.log_writer.files[0])
    assert got.last == lost.copy() and got.last.fifo_overflow > 0


def test_log_info_of_a_log_without_loss_counters_says_so(tmp_path, capsys):
    import numpy as np

    from ahrs_service.logs.writer import FlightLogWriter

    w = FlightLogWriter(tmp_path)
    w.write_raw(1, np.zeros(10), 0)
    w.close()
    assert main(["log", "info", str(w.files[0])]) == 0
    assert "lost samples: not recorded" in capsys.readouterr().out
    assert log_losses(w.files[0]).last is None and LossCounts().summary() == "0"
