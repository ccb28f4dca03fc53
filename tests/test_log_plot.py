"""``ahrs-service log plot``: the figure's data (its lines), not only that a file exists."""

from __future__ import annotations

import sys

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from ahrs_service.cli import main  # noqa: E402
from ahrs_service.core.quaternion import quat_from_euler  # noqa: E402
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_VALID  # noqa: E402
from ahrs_service.logs import plot as plot_mod  # noqa: E402
from ahrs_service.logs.writer import FlightLogWriter  # noqa: E402

N = 12_000  # samples at 200 Hz: long enough that every per-sample series is decimated
SPIKE = 7_777  # the one sample with a gyro spike, which the envelope must keep
T0 = 5_000_000_000


def write_log(path_dir) -> tuple:
    t = np.arange(N) * 0.005
    roll = 0.5 * np.sin(t)
    gyr_x = 0.5 * np.cos(t)
    gyr_x[SPIKE] = 3.0
    w = FlightLogWriter(path_dir, fsync=False, tf_rate_hz=None)
    w.write_config(T0, {"estimator": {"name": "madgwick", "params": {}}})
    for i in range(N):
        t_ns = T0 + i * 5_000_000
        row = np.array([gyr_x[i], 0.0, 0.0, 0.0, 0.0, -9.8, 20.0, 0.0, 45.0, 0.005])
        q = np.array(quat_from_euler(roll[i], 0.0, 0.0))
        diag = {"mag_disturbed": 3_000 <= i < 6_000, "reduced": False} if i % 20 == 0 else None
        w.write_sample(t_ns, row, GYR_VALID | ACC_VALID | MAG_VALID, q=q, estimator="madgwick", bias=np.zeros(3),
                       truth_q=q, diagnostics=diag)
        if i % 200 == 0:
            w.write_loop(t_ns, {"period_jitter_p99_us": 100.0 + i / 200, "lateness_p99_us": 50.0,
                                "overruns": i // 4000, "missed_ticks": 2 * (i // 4000),
                                "source": {"lost": {"total": 5 * (i // 4000)}}})
    w.write_log(T0 + SPIKE * 5_000_000, 3, "sensor lost: test")
    w.close()
    (path,) = path_dir.glob("*.mcap")
    return path, t, roll, gyr_x


@pytest.fixture(scope="module")
def log_file(tmp_path_factory):
    return write_log(tmp_path_factory.mktemp("plotlog"))


def test_figure_shows_the_series_of_the_log(log_file, tmp_path, capsys):
    path, t, roll, gyr_x = log_file
    out = tmp_path / "flight.svg"
    assert main(["log", "plot", str(path), "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000 and out.read_text().lstrip().startswith("<?xml")
    assert f"{N} samples" in capsys.readouterr().out
    series, fig = plot_mod.plot_log(path, tmp_path / "flight.png", progress=False)
    ax_att, ax_gyr, _, ax_mag, ax_loop, ax_lost, ax_flags = fig.axes
    labels = [line.get_label() for line in ax_att.lines]
    assert labels == ["roll", "pitch", "yaw", "truth roll", "truth pitch", "truth yaw"]
    roll_line = ax_att.lines[0]
    x, y = roll_line.get_xdata(), roll_line.get_ydata()
    assert len(y) == 2 * plot_mod.DRAW_BINS < N  # decimated for drawing (min and max of each bin) …
    assert y.max() == pytest.approx(np.degrees(roll.max()), abs=1e-9)  # … keeping the extremes
    assert y.min() == pytest.approx(np.degrees(roll.min()), abs=1e-9)
    assert x[0] == 0.0 and x[-1] == pytest.approx(t[-(N // plot_mod.DRAW_BINS)])  # the last bin starts there
    gx = ax_gyr.lines[0].get_ydata()
    assert gx.max() == 3.0  # the one-sample spike is drawn
    assert ax_mag.lines[2].get_ydata() == pytest.approx(np.full_like(ax_mag.lines[2].get_ydata(), 45.0))
    jitter = ax_loop.lines[0]
    assert list(jitter.get_ydata()) == [100.0 + k for k in range(N // 200)]  # short: not decimated
    assert ax_lost.lines[0].get_ydata().max() == 5 * ((N - 1) // 4000)
    assert ax_lost.lines[1].get_ydata().max() == 2 * ((N - 1) // 4000)
    rejected = ax_flags.lines[0]
    on = rejected.get_xdata()[rejected.get_ydata() == 1.0]
    assert on.min() == pytest.approx(15.0) and on.max() == pytest.approx(29.9)
    marks = ax_flags.lines[2]
    assert marks.get_label() == "/log warning+" and list(marks.get_xdata()) == [pytest.approx(SPIKE * 0.005)]
    # the statistics come from the full arrays
    assert series.mag_rejected.mean() == pytest.approx(3000 / N, abs=0.01)
    assert "lost samples 10, overruns 2" in fig.texts[0].get_text()


def test_truncated_log_is_plotted_up_to_the_damage(log_file, tmp_path, capsys):
    path, t, _, _ = log_file
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) * 6 // 10])
    assert main(["log", "plot", str(cut), "--out", str(tmp_path / "cut.png")]) == 0
    err = capsys.readouterr().err
    assert "damaged" in err and "plotted up to the damage" in err and err.count("\n") == 1
    series, fig = plot_mod.plot_log(cut, tmp_path / "cut2.png", progress=False)
    assert 0 < series.raw_t[-1] < t[-1] * 0.8
    assert "TRUNCATED" in fig.texts[0].get_text()


def test_bad_arguments_and_missing_extra_give_one_line(log_file, tmp_path, capsys, monkeypatch):
    path = log_file[0]
    assert main(["log", "plot", str(path), "--out", str(tmp_path / "x.jpg")]) == 2
    assert main(["log", "plot", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "x.png")]) == 2
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["log", "plot", str(path), "--out", str(tmp_path / "x.png")]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 3 and "ahrs-service[analysis]" in lines[2] and "no such file" in lines[1] and ".svg" in lines[0]


def test_envelope_keeps_every_bin_extreme():
    rng = np.random.default_rng(3)
    y = rng.normal(size=100_003)
    t = np.arange(len(y), dtype=float)
    tt, yy = plot_mod.envelope(t, y, bins=1000)
    k = len(y) // 1000
    assert len(yy) == 2000 + len(y) - 1000 * k
    assert np.array_equal(yy[1:2000:2], y[: 1000 * k].reshape(1000, k).max(axis=1))
    assert yy.max() == y.max() and yy.min() == y.min()


def test_fast_scan_reads_what_the_mcap_library_reads(log_file, tmp_path):
    from ahrs_service.logs.fast_scan import scan_messages
    from ahrs_service.logs.reader import MessageSource

    path = log_file[0]
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    for f in (path, cut):
        topics = ("/imu/raw", "/attitude", "/loop", "/log", "/config")
        got: list = []
        result = scan_messages(f, {t: (lambda t_ns, d, t=t: got.append((t, t_ns, bytes(d)))) for t in topics})
        ref = [(t, t_ns, d) for t, t_ns, _, d in MessageSource(f, stream_only=True) if t in topics]
        assert got == ref and result.messages == len(ref) > 0
        assert (result.damage is None) == (f == path)
