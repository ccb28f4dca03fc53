"""Inputs that are bounded before they are trusted: the bytes a log read may decompress, the
values and the nesting of a preset file, and the names a fleet replay gives its outputs.

- A log whose chunks state more than the read budget (or thousands of times their file's
  size: a decompression bomb) is refused before its first chunk is decompressed, with one
  line naming the path and where the chunk that crosses the limit starts; a fleet replay
  lists it as failed.
- A preset file is held to the bounds of ``[estimator] params`` (from the estimator's own
  defaults and paper values, never from the preset), and JSON nested 100 000 deep is one
  error line.
- ``x/f.mcap`` and ``y/x/f.mcap`` replayed together get two outputs.
"""

from __future__ import annotations

import csv
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import pytest
import zstandard
from mcap.writer import CompressionType, Writer

from ahrs_service import estimators, fleet
from ahrs_service.cli import main
from ahrs_service.logs.reader import read_log
from ahrs_service.logs.schemas import CHANNELS, schema_bytes

pytestmark = pytest.mark.timeout(120)

MAGIC = b"\x89MCAP0\r\n"
RAW = {"t_ns": 0, "index": 0, "dt": 0.005, "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, -9.81],
       "mag": [20.0, 0.0, 40.0], "flags": 7}
N = 40


def _run(capsys, argv) -> tuple[int, str, str]:
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err.strip()


