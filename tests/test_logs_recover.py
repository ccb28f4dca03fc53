"""Crash safety: a killed writer's file is recovered up to about one flush interval before the kill;
truncated and corrupted files are read up to the damage, and the damage is reported."""

from __future__ import annotations

import io
import struct

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Footer
from mcap.stream_reader import StreamReader

from ahrs_service.cli import main as cli_main
from ahrs_service.logs.reader import read_log
from ahrs_service.logs.recover import RecordScanner, recover
from ahrs_service.logs.writer import FlightLogWriter

FLUSH_S = 1.0

CHILD = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from ahrs_service.logs.writer import FlightLogWriter

    # chunks far larger than 3 s of data: only the flush interval closes them
    w = FlightLogWriter(sys.argv[1], flush_interval_s={flush}, chunk_size=1 << 26)
    w.write_config(time.monotonic_ns(), {{"estimator": {{"name": "madgwick", "params": {{"beta": 0.1}}}}}})
    row = np.zeros(10)
    next_t = time.monotonic()
    for i in range(10**7):  # the parent kills us long before this ends
        next_t += 0.001
        while time.monotonic() < next_t:
            time.sleep(0.0002)
        t = time.monotonic_ns()
        row[0] = i
        w.write_raw(t, row, 3)
        w.write_attitude(t, [1.0, 0.0, 0.0, 0.0], "madgwick")
        if i == 0:
            print("started", t, flush=True)
    """
).format(flush=FLUSH_S)


def _valid_indexed(path: Path) -> dict[str, int]:
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes
        counts: dict[str, int] = {}
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_sigkill_loses_at_most_about_one_flush_interval(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    logs = tmp_path / "logs"
    proc = subprocess.Popen([sys.executable, str(script), str(logs)], stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # blocks until the first sample is written
        assert line.startswith("started"), line
        first_ns = int(line.split()[1])
        time.sleep(3.0)
        kill_ns = time.monotonic_ns()
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    (crashed,) = logs.glob("*.mcap")

    damaged = read_log(crashed)
    assert damaged.damage is not None and not damaged.indexed

    report = recover(crashed, tmp_path / "recovered.mcap")
    assert report.damage is not None
    assert report.bytes_valid + report.bytes_lost == crashed.stat().st_size
    counts = _valid_indexed(tmp_path / "recovered.mcap")
    assert counts == report.messages and counts["/config"] == 1

    log = read_log(tmp_path / "recovered.mcap")
    assert log.damage is None and log.indexed
    # no holes: every sample up to the last saved one is there, in order
    assert np.array_equal(log.index, np.arange(len(log)))
    assert np.all(np.diff(log.t_ns) > 0) and log.t_ns[0] == first_ns
    gap_s = (kill_ns - int(log.t_ns[-1])) / 1e9
    # flushed every FLUSH_S; 0.5 s more for a writer thread that waits for a busy, shared CPU
    assert 0.0 < gap_s < FLUSH_S + 0.5, gap_s
    # a flush may fall between a sample's raw message and its attitude: only the last may miss it
    assert np.array_equal(log.attitudes[:-1, 0], np.ones(len(log) - 1))


def _complete_log(tmp_path: Path, n: int = 3000) -> tuple[Path, np.ndarray]:
    rows = np.random.default_rng(1).normal(size=(n, 10))
    w = FlightLogWriter(tmp_path / "complete", chunk_size=8192)
    w.write_config(0, {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}})
    for i, row in enumerate(rows):
        w.write_raw(i + 1, row, 3)
        w.write_attitude(i + 1, [1.0, 0.0, 0.0, 0.0], "madgwick")
    w.close()
    return w.files[0], rows


def _summary_start(data: bytes) -> int:
    """Where the summary section begins (the file's Footer record, read with mcap)."""
    footer = next(r for r in StreamReader(io.BytesIO(data)).records if isinstance(r, Footer))
    assert 0 < footer.summary_start < len(data)
    return footer.summary_start


# a cut in the summary section (5 bytes into its first record: a fraction of the file there
# fell on a record boundary in 3 runs of 15, the writer's time-paced flushes moving the
# file's size by a few hundred bytes): the damage is reported, no sample is lost
@pytest.mark.parametrize("fraction, all_kept", [(0.3, False), (0.77, False), ("summary", True)])
def test_truncated_file_is_read_up_to_the_damage(tmp_path, fraction, all_kept):
    path, rows = _complete_log(tmp_path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    end = _summary_start(data) + 5 if fraction == "summary" else int(len(data) * fraction)
    cut.write_bytes(data[:end])

    log = read_log(cut)
    assert log.damage is not None and not log.indexed
    assert 0 < log.damage.offset <= cut.stat().st_size
    assert 0 < len(log) <= len(rows) and (len(log) == len(rows)) == all_kept
    assert np.array_equal(log.rows, rows[: len(log)])  # a bit-exact prefix

    report = recover(cut, tmp_path / "fixed.mcap")
    assert report.messages["/imu/raw"] == len(log)
    assert report.bytes_lost == cut.stat().st_size - report.damage.offset > 0
    assert report.damage.offset == log.damage.offset
    assert _valid_indexed(tmp_path / "fixed.mcap") == report.messages


def test_corrupted_chunk_stops_reading_at_that_chunk(tmp_path):
    path, rows = _complete_log(tmp_path)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) > 4
    middle = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    mid = middle.chunk_start_offset + middle.chunk_length // 2
    data[mid : mid + 16] = bytes(16)  # a torn write inside the compressed data of one chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    scanner = RecordScanner(bad)
    records = list(scanner)
    assert records and scanner.damage is not None
    assert scanner.damage.offset == middle.chunk_start_offset  # everything before it is kept
    log = read_log(bad)  # the summary is intact, the chunk is not: read_log finds it too
    assert log.damage is not None and log.damage.offset == middle.chunk_start_offset
    assert 0 < len(log) < len(rows) and np.array_equal(log.rows, rows[: len(log)])
    report = recover(bad, tmp_path / "fixed.mcap")
    assert 0 < report.messages["/imu/raw"] < len(rows)
    log = read_log(tmp_path / "fixed.mcap")
    assert np.array_equal(log.rows, rows[: len(log)])


def test_the_indexed_read_goes_chunk_by_chunk(tmp_path):
    """A complete file is read through its index one chunk at a time, in file order: a
    damaged chunk (its summary intact) stops the read there, after the earlier chunks'
    messages came out, not before the first (the mcap library's unordered read decompresses
    every chunk, holding a whole log's messages, before it yields one)."""
    from ahrs_service.logs.reader import MessageSource

    path, rows = _complete_log(tmp_path)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    sound = [topic for topic, *_ in MessageSource(path)]
    assert sound.count("/imu/raw") == len(rows)
    middle = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    mid = middle.chunk_start_offset + middle.chunk_length // 2
    data[mid : mid + 16] = bytes(16)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    source = MessageSource(bad)
    before_damage = [topic for topic, *_ in source]
    assert source.indexed and source.damage is not None
    assert before_damage == sound[: len(before_damage)]  # the same messages, the same order
    assert 0 < before_damage.count("/imu/raw") < len(rows)


def _record_end_at_or_after(data: bytes, offset: int) -> int:
    """Where the MCAP record that holds byte ``offset`` of ``data`` ends (records: opcode u8,
    length u64, body; after the 8-byte magic)."""
    pos = 8
    while pos < offset:
        _opcode, length = struct.unpack_from("<BQ", data, pos)
        pos += 9 + length
    return pos


def test_zero_filled_tail_after_power_loss(tmp_path):
    path, rows = _complete_log(tmp_path)
    data = path.read_bytes()
    torn = tmp_path / "torn.mcap"
    keep = int(len(data) * 0.6)
    torn.write_bytes(data[:keep] + bytes(4096))  # the file system extended the file with zeros
    report = recover(torn, tmp_path / "fixed.mcap")
    # the damage is found at the cut, or at the end of the record the cut falls in: a record
    # without a CRC (a Message, an index) whose tail became zeros reads as valid data
    end = _record_end_at_or_after(data, keep)
    assert report.damage is not None and report.damage.offset <= end
    assert report.bytes_lost >= keep + 4096 - end  # every zero past that record
    assert _valid_indexed(tmp_path / "fixed.mcap")["/imu/raw"] == report.messages["/imu/raw"] > 0


def test_complete_file_recovers_without_damage(tmp_path):
    path, rows = _complete_log(tmp_path)
    report = recover(path)
    assert report.damage is None and report.bytes_lost == 0
    # /tf at its default 50 Hz: the samples are 1 ns apart, so only the first attitude gets one
    assert report.messages == {"/config": 1, "/imu/raw": len(rows), "/attitude": len(rows), "/tf": 1}
    assert Path(report.output).name.endswith(".recovered.mcap")
    assert np.array_equal(read_log(report.output).rows, rows)


def test_not_an_mcap_file_is_damage_not_a_crash(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"hello world, not an mcap file")
    log = read_log(junk)
    assert log.damage is not None and log.damage.offset == 0 and len(log) == 0


def test_cli_recover_and_info(tmp_path, capsys):
    path, rows = _complete_log(tmp_path)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert cli_main(["log", "info", str(cut)]) == 1  # damage is a non-zero exit
    assert "damaged at byte" in capsys.readouterr().out
    assert cli_main(["log", "recover", str(cut), str(tmp_path / "out.mcap")]) == 0
    out = capsys.readouterr().out
    assert "/imu/raw" in out and "damaged at byte" in out
    assert cli_main(["log", "info", str(tmp_path / "out.mcap")]) == 0
