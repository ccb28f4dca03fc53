"""The embedded default ("the demo"): a simulated GY-80 on a simulated I2C bus flying the first
paper's validation manoeuvre, estimated by `robust` (README, "Two commands").

The samples are those the service's default source delivers — the same board, parts, error
models, seed and FIFO drains — but on a simulation clock stepped once per wake-up, so no
sample is lost and the figures do not depend on the machine's load. Every estimator runs
through the service's own estimation pipeline and is scored against the simulator's truth as
``evaluation/metrics.py`` scores BROAD: total error for the estimators that use the
magnetometer, inclination for the 6-D ones. What is found and why: docs/simulator.md, "The
embedded default".
"""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest

from ahrs_service import config as config_mod
from ahrs_service import estimators
from ahrs_service.drivers.boards import BOARDS, make_simulated_board
from ahrs_service.drivers.sim.imu import ManualClock, SimulatedImu
from ahrs_service.drivers.sim.motion import profile
from ahrs_service.drivers.sim.sensor_model import PART_MODELS
from ahrs_service.core.quaternion import quat_rotate_array
from ahrs_service.evaluation.metrics import error_angles, rmse
from ahrs_service.pipeline import EstimationPipeline

pytestmark = pytest.mark.timeout(900)  # a cold numba cache compiles all 13 estimators

SECONDS = 30.0  # the README's `ahrs-service run --duration 30`


def default_config() -> config_mod.Config:
    return config_mod.validate({})


def demo_blocks(seconds: float = SECONDS):
    """The default source's sample blocks over ``seconds``, one FIFO drain per wake-up of a
    simulation clock, and its SimulatedImu (the default [source]: board, profile, seed, the
    parts' error models as ``sources.simulated_imu`` builds them)."""
    src_cfg = default_config().raw["source"]
    assert (src_cfg["type"], src_cfg["board"], src_cfg["profile"]) == ("simulated_i2c", "gy80", "validation")
    clock = ManualClock()
    gyr, acc, mag = (PART_MODELS[p].analog() for p in BOARDS[src_cfg["board"]].sensor_models)
    imu = SimulatedImu(profile(src_cfg["profile"], looping=src_cfg["loop_profile"]),
                       {"gyr": gyr, "acc": acc, "mag": mag}, clock=clock, seed=src_cfg["seed"])
    source = make_simulated_board(src_cfg["board"], imu, i2c_speed_hz=src_cfg["i2c_speed_hz"],
                                  **src_cfg["board_options"])
    source.open()
    period = 1.0 / source.wakeup_rate_hz
    blocks = []
    for k in range(1, int(round(seconds / period)) + 1):
        clock.set(k * period)
        block = source.read_block(64)
        if len(block):
            blocks.append(block)
    assert source.diagnostics.lost.total == 0 and source.diagnostics.dropped_frames == 0
    return blocks, imu


@pytest.fixture(scope="module")
def demo():
    return demo_blocks()


def estimate(name: str, blocks) -> tuple[np.ndarray, np.ndarray, bool]:
    """(estimates, truths, uses the magnetometer) of estimator ``name`` at its defaults, run
    through the service's pipeline at the default estimation rate."""
    est = estimators.create(name)
    pipeline = EstimationPipeline(est, nominal_dt=1.0 / default_config().rates["estimation_hz"])
    qs, truths = [], []
    for block in blocks:
        done = pipeline.process_block(block)
        if done is not None:
            qs.append(done.q)
            truths.append(done.truth_q)
    return np.concatenate(qs), np.concatenate(truths), bool(est.uses_mag)


@pytest.fixture(scope="module")
def scores(demo):
    """{name: (total RMSE °, inclination RMSE °, uses the magnetometer)} over the demo."""
    blocks, _ = demo
    out = {}
    for name in estimators.names():
        q, truth, uses_mag = estimate(name, blocks)
        total, _, incl = (np.degrees(a) for a in error_angles(q, truth))
        out[name] = (rmse(total), rmse(incl), uses_mag)
    return out


def test_the_simulated_field_is_the_declared_undisturbed_field(demo):
    """Magnitude and dip of every field reading, turned into the earth frame with the true
    attitude, are those of the field the trajectory declares: nothing disturbs it."""
    blocks, imu = demo
    mag = np.concatenate([b.mag for b in blocks])
    truth = np.concatenate([b.truth_q for b in blocks])
    new = ~np.isnan(mag[:, 0])
    field = quat_rotate_array(truth[new], mag[new])
    declared = np.asarray(imu.trajectory.field_ned, dtype=float)
    norm = np.linalg.norm(mag[new], axis=1)
    dip = np.degrees(np.arctan2(field[:, 2], np.hypot(field[:, 0], field[:, 1])))
    declared_dip = math.degrees(math.atan2(declared[2], math.hypot(declared[0], declared[1])))
    assert new.sum() > 2000  # 75 Hz for 30 s, read at the 200 Hz drains
    assert abs(norm.mean() - np.linalg.norm(declared)) < 0.1  # µT (49.2 µT declared)
    assert abs(dip.mean() - declared_dip) < 0.1  # ° (66.0° declared)
    # the spread is the HMC5883L model's white noise (0.45 µT a reading at 75 Hz), no drift:
    # every 3 s stretch has the same mean field
    assert norm.std() < 0.6 and dip.std() < 0.7
    t = np.concatenate([b.t_ns for b in blocks])[new] * 1e-9
    t -= t[0]
    for start in np.arange(0.0, SECONDS - 3.0, 3.0):
        part = (t >= start) & (t < start + 3.0)
        np.testing.assert_allclose(field[part].mean(axis=0), declared, atol=0.15)


