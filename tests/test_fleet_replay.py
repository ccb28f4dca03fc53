"""Fleet replay: ``ahrs-service replay DIR --out DIR`` over several logs, one a truncated copy,
on a real LocalCluster of 2 worker processes: every log's new log, one table row per log
(CSV and Parquet, read back), the damaged log replayed up to its damage, the rows equal to the
serial run's, in the logs' order."""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest

from ahrs_service import fleet
from ahrs_service.cli import main as cli_main
from ahrs_service.logs.reader import read_log

pq = pytest.importorskip("pyarrow.parquet")
pytest.importorskip("distributed")

_spec = importlib.util.spec_from_file_location(
    "make_fixtures", Path(__file__).resolve().parent / "fixtures" / "make_fixtures.py"
)
make_fixtures = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(make_fixtures)


@pytest.fixture(scope="module")
def logs_dir(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("fleet")
    for name, seconds in (("a", 2.0), ("b", 3.0)):
        sub = tmp_path_factory.mktemp(name)
        path = make_fixtures.record_analytic(sub, seconds=seconds)[0]
        (d / f"{name}.mcap").write_bytes(Path(path).read_bytes())
    whole = (d / "b.mcap").read_bytes()
    (d / "c_truncated.mcap").write_bytes(whole[: len(whole) * 2 // 3])  # cut mid-file, as a power loss
    return d


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.timeout(180)
def test_fleet_replay_on_two_workers_equals_serial_and_reports_the_damaged_log(logs_dir, tmp_path, capsys):
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    assert cli_main(["replay", str(logs_dir), "--out", str(serial), "--workers", "1"]) == 0
    assert cli_main(["replay", str(logs_dir / "*.mcap"), "--out", str(parallel), "--workers", "2"]) == 0
    rows = _rows(parallel / "fleet.csv")
    assert [Path(r["log"]).name for r in rows] == ["a.mcap", "b.mcap", "c_truncated.mcap"]
    strip = lambda rs: [{k: v for k, v in r.items() if k != "output"} for r in rs]  # noqa: E731
    assert strip(rows) == strip(_rows(serial / "fleet.csv"))
    a, b, c = rows
    assert a["damage"] == "" and b["damage"] == "" and c["damage"] != ""
    # the recorded estimator replayed as recorded: no difference; the truncated log has fewer samples
    assert float(a["rms_diff_vs_recorded_deg"]) == 0.0 and float(b["rms_diff_vs_recorded_deg"]) == 0.0
    assert 0 < int(c["samples"]) < int(b["samples"]) and a["error"] == b["error"] == c["error"] == ""
    # against the recording's truth: a real error, neither zero (truth against itself) nor
    # NaN (no truth found); measured 1.05 deg
    assert int(a["lost_samples"]) == 0 and 0.0 < float(a["truth_total_rmse_deg"]) < 5.0
    # the truth column is the single-log comparison's (what was replayed is what was recorded)
    from ahrs_service.replay import compare

    log_a = read_log(logs_dir / "a.mcap")
    assert float(a["truth_total_rmse_deg"]) == pytest.approx(compare(log_a, log_a.attitudes)["vs_truth"]["total"], rel=1e-12)
    # Parquet holds the same table
    table = pq.read_table(parallel / "fleet.parquet").to_pylist()
    assert [t["samples"] for t in table] == [int(r["samples"]) for r in rows]
    assert table[2]["damage"] == c["damage"] and table[0]["damage"] is None
    # every log got its new log, readable, as long as its input
    for r in rows:
        assert len(read_log(r["output"])) == int(r["samples"])
    assert "3 log(s): 3 replayed" in (parallel / "summary.txt").read_text()


def test_an_unreadable_log_is_a_row_and_the_others_complete(logs_dir, tmp_path):
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(b"not an mcap file at all")
    out = tmp_path / "o"
    code = cli_main(["replay", str(logs_dir / "a.mcap"), str(bad), "--out", str(out), "--workers", "1"])
    assert code == 1  # something failed: said in the exit code
    rows = _rows(out / "fleet.csv")
    assert rows[0]["error"] == "" and int(rows[0]["samples"]) > 0
    assert rows[1]["log"].endswith("garbage.mcap") and rows[1]["error"] != ""


def test_missing_logs_and_a_file_as_fleet_output_are_errors(logs_dir, tmp_path, capsys):
    assert cli_main(["replay", str(tmp_path / "none*.mcap"), "--out", str(tmp_path / "o")]) == 2
    assert "none*.mcap" in capsys.readouterr().err
    assert cli_main(["replay", str(logs_dir), "--out", str(logs_dir / "a.mcap")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert cli_main(["replay", str(logs_dir)]) == 2
    assert "--out DIR" in capsys.readouterr().err


def test_lost_samples_count_whole_missing_periods():
    import numpy as np

    assert fleet._lost_samples(np.array([0, 1, 2, 5, 6, 8])) == 3
    assert fleet._lost_samples(np.array([7])) == 0
