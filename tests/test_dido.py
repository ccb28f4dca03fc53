"""The DIDO quadrotor flights (K. Zhang et al., "DIDO: Deep Inertial Quadrotor Dynamical
Odometry", RA-L 7(4), 2022, arXiv:2203.03149), read from ../shared/data/dido: skipped with the
loader's reason when absent.

The figures are asserted against VQF 6D (the ``vqf`` package, its defaults, at the flight's
fitted rate) and the best filters of the source papers at their defaults in the same run, not
against stored numbers. Measured 2026-12-02 (mean inclination RMSE of the 8 flights): robust
1.24° with recovered stamps (0.73 × VQF 6D's 1.71°; the issue's target is ≤ 0.85 ×), 1.60°
with the raw steps, 1.80° with the accelerometer time constant fixed at 3 s
(``tilt_rate_ref=0``); complementary_reduced 1.55°, valenti 1.66°.
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from ahrs_service import estimators
from ahrs_service.evaluation import command, dido, metrics, peers

DATA = dido.default_dir()
REASON = dido.missing_reason(DATA)
needs_data = pytest.mark.skipif(REASON is not None, reason=REASON or "")


def test_missing_folder_gives_a_clear_reason(tmp_path):
    reason = dido.missing_reason(tmp_path / "nowhere")
    assert "does not exist" in reason and dido.ENV_VAR in reason
    assert "holds no *.hdf5 flights" in dido.missing_reason(tmp_path)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        dido.list_trials(tmp_path / "nowhere")


def inclination(q_ned: np.ndarray, flight: dido.Flight) -> float:
    return metrics.score(q_ned, flight.ref, flight.movement, rate_hz=flight.rate_hz, with_heading=False).inclination_rmse


#: the source papers' filters that score best on the flights at their defaults (the others
#: are at 2.5° and above, docs/evaluation.md): robust must be no worse than either
PAPER_BEST = ("complementary_reduced", "valenti")


@pytest.fixture(scope="module")
def figures():
    """Per flight: robust (recovered stamps), robust (raw steps), VQF 6D."""
    out = {"robust": [], "robust_raw": [], "robust_fixed_tau": [], "vqf6d": [], "rates": []}
    out.update({name: [] for name in PAPER_BEST})
    for name in dido.list_trials(DATA):
        f = dido.load_trial(DATA, name)
        out["robust"].append(inclination(estimators.run("robust", f.gyr, f.acc, None, timestamps=f.timestamps), f))
        out["robust_raw"].append(
            inclination(estimators.run("robust", f.gyr, f.acc, None, timestamps=f.timestamps, recover_clock=False), f)
        )
        out["robust_fixed_tau"].append(
            inclination(estimators.run("robust", f.gyr, f.acc, None, timestamps=f.timestamps, tilt_rate_ref=0.0), f)
        )
        for paper in PAPER_BEST:
            out[paper].append(inclination(estimators.run(paper, f.gyr, f.acc, None, timestamps=f.timestamps), f))
        out["vqf6d"].append(inclination(peers.run("vqf", f.gyr, f.acc, f.mag, rate_hz=f.rate_hz), f))
        out["rates"].append(f.rate_hz)
    return {k: np.array(v) for k, v in out.items()}


@needs_data
def test_loader_reads_the_flights():
    names = dido.list_trials(DATA)
    assert len(names) >= 1
    f = dido.load_trial(DATA, names[0])
    n = len(f)
    assert f.gyr.shape == f.acc.shape == (n, 3) and f.ref.shape == (n, 4) and f.timestamps.shape == (n,)
    assert np.isnan(f.mag).all()
    assert f.movement.sum() == n - int(np.ceil(0.1 * n))
    # at rest the accelerometer reads about +9.8 m/s² along the axis pointing up
    assert 9.0 < np.linalg.norm(f.acc[:50].mean(axis=0)) < 10.6


@needs_data
@pytest.mark.skipif(not peers.PEERS["vqf"].available(), reason="the vqf package is not installed")
def test_robust_against_vqf_6d_in_the_same_run(figures):
    assert np.allclose(figures["rates"], 400.0, rtol=1e-3)  # the fitted rate of every flight
    robust, raw, vqf6d = figures["robust"].mean(), figures["robust_raw"].mean(), figures["vqf6d"].mean()
    # the acceptance: at most 0.85 × VQF 6D (measured 1.24° against 1.71°, 0.73×)
    assert robust <= 0.85 * vqf6d
    for paper in PAPER_BEST:  # measured 1.55° and 1.66°
        assert robust <= figures[paper].mean(), paper
    # clock recovery: the raw jittered steps cost robust over 20 % (measured 1.60° vs 1.24°)
    assert raw > 1.2 * robust
    # the tilt-rate time constant is what wins here: fixed at 3 s, 1.80° (1.05 × VQF)
    assert figures["robust_fixed_tau"].mean() > 1.3 * robust
    assert np.all(np.isfinite(figures["robust"])) and figures["robust"].max() < 1.5 * vqf6d  # measured 1.79° / 1.71°


@needs_data
def test_evaluate_dido_writes_the_report(tmp_path):
    parser = argparse.ArgumentParser()
    command.add_subcommands(parser.add_subparsers(dest="command"))
    shortest = min(dido.list_trials(DATA), key=lambda n: len(dido.load_trial(DATA, n)))
    args = parser.parse_args(
        ["evaluate", "--dataset", "dido", "--estimators", "robust", "--peers", "none",
         "--trials", shortest, "--out", str(tmp_path), "--quiet"]
    )
    assert args.func(args) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["dataset"] == "dido" and results["citation"] == dido.CITATION
    row = results["per_trial"]["robust"][shortest]
    assert row["total_rmse"] is None and row["heading_rmse"] is None  # no magnetometer: inclination only
    f = dido.load_trial(DATA, shortest)
    expected = inclination(estimators.run("robust", f.gyr, f.acc, None, timestamps=f.timestamps), f)
    assert row["inclination_rmse"] == pytest.approx(expected, rel=1e-12)
    md = (tmp_path / "results.md").read_text()
    assert "evaluation on DIDO" in md and "DIDO: Deep Inertial Quadrotor" in md
    assert (tmp_path / f"error_{shortest}.png").is_file()
