"""A fleet of generated logs (``benchmarks/fleet_logs.py``: simulated flights of varied
lengths, boards, rates and estimators, some truncated, some corrupt) replayed with results
streamed (``Runner.stream``: at most ``max_in_flight`` tasks out, the jobs read lazily, every
job once) into the journal: on a real LocalCluster, with the damaged logs named by kind in the
summary; a client killed mid-run (SIGKILL of ``ahrs-service replay``) and the re-run, through a
``dask scheduler`` + ``dask worker`` subprocess pair, which finishes the rest without redoing a
finished log and redoes an output cut short; ``--force`` redoes everything."""

from __future__ import annotations

import csv
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ahrs_service import fleet
from ahrs_service.cli import main as cli_main
from ahrs_service.execution import open_runner
from tests.dask_cluster import hand_started_cluster

pytest.importorskip("distributed")

_spec = importlib.util.spec_from_file_location(
    "fleet_logs", Path(__file__).resolve().parents[1] / "benchmarks" / "fleet_logs.py"
)
fleet_logs = importlib.util.module_from_spec(_spec)
sys.modules.setdefault("fleet_logs", fleet_logs)  # its dataclasses look their module up
_spec.loader.exec_module(fleet_logs)

COUNT = 24
SEED = 3


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory) -> tuple[Path, list]:
    d = tmp_path_factory.mktemp("generated_fleet")
    plan = fleet_logs.generate(d, COUNT, SEED, min_s=2.0, max_s=8.0, truncated=0.12, corrupt=0.12)
    faults = [log.fault for log in plan]
    # the seed gives both kinds of damage and a majority of intact logs
    assert faults.count("truncated") >= 1 and faults.count("corrupt") >= 1 and faults.count(None) >= COUNT // 2
    return d, plan


def _rows(path: Path) -> list[dict]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _square_after(job: tuple[int, float]) -> int:
    time.sleep(job[1])
    return job[0] * job[0]


@pytest.mark.timeout(120)
@pytest.mark.parametrize("workers", [1, 2])
def test_stream_yields_every_job_once_with_at_most_max_in_flight_out(workers):
    pulled = 0

    def jobs():
        nonlocal pulled
        for i in range(30):
            pulled += 1
            yield i, 0.05 * (i % 3)  # uneven durations: on 2 workers they finish out of order

    seen = []
    with open_runner(workers) as runner:
        for i, result in runner.stream(_square_after, jobs(), max_in_flight=3):
            # the jobs are read as tasks are submitted: never more than 3 out, plus the next one
            # submitted before this result is handed over
            assert pulled - len(seen) <= 4
            assert result == i * i
            seen.append(i)
    assert sorted(seen) == list(range(30))
    if workers == 1:
        assert seen == list(range(30))  # serially: in order


def test_generated_fleet_is_deterministic_and_varied(fleet_dir):
    d, plan = fleet_dir
    assert plan == fleet_logs.plan(COUNT, SEED, 2.0, 8.0, 0.12, 0.12)
    assert fleet_logs.plan(5, SEED, 2.0, 8.0, 0.12, 0.12) == plan[:5]  # a longer fleet starts alike
    assert len({log.board for log in plan}) > 1 and len({log.rate_hz for log in plan}) > 1
    assert all(2.0 <= log.seconds <= 8.0 for log in plan)
    assert sorted(p.name for p in d.glob("*.mcap")) == [log.name for log in plan]


@pytest.mark.timeout(300)
def test_generated_fleet_on_two_workers_names_each_damage(fleet_dir, tmp_path, capsys):
    d, plan = fleet_dir
    out = tmp_path / "out"
    assert cli_main(["replay", str(d), "--out", str(out), "--workers", "2"]) == 0
    rows = _rows(out / "fleet.csv")
    assert [Path(r["log"]).name for r in rows] == [log.name for log in plan]  # the logs' order
    for log, row in zip(plan, rows):
        assert row["error"] == ""  # damaged logs are replayed up to the damage
        assert (row["problem"] or None) == log.fault, row
        # a truncated log keeps fewer samples than it was written with, an intact one all
        if log.fault is None:
            assert int(row["samples"]) == log.samples and row["damage"] == ""
        else:
            assert 0 <= int(row["samples"]) < log.samples and row["damage"] != ""
        assert fleet.output_complete(row["output"], int(row["samples"]))
    n_trunc = sum(log.fault == "truncated" for log in plan)
    n_corrupt = sum(log.fault == "corrupt" for log in plan)
    text = (out / "summary.txt").read_text()
    assert text.startswith(f"{COUNT} log(s): {COUNT} replayed")
    assert f"truncated: {n_trunc} log(s), replayed up to the damage" in text
    assert f"corrupt: {n_corrupt} log(s), replayed up to the damage" in text
    assert text in capsys.readouterr().out
    # the journal holds one line per log, in the logs' order, equal to the table
    journal = [json.loads(line) for line in (out / "fleet.jsonl").read_text().splitlines()]
    assert [j["log"] for j in journal] == [r["log"] for r in rows]