def test_the_demo_scores_of_every_estimator(scores):
    """Every estimator is scored and the figures are finite (the table in docs/simulator.md)."""
    assert len(scores) == 13
    for name, (total, incl, _) in scores.items():
        assert math.isfinite(total) and math.isfinite(incl), name


@pytest.mark.xfail(strict=True, reason=(
    "robust learns the gyro bias at rest and, in motion, on the two horizontal axes, from VQF's "
    "0.5 °/s prior (bias_sigma_init, meant for a calibrated gyro); the demo's uncalibrated L3G4200D "
    "has a 2.1 °/s turn-on bias on z (seed 0, datasheet ±10 °/s), and no rest is detected in the "
    "manoeuvre's 2 s holds (the clip is not the cause: 2, 5 and 10 °/s score alike), so the motion "
    "update learns it over tens of seconds: robust 6.5° total against ekf 3.3°; a 2 or 5 °/s prior "
    "gives 3.5° or 3.1° here but costs DIDO 5-6 % (docs/simulator.md, 'The embedded default')"))
def test_robust_is_at_least_as_accurate_as_every_other_estimator(scores):
    robust_total, robust_incl, _ = scores["robust"]
    for name, (total, incl, uses_mag) in scores.items():
        if name == "robust":
            continue
        if uses_mag:
            assert robust_total <= total, (name, robust_total, total)
        else:
            assert robust_incl <= incl, (name, robust_incl, incl)


def _log_events(path) -> list[tuple[int, str]]:
    """(foxglove.Log level, message) of every /log message of an MCAP flight log."""
    from mcap.reader import make_reader

    out = []
    with open(path, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=["/log"]):
            d = json.loads(message.data)
            out.append((int(d["level"]), str(d["message"])))
    return out


#: health reports of a loop the host starved (overruns, FIFO overflows): real, and warnings,
#: but about the machine, not the start; each is checked against the service's own counters
LOAD_REPORTS = ("loop overruns:", "IMU samples lost:")


def test_a_clean_start_warns_of_nothing(tmp_path):
    """The embedded default for a few seconds, attitude to a real UDP peer on 127.0.0.1: no
    WARNING-or-worse event on /log, and the start-up field's confirmation is reported as what
    it is (information), not as a disturbed field."""
    from pymavlink import mavutil

    from ahrs_service.service import Service

    peer = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=255, source_component=190)
    try:
        port = peer.port.getsockname()[1]
        cfg = config_mod.validate({"mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"]},
                                   "log": {"directory": str(tmp_path / "logs")}})
        service = Service(cfg, duration_s=6.0)
        service.start()
        runner = threading.Thread(target=service.run, daemon=True)
        runner.start()
        received = 0
        while runner.is_alive():
            if peer.recv_match(blocking=True, timeout=0.1) is not None:
                received += 1
        runner.join(10)
        overruns = service.scheduler.overruns
        lost_samples = service.source.diagnostics.lost.total
        files = list(service.log_writer.files)
        service.close()
    finally:
        peer.close()
    assert received > 0
    events = [e for f in files for e in _log_events(f)]
    messages = [m for _, m in events]
    assert any(m.startswith("magnetometer not confirmed yet") for m in messages), messages
    assert not any("disturbed" in m for m in messages), messages
    warnings = [(level, m) for level, m in events if level >= 3]  # foxglove.Log: 3 WARNING
    unexplained = [w for w in warnings if not w[1].startswith(LOAD_REPORTS)]
    assert unexplained == []
    if any(m.startswith("loop overruns:") for _, m in warnings):
        assert overruns > 0
    if any(m.startswith("IMU samples lost:") for _, m in warnings):
        assert lost_samples > 0


def test_the_start_up_confirmation_is_information_and_a_later_rejection_a_warning():
    """The service's report of the field's use (``Service._report_mag_rejection``) over a
    sequence of diagnostics records: robust confirming its start-up field, then confirmed,
    then rejecting a disturbed field; an estimator without ``mag_confirmed`` warns at once."""
    import types

    from ahrs_service.service import Service

    events: list[tuple[int, str]] = []
    host = types.SimpleNamespace(_mag_state="accepted",
                                 log_event=lambda text, severity=6: events.append((severity, text)))
    confirming = {"mag_disturbed": True, "mag_confirmed": False}
    accepted = {"mag_disturbed": False, "mag_confirmed": True}
    rejected = {"mag_disturbed": True, "mag_confirmed": True}
    for diag in (confirming, confirming, accepted, accepted, rejected, rejected, accepted,
                 {"mag_disturbed": True}, {}):
        Service._report_mag_rejection(host, diag)
    assert [(s, t.split(":")[0]) for s, t in events] == [
        (6, "magnetometer not confirmed yet"),
        (6, "magnetometer confirmed"),
        (4, "magnetometer rejected"),
        (6, "magnetometer accepted again"),
        (4, "magnetometer rejected"),
        (6, "magnetometer accepted again"),
    ]
