"""BROAD import (HDF5 → MCAP with NED truth), replay against truth, and recorded playback.

BROAD: D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD — A Benchmark for Robust Inertial
Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072 (CC BY 4.0).
"""

from __future__ import annotations

import json
import time

import h5py
import numpy as np
import pytest
from analytic import error_deg
from mcap.reader import make_reader

from ahrs_service.cli import main as cli_main
from ahrs_service.core.quaternion import ned_to_enu_array
from ahrs_service.evaluation.broad_import import CITATION, import_broad
from ahrs_service.logs.reader import read_log
from ahrs_service.recorded import RecordedSource
from ahrs_service.replay import compare, replay

TRIAL = "02_undisturbed_slow_rotation_B.hdf5"
START_S, DURATION_S = 20.0, 30.0


@pytest.fixture(scope="module")
def imported(broad_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("broad") / "trial02.mcap"
    summary = import_broad(broad_dir / TRIAL, out, START_S, DURATION_S)
    with h5py.File(broad_dir / TRIAL, "r") as h5:
        rate = float(h5.attrs["sampling_rate"])
        a = int(round(START_S * rate))
        b = a + int(round(DURATION_S * rate))
        ref = {k: np.asarray(h5[k][a:b]) for k in ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement")}
    return out, summary, ref, rate, a


def test_import_keeps_samples_exact_and_truth_in_ned(imported):
    out, summary, ref, rate, a = imported
    log = read_log(out)
    n = len(ref["imu_gyr"])
    assert len(log) == summary["samples"] == n and log.damage is None
    assert np.array_equal(log.rows[:, 0:3], ref["imu_gyr"])
    assert np.array_equal(log.rows[:, 3:6], ref["imu_acc"])
    assert np.array_equal(log.rows[:, 6:9], ref["imu_mag"])
    assert np.all(log.rows[:, 9] == 1.0 / rate)
    assert np.array_equal(log.t_ns, np.round(np.arange(a, a + n) * (1e9 / rate)).astype(np.int64))
    finite = np.all(np.isfinite(ref["opt_quat"]), axis=1)
    assert log.counts["/attitude/truth"] == finite.sum() == summary["truth_samples"]
    # back to ENU, the truth is BROAD's reference again
    back = ned_to_enu_array(log.truth[finite])
    assert np.allclose(back, ref["opt_quat"][finite], atol=1e-15)
    assert np.array_equal(log.movement[finite], ref["movement"][finite])
    with open(out, "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    assert meta["broad"]["citation"] == CITATION and "10.3390/data6070072" in CITATION


def test_madgwick_replay_error_vs_truth(imported):
    out, _, ref, _, _ = imported
    log = read_log(out)
    q = replay(log, "madgwick")
    result = compare(log, q)["vs_truth"]
    # measured on this slice: total 1.31°, heading 1.16°, inclination 0.61° (β = 0.1)
    assert result["total"] < 2.0 and result["inclination"] < 1.0
    # the benchmark's own way — estimate turned into ENU against opt_quat — gives the same figures
    mask = ref["movement"] & np.all(np.isfinite(ref["opt_quat"]), axis=1)
    total, heading, incl = error_deg(ned_to_enu_array(q[mask]), ref["opt_quat"][mask])
    assert result["samples"] == mask.sum()
    assert result["total"] == pytest.approx(np.sqrt(np.mean(total**2)), abs=1e-9)
    assert result["heading"] == pytest.approx(np.sqrt(np.mean(heading**2)), abs=1e-9)
    assert result["inclination"] == pytest.approx(np.sqrt(np.mean(incl**2)), abs=1e-9)


def test_cli_import_broad(broad_dir, tmp_path, capsys):
    out = tmp_path / "slice.mcap"
    assert cli_main(["log", "import-broad", str(broad_dir / TRIAL), str(out), "--start", "5", "--duration", "1"]) == 0
    summary = json.loads(capsys.readouterr().out)
    log = read_log(out)
    assert summary["samples"] == len(log) == 286  # 1 s at 285.714 Hz
    assert log.index[0] == round(5 * 285.7142857142857)


def test_recorded_source_plays_hdf5_as_fast_as_possible(broad_dir):
    src = RecordedSource(broad_dir / TRIAL, realtime=False, start_s=10.0, duration_s=0.5)
    src.open()
    samples = []
    for _ in range(10_000):  # bounded
        s = src.read()
        if s is None:
            break
        samples.append(s)
    assert src.finished and len(samples) == len(src) == 143
    with h5py.File(broad_dir / TRIAL, "r") as h5:
        a = int(round(10.0 * float(h5.attrs["sampling_rate"])))
        gyr = np.asarray(h5["imu_gyr"][a : a + 143])
    assert np.array_equal(np.array([s.gyr for s in samples]), gyr)
    assert all(s.truth_q is not None and s.mag is not None for s in samples)
    assert np.all(np.diff([s.t_ns for s in samples]) > 0)


def test_recorded_source_paces_a_log_in_real_time(imported, monkeypatch):
    """Paced on a fake monotonic clock: a sample is handed out exactly when its recorded
    offset from the first one has elapsed, never before."""
    import types

    from ahrs_service import recorded as source_mod

    now = {"ns": 5_000_000_000}
    monkeypatch.setattr(source_mod, "time", types.SimpleNamespace(monotonic_ns=lambda: now["ns"]))
    out, _, _, rate, _ = imported
    src = RecordedSource(out, realtime=True)
    src.open()
    offsets = np.asarray(src.t_ns - src.t_ns[0], dtype=np.int64)
    assert offsets[1] == pytest.approx(1e9 / rate, abs=1)  # 3.5 ms at 285.714 Hz
    t0 = now["ns"]
    first = src.read()
    assert first is not None and first.t_ns == t0  # rebased on the host clock
    # right after the first sample the next one is not due yet: a live sensor has nothing new
    assert src.read() is None
    now["ns"] = t0 + int(offsets[1]) - 1
    assert src.read() is None  # 1 ns early
    now["ns"] = t0 + int(offsets[1])
    second = src.read()
    assert second is not None and second.t_ns == t0 + offsets[1] and src.read() is None
    # 0.3 s of playback in 0.5 ms steps: every due sample, in order, none early, none dropped
    got = [first.t_ns, second.t_ns]
    while now["ns"] < t0 + 300_000_000:
        now["ns"] += 500_000
        s = src.read()
        if s is not None:
            assert s.t_ns <= now["ns"]  # never ahead of the recording's clock
            got.append(s.t_ns)
    due = int(np.searchsorted(offsets, now["ns"] - t0, side="right"))
    assert np.array_equal(np.asarray(got) - t0, offsets[:due])
    assert src.diagnostics.dropped_frames == 0 and not src.finished


def test_recorded_source_catches_up_in_order_after_a_late_read():
    """A replay must not lose samples when the loop is late: the missed ones come in order."""
    from pathlib import Path

    from ahrs_service.recorded import RecordedSource

    fixture = Path(__file__).parent / "fixtures" / "logs" / "analytic_madgwick.mcap"
    for catch_up in (True, False):
        src = RecordedSource(fixture, realtime=True, catch_up=catch_up)
        src.open()
        first = src.read()
        time.sleep(0.1)  # a stall of 100 ms
        got = []
        for _ in range(10_000):
            s = src.read()
            if s is None:
                break
            got.append(s.t_ns)
        step = int(np.median(np.diff(src.t_ns)))
        if catch_up:
            assert len(got) >= 0.1 * 1e9 / step - 1
            # consecutive recorded samples: the same time steps as the recording
            seq = np.array([first.t_ns] + got)
            assert np.array_equal(np.diff(seq), np.diff(np.asarray(src.t_ns[: len(seq)], dtype=np.int64)))
            assert src.diagnostics.dropped_frames == 0
        else:
            assert len(got) == 1 and src.diagnostics.dropped_frames >= 0.1 * 1e9 / step - 2