def _rec(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def _str(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


def _chunk(records: bytes, compressed: bytes | None = None, size: int | None = None, crc: int | None = None) -> bytes:
    """A zstd Chunk record holding ``records`` (or the given compressed stream, size and CRC)."""
    compressed = zstandard.ZstdCompressor(level=1).compress(records) if compressed is None else compressed
    size = len(records) if size is None else size
    crc = zlib.crc32(records) if crc is None else crc
    return _rec(0x06, struct.pack("<QQQI", 0, 0, size, crc) + _str("zstd") + struct.pack("<Q", len(compressed)) + compressed)


def _raw_record(i: int) -> bytes:
    t = (i + 1) * 5_000_000
    return _rec(0x05, struct.pack("<HIQQ", 1, 0, t, t) + json.dumps({**RAW, "t_ns": t, "index": i}).encode())


def _bomb_file(path: Path, chunks: list[bytes]) -> Path:
    """An MCAP file (header, /imu/raw schema and channel, a chunk with one sound sample, then
    ``chunks``, footer): what a writer that lies or repeats itself would produce."""
    schema = _rec(0x03, struct.pack("<H", 1) + _str("ahrs.ImuRaw") + _str("jsonschema") + struct.pack("<I", 2) + b"{}")
    channel = _rec(0x04, struct.pack("<HH", 1, 1) + _str("/imu/raw") + _str("json") + struct.pack("<I", 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    body = _rec(0x01, _str("") + _str("test")) + schema + channel + _chunk(_raw_record(0)) + b"".join(chunks)
    path.write_bytes(MAGIC + body + _rec(0x02, struct.pack("<QQI", 0, 0, 0)) + MAGIC)
    return path


def _row_bomb(path: Path, chunks: int, rows_per_chunk: int) -> Path:
    """``chunks`` copies of one chunk of ``rows_per_chunk`` identical /imu/raw samples: a few
    hundred bytes of file per chunk, as the 8.7 kB log that read as 762 600 rows."""
    chunk = _chunk(_raw_record(1) * rows_per_chunk)
    return _bomb_file(path, [chunk] * chunks)


def _zero_bomb(mib: int) -> bytes:
    """One chunk stating (and holding) ``mib`` MiB of zeros, in a few kB."""
    c = zstandard.ZstdCompressor(level=1).compressobj()
    block, crc, out = bytes(1 << 20), 0, b""
    for _ in range(mib):
        out += c.compress(block)
        crc = zlib.crc32(block, crc)
    return _chunk(b"", out + c.flush(), mib << 20, crc)


def write_flight(path: Path, *, config: dict | None = None, n: int = N) -> Path:
    """A sound flight log (the mcap library's writer, this project's channels): /config, then
    ``n`` samples of a level, still sensor with their /attitude."""
    path.parent.mkdir(parents=True, exist_ok=True)
    config = config or {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}}
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        ch = {}
        for topic in ("/config", "/imu/raw", "/attitude"):
            ch[topic] = w.register_channel(topic, "json", w.register_schema(CHANNELS[topic][0], "jsonschema", schema_bytes(topic)))
        w.add_message(ch["/config"], 0, json.dumps({"t_ns": 0, "config": config, "reason": "start"}).encode(), 0)
        for i in range(n):
            t = (i + 1) * 5_000_000
            w.add_message(ch["/imu/raw"], t, json.dumps({**RAW, "t_ns": t, "index": i}).encode(), t)
            att = {"t_ns": t, "q": [1.0, 0.0, 0.0, 0.0], "roll": 0.0, "pitch": 0.0, "yaw": 0.0, "estimator": "madgwick"}
            w.add_message(ch["/attitude"], t, json.dumps(att).encode(), t)
        w.finish()
    return path


# ------------------------------------------------------------------ decompression budget
def test_a_decompression_bomb_is_refused_before_it_is_decompressed(tmp_path, capsys):
    """200 MiB of zeros in one chunk of a 10 kB file (within the per-chunk limit, so it was
    decompressed whole before finding no record in it): refused by its expansion, having
    allocated next to nothing, with one line naming the path and the chunk."""
    path = _bomb_file(tmp_path / "zeros.mcap", [_zero_bomb(200)])
    size = path.stat().st_size
    assert size < 64 * 1024
    tracemalloc.start()
    try:
        with pytest.raises(ValueError) as refused:
            read_log(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 << 20, peak  # the bomb's 200 MiB never allocated
    text = str(refused.value)
    assert "\n" not in text and text.startswith(f"{path}: refused, nothing read: the chunk at byte ") and f" of {size} " in text
    assert "more than 100 times the file's" in text
    rc, out, err = _run(capsys, ["log", "info", path])
    assert rc == 2 and out == "" and err.count("\n") == 0 and "refused" in err and "Traceback" not in err


def test_the_read_budget_refuses_a_log_of_repeated_rows_and_fleet_lists_it_as_failed(tmp_path, capsys):
    """A row bomb (8 chunks of 2 000 identical samples, 4 kB of file for 1.6 MB of rows) under
    a 1 MiB budget: ``replay`` refuses it in one line; in a fleet it is a failed row with that
    reason, beside a sound log replayed as usual."""
    bomb = _row_bomb(tmp_path / "bombs" / "rows.mcap", chunks=8, rows_per_chunk=2_000)
    assert len(read_log(bomb)) == 8 * 2_000 + 1  # the default budget reads it: 1.6 MB is no real log's limit
    rc, out, err = _run(capsys, ["replay", bomb, "--estimator", "madgwick", "--read-budget-mb", "1"])
    assert rc == 2 and out == "" and err.count("\n") == 0, err
    assert "refused" in err and "the read budget of 1 MiB (--read-budget-mb)" in err
    good = write_flight(tmp_path / "good" / "f.mcap")
    job = dict(estimator="madgwick", params={}, follow_param_changes=True, blend_time_s=None, out_path=None,
               budget_bytes=1 << 20)
    rows = [fleet.replay_one(fleet.ReplayJob(path=str(p), **job)) for p in (good, bomb)]
    assert rows[0].error is None and rows[0].samples == N
    assert rows[1].samples is None and rows[1].error.startswith(f"{bomb}: refused, nothing read: the chunk at byte ")
    assert "the read budget of 1 MiB" in rows[1].error
    assert fleet.summary(rows).splitlines()[0].startswith("2 log(s): 1 replayed") and "1 failed" in fleet.summary(rows)
    rc, out, err = _run(capsys, ["replay", "--read-budget-mb", "nan", bomb, "--estimator", "madgwick"])
    assert rc == 2 and "--read-budget-mb: nan must be a number of MiB above 0" in err


# ---------------------------------------------------------------------------- presets
def _preset(path: Path, params: dict | str) -> Path:
    text = params if isinstance(params, str) else json.dumps({"estimator": "madgwick", "params": params})
    path.write_text(text, encoding="utf-8")
    return path


def _config(path: Path, preset: Path) -> Path:
    path.write_text(f'[estimator]\nname = "madgwick"\npreset = "{preset}"\n\n[log]\nenabled = false\n\n'
                    '[mavlink]\nendpoints = ["udpout:127.0.0.1:9"]\n', encoding="utf-8")
    return path


def test_a_preset_is_held_to_the_bounds_of_estimator_params(tmp_path, capsys):
    """``beta = 1e300`` from a preset file (before: its own value was the range's reference, so
    it passed and the filter published a constant attitude) is refused by ``config --check``
    and ``run`` alike, in one line naming the file and the key; a value within the estimator's
    own range still passes."""
    preset = _preset(tmp_path / "huge.json", {"beta": 1e300})
    cfg = _config(tmp_path / "ahrs.toml", preset)
    for argv in (["config", "--check", cfg], ["run", "--config", cfg, "--duration", "1"]):
        rc, out, err = _run(capsys, argv)
        assert rc == 2 and err.count("\n") == 0, (argv, err)
        assert str(preset) in err and "params.beta = 1e+300: must be within 0 …" in err, err
    with pytest.raises(ValueError, match="params.beta = 1e\\+300"):
        estimators.create("madgwick", preset=preset)
    fine = _preset(tmp_path / "fine.json", {"beta": 0.5})
    rc, out, err = _run(capsys, ["config", "--check", _config(tmp_path / "fine.toml", fine)])
    assert rc == 0 and "beta = 0.5" in out, err


def test_a_preset_nested_100000_deep_is_one_line(tmp_path, capsys):
    deep = _preset(tmp_path / "deep.json", '{"estimator": "madgwick", "params": ' + "[" * 100_000 + "]" * 100_000 + "}")
    rc, out, err = _run(capsys, ["config", "--check", _config(tmp_path / "deep.toml", deep)])
    assert rc == 2 and err.count("\n") == 0 and "Traceback" not in err and "RecursionError" not in err, err
    assert str(deep) in err and "nested 100001 levels deep, more than 32" in err


# ---------------------------------------------------------------------- fleet outputs
@pytest.mark.timeout(180)
def test_fleet_outputs_of_logs_with_one_name_in_nested_folders_do_not_collide(tmp_path, capsys, monkeypatch):
    """``x/f.mcap`` and ``y/x/f.mcap`` (before: both ``out/x_f.mcap``, one overwritten, the
    summary saying 2 logs) keep their relative paths under the output folder."""
    monkeypatch.chdir(tmp_path)
    first = write_flight(tmp_path / "x" / "f.mcap", n=N)
    second = write_flight(tmp_path / "y" / "x" / "f.mcap", n=N + 10)
    rc, out, err = _run(capsys, ["replay", "x/f.mcap", "y/x/f.mcap", "--out", "out", "--workers", "1"])
    assert rc == 0, err
    with (tmp_path / "out" / "fleet.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    outputs = [Path(r["output"]) for r in rows]
    assert outputs == [Path("out/x/f.mcap"), Path("out/y/x/f.mcap")]
    assert [len(read_log(p)) for p in outputs] == [N, N + 10]  # each its own log's samples
    assert fleet.output_paths([first, second], "o") == [Path("o/x/f.mcap"), Path("o/y/x/f.mcap")]
    assert fleet.output_paths([first, tmp_path / "x" / "g.mcap"], "o") == [Path("o/f.mcap"), Path("o/g.mcap")]
