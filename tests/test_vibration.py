"""VIBRATION (#241): ArduPilot's vibration levels and clipping counts, from the module to a
real pymavlink ground station on 127.0.0.1 watching a simulated board that shakes."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")

from ahrs_service.drivers.base import ACC_SATURATED, ACC_VALID, GYR_VALID  # noqa: E402
from ahrs_service.drivers.sim.motion import Vibrating, profile  # noqa: E402
from ahrs_service.logs.reader import read_log  # noqa: E402
from ahrs_service.vibration import CLIP_LIMIT_MSS, FLOOR_HZ, VIBE_HZ, VibrationMonitor  # noqa: E402
from tests.test_service import RunningService, collect, service_config  # noqa: E402

pytestmark = pytest.mark.timeout(120)
G = 9.80665


def steady_level(amplitude: float, frequency_hz: float, rate_hz: float) -> float:
    """The level a sinusoid amplitude·sin(2π f t) sampled at rate_hz settles to (the 2 Hz
    filter's ripple at 2f aside), from the filters' frequency response, not by running them:
    amplitude/√2 · |1 − H(e^{jω})|, H = α / (1 − (1 − α) e^{−jω}) the discrete 5 Hz floor."""
    dt = 1.0 / rate_hz
    alpha = dt / (dt + 1.0 / (2.0 * math.pi * FLOOR_HZ))
    h = alpha / (1.0 - (1.0 - alpha) * np.exp(-1j * 2.0 * math.pi * frequency_hz * dt))
    return float(amplitude / math.sqrt(2.0) * abs(1.0 - h))


def _rows(amplitude, frequency_hz: float, rate_hz: float, seconds: float) -> np.ndarray:
    t = np.arange(int(seconds * rate_hz)) / rate_hz
    rows = np.zeros((t.size, 10))
    rows[:, 3:6] = np.outer(np.sin(2 * np.pi * frequency_hz * t), amplitude)
    rows[:, 5] -= G  # level, at rest: specific force (0, 0, −g)
    rows[:, 9] = 1.0 / rate_hz
    return rows


@pytest.mark.parametrize("rate_hz, frequency_hz", [(200.0, 30.0), (1000.0, 80.0), (1000.0, 8.0)])
def test_levels_of_a_sinusoid_match_the_filters_response(rate_hz, frequency_hz):
    amplitude = np.array([3.0, 1.0, 0.0])
    vib = VibrationMonitor()
    vib.update(_rows(amplitude, frequency_hz, rate_hz, 10.0), np.full(int(10 * rate_hz), GYR_VALID | ACC_VALID))
    lv = vib.levels()
    for got, a in zip((lv.x, lv.y), amplitude[:2]):
        # the 2 Hz filter leaves a ripple at 2f of about ±(2 Hz / 2f) of the square, half of
        # that in the level: the bound is that ripple (6 % at 8 Hz, 0.6 % at 80 Hz) + 0.5 %
        ripple = 0.5 * VIBE_HZ / (2 * frequency_hz)
        assert got == pytest.approx(steady_level(a, frequency_hz, rate_hz), rel=ripple + 0.005)
    assert lv.z < 1e-6 and lv.clipping == (0, 0, 0)  # gravity is the floor, not vibration


def test_rows_one_by_one_give_the_block_result_bit_for_bit():
    rows = _rows(np.array([2.0, 0.5, 4.0]), 45.0, 400.0, 2.0)
    rows[100:110, 3:6] = np.nan  # invalid readings: skipped by both
    flags = np.full(len(rows), GYR_VALID | ACC_VALID)
    flags[100:110] = GYR_VALID
    flags[300] |= ACC_SATURATED
    block, single = VibrationMonitor(), VibrationMonitor()
    block.update(rows, flags)
    for row, f in zip(rows, flags):
        single.update(row, int(f))
    assert block.levels() == single.levels() and block.clipping == single.clipping == 1


def test_clipping_counts_samples_beyond_the_limit_or_flagged_saturated():
    rows = _rows(np.zeros(3), 1.0, 100.0, 1.0)
    flags = np.full(len(rows), GYR_VALID | ACC_VALID)
    rows[10, 3] = CLIP_LIMIT_MSS * 1.01  # beyond ArduPilot's (16 − 0.5) g on one axis
    rows[20, 4] = -CLIP_LIMIT_MSS * 1.5
    rows[30, 3:6] = np.nan  # a saturated part: no valid reading, the flag says why
    flags[30] = GYR_VALID | ACC_SATURATED
    rows[40, 5] = CLIP_LIMIT_MSS * 0.99  # below the limit: not clipping
    vib = VibrationMonitor()
    vib.update(rows, flags)
    assert vib.levels().clipping == (3, 0, 0)


def test_vibrating_trajectory_adds_the_sinusoid_to_the_specific_force_only():
    base = profile("static")
    shaken = Vibrating(base, [3.0, 0.0, 1.0], 50.0)
    t = 0.005  # a quarter period: sin = 1
    a, b = base.state(t), shaken.state(t)
    assert np.allclose(b.specific_force_body - a.specific_force_body, [3.0, 0.0, 1.0])
    assert np.array_equal(a.omega_body, b.omega_body) and np.array_equal(a.q, b.q)


def _vibrations(msgs):
    return [m for m in msgs if m.get_type() == "VIBRATION"]


def test_service_publishes_the_levels_of_a_shaking_board(tmp_path, gcs):
    conn, port = gcs
    amplitude, freq = [4.0, 0.0, 2.0], 30.0
    cfg = service_config(tmp_path, port, source={"profile": "static", "vibration_mss": amplitude,
                                                 "vibration_hz": freq}, rates={"vibration_hz": 5})
    run = RunningService(cfg)
    try:
        msgs = collect(conn, 60.0, until=lambda m: len(_vibrations([m])) and m.time_usec > 8_000_000)
    finally:
        run.stop()
    vib = [m for m in _vibrations(msgs) if m.time_usec > 5_000_000]  # settled: 2 Hz filter, 5 s
    assert vib, [m.get_type() for m in msgs][-20:]
    rate = 200.0  # the GY-80's accelerometer rate at estimation_hz 200
    for axis, a in zip("xyz", amplitude):
        got = float(np.median([getattr(m, f"vibration_{axis}") for m in vib]))
        # 5 %: the polled part samples at the loop's ticks, whose jitter the filters' dt follows
        expected = steady_level(a, freq, rate) if a else 0.0
        assert got == pytest.approx(expected, rel=0.05, abs=0.05), axis
    assert all(m.clipping_0 == m.clipping_1 == m.clipping_2 == 0 for m in vib)


def test_clipping_counted_when_the_simulated_accelerometer_saturates(tmp_path, gcs):
    conn, port = gcs
    # the ADXL345 is set to ±8 g (full scale 2047/256 g): it saturates near every peak. At 200 Hz
    # a 30 Hz sinusoid is sampled at 20 phases; 8 g / 9.1 g = 0.88 lies between two of their
    # |sin| values (0.81, 0.95), so the host's jitter does not move samples across it
    amplitude = 9.1 * G
    cfg = service_config(tmp_path, port, source={"profile": "static", "vibration_mss": [amplitude, 0.0, 0.0],
                                                 "vibration_hz": 30.0}, rates={"vibration_hz": 5})
    run = RunningService(cfg)
    try:
        msgs = collect(conn, 60.0, until=lambda m: len(_vibrations([m])) and m.time_usec > 3_000_000)
    finally:
        run.stop()
    last = _vibrations(msgs)[-1]
    log = read_log(run.service.log_writer.files[0])
    # the count is the log's: every row up to the message's sample that the part flagged
    # saturated or that is beyond the clip limit
    upto = (log.t_ns - run.service.boot_ns) // 1000 <= last.time_usec
    beyond = np.nan_to_num(np.abs(log.rows[:, 3:6])).max(axis=1) > CLIP_LIMIT_MSS
    expected = int(np.count_nonzero(upto & (((log.flags & ACC_SATURATED) != 0) | beyond)))
    assert last.clipping_0 == expected > 0 and last.clipping_1 == last.clipping_2 == 0
    # about the share of a sinusoid beyond full scale: (2/π)·acos(8 g / 9.1 g) ≈ 0.31
    share = expected / np.count_nonzero(upto)
    assert share == pytest.approx(2 / math.pi * math.acos(2047 / 256 * G / amplitude), abs=0.06)


@pytest.fixture
def gcs():
    from tests.test_service import make_gcs

    conn, port = make_gcs()
    yield conn, port
    conn.close()