def test_a_failed_log_is_counted_by_why(tmp_path):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all")
    missing = fleet.replay_one(fleet.ReplayJob(str(tmp_path / "gone.mcap"), None, {}, True, None, None))
    bad = fleet.replay_one(fleet.ReplayJob(str(garbage), None, {}, True, None, None))
    assert bad.problem == "not an MCAP file" and missing.problem == "missing"
    tally = fleet.FleetTally()
    for row in (bad, missing, bad):
        tally.add(row)
    text = tally.text()
    assert text.startswith("3 log(s): 0 replayed") and "3 failed" in text
    assert "not an MCAP file: 2 log(s), not replayed" in text and f"    {garbage}: " in text
    assert "missing: 1 log(s), not replayed" in text


def test_a_killed_run_resumed_through_a_scheduler_redoes_no_finished_log(fleet_dir, tmp_path):
    d, plan = fleet_dir
    out = tmp_path / "out"
    journal = out / fleet.JOURNAL_NAME
    cmd = [str(Path(sys.executable).with_name("ahrs-service")), "replay", str(d), "--out", str(out), "--workers", "1"]
    client = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while len(fleet.journal_logs(out)) < 4 and client.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        os.killpg(client.pid, signal.SIGKILL)
        client.wait(timeout=30)
    finally:
        if client.poll() is None:
            client.kill()
            client.wait(timeout=30)
    # killed mid-run: some logs finished, not all (else this test proves nothing)
    assert client.returncode == -signal.SIGKILL, client.stderr.read()
    finished = fleet.journal_logs(out)
    assert 4 <= len(finished) < COUNT
    assert not (out / "fleet.csv").exists()
    stamps = {log: os.stat(json.loads(_line(journal, log))["output"]).st_mtime_ns for log in finished}
    # one finished output cut short afterwards, as a write interrupted by a crash leaves it: invalid, redone
    cut_log = finished[1]
    cut_output = Path(json.loads(_line(journal, cut_log))["output"])
    cut_output.write_bytes(cut_output.read_bytes()[: cut_output.stat().st_size // 2])
    assert not fleet.output_complete(cut_output, 10)

    with hand_started_cluster(workers=1) as address:
        assert cli_main(["replay", str(d), "--out", str(out), "--scheduler", address]) == 0
    rows = _rows(out / "fleet.csv")
    assert [Path(r["log"]).name for r in rows] == [log.name for log in plan]
    assert all(r["error"] == "" and fleet.output_complete(r["output"], int(r["samples"])) for r in rows)
    by_log = {r["log"]: r for r in rows}
    for log, stamp in stamps.items():
        redone = os.stat(by_log[log]["output"]).st_mtime_ns != stamp
        assert redone == (log == cut_log), log
    skipped = len(finished) - 1
    assert f"{COUNT} log(s): {COUNT} replayed" in (out / "summary.txt").read_text()
    assert f"{skipped} of them done by a previous run" in (out / "summary.txt").read_text()

    # a third run has nothing to do; with --force it redoes every log
    stamps = {r["log"]: os.stat(r["output"]).st_mtime_ns for r in rows}
    assert cli_main(["replay", str(d), "--out", str(out), "--workers", "1"]) == 0
    assert all(os.stat(r["output"]).st_mtime_ns == stamps[r["log"]] for r in rows)
    assert f"{COUNT} of them done by a previous run" in (out / "summary.txt").read_text()
    assert cli_main(["replay", str(d), "--out", str(out), "--workers", "1", "--force"]) == 0
    assert all(os.stat(r["output"]).st_mtime_ns != stamps[r["log"]] for r in rows)
    assert "done by a previous run" not in (out / "summary.txt").read_text()
    assert _rows(out / "fleet.csv") == rows  # the same replay, whichever run did it


def _line(journal: Path, log: str) -> str:
    """The journal's last complete line for ``log``."""
    lines = [line for line in journal.read_bytes().split(b"\n")[:-1] if _log_of(line) == log]
    return lines[-1].decode()


def _log_of(line: bytes) -> str | None:
    try:
        return json.loads(line)["log"]
    except ValueError:
        return None
