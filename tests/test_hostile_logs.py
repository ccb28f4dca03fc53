"""Hostile and foreign MCAP files given to ``log info``, ``log recover``, ``log plot`` and
``replay`` (single and fleet): structurally valid files whose JSON messages have wrong types,
missing keys, NaN, deep nesting or are no JSON at all, and chunks that lie about their size
or contents (a zstd bomb, a record longer than its chunk, an unknown compression).

Issue 14 probe (14d): before, 246 of 1 044 such runs ended in a traceback (KeyError,
TypeError, OverflowError, RecursionError …), a chunk of zeros 64 MiB long took 24 s to read
(1 GiB: minutes and a GiB of memory), a record longer than its chunk was dropped without a
word (``log info`` exit 0), and ``replay --out`` copied what followed the damage into the new
log. Now every one is damage at the message (or chunk) that is wrong, named with its field,
the file read up to it, and no traceback.
"""

from __future__ import annotations

import json
import math
import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.writer import CompressionType, Writer

from ahrs_service import fleet
from ahrs_service.cli import main
from ahrs_service.logs.reader import read_log
from ahrs_service.logs.schemas import CHANNELS, schema_bytes

N = 40
RAW = {"t_ns": 0, "index": 0, "dt": 0.005, "gyr": [0.0, 0.0, 0.0], "acc": [0.0, 0.0, -9.81],
       "mag": [20.0, 0.0, 40.0], "flags": 7}
ATT = {"t_ns": 0, "q": [1.0, 0.0, 0.0, 0.0], "roll": 0.0, "pitch": 0.0, "yaw": 0.0, "estimator": "madgwick"}
CONFIG = {"t_ns": 0, "config": {"estimator": {"name": "madgwick", "params": {"beta": 0.1}}}, "reason": "start"}


def _t(i: int) -> int:
    return (i + 1) * 5_000_000


def write_mcap(path: Path, messages: list[tuple[str, object, int]]) -> Path:
    """A valid MCAP file (the mcap library's writer, this project's channels and schemas)
    holding ``messages``: (topic, JSON value or raw bytes, log time)."""
    with open(path, "wb") as f:
        w = Writer(f, compression=CompressionType.ZSTD)
        w.start()
        channels = {}
        for topic in ("/config", "/imu/raw", "/attitude", "/params", "/loop", "/log", "/estimator/state",
                      "/imu/raw_block", "/attitude_block"):
            sid = w.register_schema(CHANNELS[topic][0], "jsonschema", schema_bytes(topic))
            channels[topic] = w.register_channel(topic, "json", sid)
        for topic, value, t in messages:
            data = value if isinstance(value, bytes) else json.dumps(value, allow_nan=True).encode()
            w.add_message(channels[topic], t, data, t)
        w.finish()
    return path


def flight(raw=lambda i: {**RAW, "t_ns": _t(i), "index": i}, extra=(), config=CONFIG, n=N):
    msgs = [("/config", config, 0)]
    for i in range(n):
        msgs += [("/imu/raw", raw(i), _t(i)), ("/attitude", {**ATT, "t_ns": _t(i)}, _t(i))]
    return msgs + list(extra)


def block_flight(bad: dict | None = None, bad_attitude: dict | None = None, blocks: int = 4, rows: int = 10):
    """A block log (one /imu/raw_block and /attitude_block per burst of ``rows`` samples); the
    third burst's messages get ``bad`` / ``bad_attitude`` merged in."""
    msgs = [("/config", CONFIG, 0)]
    for b in range(blocks):
        t = [_t(b * rows + i) for i in range(rows)]
        raw = {"t_ns": t, "first_index": b * rows, "dt": [0.005] * rows, "gyr": [[0.0, 0.0, 0.0]] * rows,
               "acc": [[0.0, 0.0, -9.81]] * rows, "mag": [[20.0, 0.0, 40.0]] * rows, "flags": [7] * rows}
        att = {"t_ns": t, "q": [[1.0, 0.0, 0.0, 0.0]] * rows, "estimator": "madgwick"}
        if b == 2:
            raw.update(bad or {})
            att.update(bad_attitude or {})
        msgs += [("/imu/raw_block", raw, t[-1]), ("/attitude_block", att, t[-1])]
    return msgs


def _bad_raw_at(k: int, **fields):
    return lambda i: {**RAW, "t_ns": _t(i), "index": i, **(fields if i == k else {})}


def _drop(key: str, k: int):
    return lambda i: {name: v for name, v in {**RAW, "t_ns": _t(i), "index": i}.items() if not (i == k and name == key)}


# (case, messages, the damage text: topic, message number, field)
HOSTILE = [
    ("t_ns a string", flight(_bad_raw_at(7, t_ns="1.5")), "/imu/raw message 8", "$.t_ns: expected a 64-bit integer, got the string '1.5'"),
    ("t_ns beyond int64", flight(_bad_raw_at(7, t_ns=10**30)), "/imu/raw message 8", "$.t_ns: expected a 64-bit integer"),
    ("t_ns a float", flight(_bad_raw_at(7, t_ns=1.5)), "/imu/raw message 8", "$.t_ns: expected a 64-bit integer, got the number 1.5"),
    ("t_ns missing", flight(_drop("t_ns", 7)), "/imu/raw message 8", "$.t_ns: missing"),
    ("dt an array", flight(_bad_raw_at(7, dt=[1, 2])), "/imu/raw message 8", "$.dt: expected a number or null, got an array of 2"),
    ("gyr a number", flight(_bad_raw_at(7, gyr=float("nan"))), "/imu/raw message 8", "$.gyr: expected an array of 3 numbers"),
    ("gyr of strings", flight(_bad_raw_at(7, gyr=["a", "b", "c"])), "/imu/raw message 8", "$.gyr[0]: expected a number or null, got the string 'a'"),
    ("acc too long", flight(_bad_raw_at(7, acc=[0.0] * 100_000)), "/imu/raw message 8", "$.acc: expected an array of 3 numbers, got an array of 100000"),
    ("flags a boolean", flight(_bad_raw_at(7, flags=True)), "/imu/raw message 8", "$.flags: expected a 64-bit integer, got a boolean"),
    ("sample an array", flight(lambda i: [1, 2, 3] if i == 7 else {**RAW, "t_ns": _t(i), "index": i}),
     "/imu/raw message 8", "$: expected an object, got an array of 3"),
    ("sample no JSON", flight(lambda i: b"\x00\xffgarbage" if i == 7 else {**RAW, "t_ns": _t(i), "index": i}),
     "/imu/raw message 8", "$: not JSON"),
    ("nested 100 000 deep", flight(lambda i: b'{"t_ns":' + b"[" * 100_000 + b"]" * 100_000 + b"}" if i == 7
                                   else {**RAW, "t_ns": _t(i), "index": i}), "/imu/raw message 8", "$: JSON nested too deep"),
    ("config an array", flight(config={"t_ns": 0, "config": [1, 2]}), "/config message 1", "$.config: expected an object, got an array of 2"),
    ("estimator name an object", flight(config={"t_ns": 0, "config": {"estimator": {"name": {"a": 1}}}}),
     "/config message 1", "$.name: expected a string, got an object"),
    ("params a list", flight(config={"t_ns": 0, "config": {"estimator": {"name": "madgwick", "params": [1]}}}),
     "/config message 1", "$.params: expected an object"),
    ("param change index a string", flight(extra=[("/params", {"t_ns": 1, "sample_index": "10", "name": "beta", "old": 0.1, "new": 0.2}, _t(N))]),
     "/params message 1", "$.sample_index: expected a 64-bit integer, got the string '10'"),
    ("state not an array", flight(extra=[("/estimator/state", {"t_ns": 0, "sample_index": 0, "estimator": "madgwick", "state": None}, _t(N))]),
     "/estimator/state message 1", "$.state: expected an array of numbers, got null"),
    ("block time a string", block_flight({"t_ns": [_t(20)] * 9 + ["x"]}), "/imu/raw_block message 3", "$.t_ns[9]: expected a 64-bit integer, got the string 'x'"),
    ("block rows short", block_flight({"gyr": [[0.0, 0.0, 0.0]] * 9}), "/imu/raw_block message 3", "$.gyr: expected an array of 10 rows, got an array of 9"),
    ("block row of strings", block_flight({"acc": [[0.0, 0.0, -9.81]] * 9 + [["a", 0, 0]]}), "/imu/raw_block message 3", "$.acc[9][0]: expected a number or null"),
    ("block first index missing", block_flight({"first_index": None}), "/imu/raw_block message 3", "$.first_index: expected a 64-bit integer, got null"),
    ("block attitude q short", block_flight(bad_attitude={"q": [[1.0, 0.0]] * 10}), "/attitude_block message 3", "$.q[0]: expected an array of 4 numbers, got an array of 2"),
]


def _run(capsys, argv):
    rc = main([str(a) for a in argv])
    out = capsys.readouterr()
    return rc, out.out, out.err.strip()


@pytest.mark.parametrize("case, messages, where, what", HOSTILE, ids=[c[0] for c in HOSTILE])
def test_a_message_that_is_not_what_its_schema_says_is_damage_named_by_field(tmp_path, capsys, case, messages, where, what):
    path = write_mcap(tmp_path / "hostile.mcap", messages)
    rc, out, err = _run(capsys, ["log", "info", path])
    assert rc == 1 and "Traceback" not in err and err == "", (out, err)
    (damage,) = [line for line in out.splitlines() if line.strip().startswith("damage:")]
    assert where in damage and what in damage and str(path) in out, damage
    rc, out, _ = _run(capsys, ["log", "info", "--json", path])  # the same exit status as without --json
    assert rc == 1 and where in json.loads(out)["damage"]["reason"]
    log = read_log(path)
    kept = {"/imu/raw ": 7, "/config ": 0, "/imu/raw_block ": 20, "/attitude_block ": 30}.get(where.split("message")[0], N)
    assert len(log) == kept and np.all(np.isfinite(log.rows[:, :6])) and log.damage is not None
    rc, out, err = _run(capsys, ["replay", path, "--estimator", "madgwick"])
    assert "Traceback" not in err and "\n" not in err
    if kept:
        assert rc == 0 and f"replayed {kept} samples" in out and where in out
    else:  # nothing before the damage: one line naming the file and the damage
        assert rc == 2 and err.startswith(f"ahrs-service replay: error: {path}: no sample to replay") and where in err


def test_loop_counters_of_the_wrong_kind_are_damage_in_log_info(tmp_path, capsys):
    loop = {"t_ns": _t(N), "source": {"lost": {"gap": -3, "fifo_overflow": 0}}}
    path = write_mcap(tmp_path / "loop.mcap", flight(extra=[("/loop", {"t_ns": 1, "source": {"lost": {"gap": 2}}}, _t(1)),
                                                            ("/loop", loop, _t(N))]))
    rc, out, err = _run(capsys, ["log", "info", path])
    assert rc == 1 and err == ""
    assert "lost samples (source, since the service started): 2" in out  # the totals before it
    assert "damage: /loop message 2 (log time" in out and "negative count" in out
    path = write_mcap(tmp_path / "loop2.mcap", flight(extra=[("/loop", {"t_ns": 1, "log": {"samples_not_logged": "5"}}, _t(1))]))
    rc, out, _ = _run(capsys, ["log", "info", path])
    assert rc == 1 and "$.samples_not_logged: expected a 64-bit integer, got the string '5'" in out


def test_log_plot_of_hostile_messages_plots_up_to_them(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    path = write_mcap(tmp_path / "p.mcap", flight(_bad_raw_at(20, acc=["x", 0, 0])))
    rc, out, err = _run(capsys, ["log", "plot", path, "--out", tmp_path / "p.png"])
    assert rc == 0 and "Traceback" not in err
    assert "/imu/raw message at log time 105000000 ns is not a valid ahrs.ImuRaw: $.acc[0]" in err
    assert out.startswith(f"wrote {tmp_path / 'p.png'}: 20 samples")
    path = write_mcap(tmp_path / "q.mcap", [("/imu/raw", [1], 5)])
    rc, _, err = _run(capsys, ["log", "plot", path, "--out", tmp_path / "q.png"])
    assert rc == 2 and err == (f"ahrs-service: log plot: {path}: no readable messages (/imu/raw message at log time 5 ns "
                               f"is not a valid ahrs.ImuRaw: $: expected an object, got an array of 1)")


def test_replay_out_of_a_log_damaged_in_the_middle_stops_the_new_log_there(tmp_path, capsys):
    path = write_mcap(tmp_path / "mid.mcap", flight(_bad_raw_at(25, t_ns="x")))
    rc, out, err = _run(capsys, ["replay", path, "--out", tmp_path / "new.mcap"])
    assert rc == 0 and err == "" and "replayed 25 samples" in out
    new = read_log(tmp_path / "new.mcap")
    assert new.damage is None and new.counts["/imu/raw"] == 25 and new.counts["/attitude/original"] == 25


def test_recorded_values_the_estimator_refuses_are_named_as_the_logs(tmp_path, capsys):
    cases = [
        (flight(extra=[("/params", {"t_ns": 1, "sample_index": 10, "name": "beta", "old": 0.1, "new": [1, 2], "source": "x"}, _t(N))]),
         "its /params change of beta to [1, 2] (before row 10) is refused: parameter 'beta' of estimator 'madgwick' must be a number"),
        (flight(config={"t_ns": 0, "config": {"estimator": {"name": "nope", "params": {}}}}),
         "the log's estimator 'nope' is not one of this version's; give --estimator NAME"),
        (flight(config={"t_ns": 0, "config": {"estimator": {"name": "madgwick", "params": {"preset": "/etc/passwd"}}}}),
         "the parameters recorded in its /config are refused: unknown parameter(s) preset"),
        (flight(extra=[("/estimator/state", {"t_ns": 0, "sample_index": 0, "estimator": "madgwick", "state": [1.0, 2.0]}, _t(N))]),
         "its /estimator/state has 2 values, madgwick needs"),
    ]
    for i, (messages, expected) in enumerate(cases):
        path = write_mcap(tmp_path / f"r{i}.mcap", messages)
        rc, _, err = _run(capsys, ["replay", path])
        assert rc == 2 and err.startswith(f"ahrs-service replay: error: {path}: ") and expected in err, err
    # the caller's own bad value is still the caller's
    rc, _, err = _run(capsys, ["replay", tmp_path / "r1.mcap", "--estimator", "madgwick", "--param", "beta=nan"])
    assert rc == 2 and err == "ahrs-service replay: error: parameter 'beta' of estimator 'madgwick' must be finite, got nan"


def test_replay_without_a_finite_recorded_estimate_at_any_sample_says_so(tmp_path, capsys):
    # the recorded /attitude messages at other times than the samples: nothing to compare
    msgs = [("/config", CONFIG, 0)] + [m for i in range(N) for m in (
        ("/imu/raw", {**RAW, "t_ns": _t(i), "index": i}, _t(i)), ("/attitude", {**ATT, "t_ns": _t(i) + 1}, _t(i) + 1))]
    rc, out, err = _run(capsys, ["replay", write_mcap(tmp_path / "a.mcap", msgs)])
    assert rc == 0 and err == ""
    assert "vs recorded estimate: no sample has both a finite recorded and a finite new estimate" in out


# --------------------------------------------------------------------------- lying chunks

MAGIC = b"\x89MCAP0\r\n"


def _rec(op: int, body: bytes) -> bytes:
    return struct.pack("<BQ", op, len(body)) + body


def _str(text: str) -> bytes:
    return struct.pack("<I", len(text)) + text.encode()


def _chunk(compressed: bytes, size: int, crc: int, compression: str = "zstd") -> bytes:
    return _rec(0x06, struct.pack("<QQQI", 0, 0, size, crc) + _str(compression) + struct.pack("<Q", len(compressed)) + compressed)


def _chunk_file(path: Path, chunk: bytes) -> Path:
    schema = _rec(0x03, struct.pack("<H", 1) + _str("ahrs.ImuRaw") + _str("jsonschema") + struct.pack("<I", 2) + b"{}")
    channel = _rec(0x04, struct.pack("<HH", 1, 1) + _str("/imu/raw") + _str("json") + struct.pack("<I", 0))
    good = _rec(0x05, struct.pack("<HIQQ", 1, 0, 5, 5) + json.dumps({**RAW, "t_ns": 5}).encode())
    first = zstandard.ZstdCompressor().compress(good)
    body = _rec(0x01, _str("") + _str("test")) + schema + channel + _chunk(first, len(good), zlib.crc32(good)) + chunk
    path.write_bytes(MAGIC + body + _rec(0x02, struct.pack("<QQI", 0, 0, 0)) + MAGIC)
    return path


def _zero_bomb(mib: int) -> tuple[bytes, int]:
    c = zstandard.ZstdCompressor(level=1).compressobj()
    block, crc = bytes(1 << 20), 0
    out = b""
    for _ in range(mib):
        out += c.compress(block)
        crc = zlib.crc32(block, crc)
    return out + c.flush(), crc


def _lying_record() -> bytes:
    inner = struct.pack("<BQ", 0x05, 1 << 40) + b"x" * 30  # a Message "1 TiB long" in 39 bytes
    return _chunk(zstandard.ZstdCompressor().compress(inner), len(inner), zlib.crc32(inner))


@pytest.mark.parametrize(
    "name, make, reason",
    [
        ("zstd bomb over the limit", lambda: _chunk(*(lambda d, c: (d, 300 << 20, c))(*_zero_bomb(300))),
         "chunk says it holds 314572800 bytes uncompressed, over the reader's limit of 256 MiB"),
        ("zstd bomb of zeros", lambda: _chunk(*(lambda d, c: (d, 12 << 20, c))(*_zero_bomb(12))),
         "invalid opcode 0x00 at byte 0 of the chunk"),
        ("record longer than its chunk", _lying_record,
         "record (opcode 0x05) at byte 0 of the chunk needs 1099511627776 bytes, 30 left"),
        ("stream longer than stated", lambda: _chunk(_zero_bomb(2)[0], 1000, 0), "chunk decompresses to more than the 1000 bytes it states"),
        ("unknown compression", lambda: _chunk(b"abc", 3, 0, "brotli"), "unknown chunk compression 'brotli'"),
    ],
)
@pytest.mark.timeout(60)
def test_a_chunk_that_lies_is_damage_bounded_in_time_and_memory(tmp_path, capsys, name, make, reason):
    path = _chunk_file(tmp_path / "chunk.mcap", make())
    rc, out, err = _run(capsys, ["log", "info", path])
    assert rc == 1 and err == "" and "samples 1," in out and reason in out, out
    rc, out, err = _run(capsys, ["log", "recover", path, tmp_path / "rec.mcap"])
    assert rc == 0 and "recovered 1 messages" in out and reason in out
    assert read_log(tmp_path / "rec.mcap").damage is None and len(read_log(tmp_path / "rec.mcap")) == 1
    rc, out, err = _run(capsys, ["replay", path, "--estimator", "madgwick"])
    assert rc == 0 and "replayed 1 samples" in out and reason in out


def test_the_fast_scan_stops_at_a_lying_chunk_too(tmp_path):
    from ahrs_service.logs.fast_scan import scan_messages

    path = _chunk_file(tmp_path / "chunk.mcap", _lying_record())
    seen: list[int] = []
    scan = scan_messages(path, {"/imu/raw": lambda t, data: seen.append(t)})
    assert seen == [5] and "needs 1099511627776 bytes, 30 left" in scan.damage


def test_fleet_replay_of_hostile_logs_gives_each_a_row(tmp_path):
    good = write_mcap(tmp_path / "good.mcap", flight())
    bad = write_mcap(tmp_path / "bad.mcap", flight(_bad_raw_at(0, gyr="x")))
    bomb = _chunk_file(tmp_path / "bomb.mcap", _lying_record())
    jobs = [fleet.ReplayJob(path=str(p), estimator="madgwick", params={}, follow_param_changes=True,
                            blend_time_s=None, out_path=None) for p in (good, bad, bomb)]
    rows = [fleet.replay_one(j) for j in jobs]
    assert [r.samples for r in rows] == [N, 0, 1]
    assert rows[0].error is None and rows[0].damage is None and rows[0].rms_diff_vs_recorded_deg == 0.0
    assert rows[1].error == "no sample to replay" and "$.gyr: expected an array of 3 numbers" in rows[1].damage
    assert rows[2].error is None and "needs 1099511627776 bytes" in rows[2].damage
    assert not math.isnan(rows[2].rms_diff_vs_recorded_deg or 0.0)


def _indexed_file(path: Path, bad_chunk: bytes, claimed_size: int) -> Path:
    """A complete file (summary, chunk indexes, footer) whose second chunk's index claims
    ``claimed_size`` bytes uncompressed, whatever its Chunk record says."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import ChunkIndex

    schema = _rec(0x03, struct.pack("<H", 1) + _str("ahrs.ImuRaw") + _str("jsonschema") + struct.pack("<I", 2) + b"{}")
    channel = _rec(0x04, struct.pack("<HH", 1, 1) + _str("/imu/raw") + _str("json") + struct.pack("<I", 0))
    good = _rec(0x05, struct.pack("<HIQQ", 1, 0, 5, 5) + json.dumps({**RAW, "t_ns": 5}).encode())
    first = _chunk(zstandard.ZstdCompressor().compress(good), len(good), zlib.crc32(good))
    head = MAGIC + _rec(0x01, _str("") + _str("test")) + schema + channel
    body = head + first + bad_chunk + _rec(0x0F, struct.pack("<I", 0))
    index = RecordBuilder()
    for offset, chunk, size in ((len(head), first, len(good)), (len(head) + len(first), bad_chunk, claimed_size)):
        ChunkIndex(chunk_length=len(chunk), chunk_start_offset=offset, compression="zstd",
                   compressed_size=len(chunk) - 60, message_end_time=5, message_index_length=0,
                   message_index_offsets={}, message_start_time=5, uncompressed_size=size).write(index)
    footer = _rec(0x02, struct.pack("<QQI", len(body), 0, 0))
    path.write_bytes(body + schema + channel + index.end() + footer + MAGIC)
    return path


@pytest.mark.timeout(120)
def test_a_chunk_index_that_lies_about_a_bomb_is_not_followed(tmp_path, capsys):
    """The summary's chunk index says 1 000 bytes; the Chunk record says (and holds) 1.2 GiB of
    zeros in 37 kB. The mcap library decompresses a chunk to its record's size (and then walks
    the zeros for minutes): the indexed read is not taken, the bounded stream read reports the
    chunk. Memory is what is asserted, in a fresh interpreter: its peak stays far below the
    bomb's size (before: over 1.2 GiB)."""
    import subprocess

    data, crc = _zero_bomb(1200)
    path = _indexed_file(tmp_path / "idx.mcap", _chunk(data, 1200 << 20, crc), 1000)
    # the peak of what read_log allocates, traced: a child's ru_maxrss starts from its parent's
    # RSS at fork (Linux keeps it across exec), which in the whole suite was 850 MB of pytest
    code = ("import sys, tracemalloc\nfrom ahrs_service.logs.reader import read_log\ntracemalloc.start()\n"
            "log = read_log(sys.argv[1])\nprint(len(log), log.indexed, log.damage)\n"
            "print(tracemalloc.get_traced_memory()[1] // 1024)\n")
    proc = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, timeout=100)
    assert proc.returncode == 0, proc.stderr
    result, peak_kib = proc.stdout.strip().splitlines()
    assert result.startswith("1 False damaged at byte") and "over the reader's limit of 256 MiB" in result
    assert int(peak_kib) < 300 * 1024  # far below the bomb's 1.2 GiB (and the 256 MiB chunk limit)
    rc, out, err = _run(capsys, ["log", "info", path])
    assert rc == 1 and err == "" and "over the reader's limit" in out
    # a sound complete file is still read through its index
    sound = read_log(write_mcap(tmp_path / "sound.mcap", flight()))
    assert sound.indexed and sound.damage is None and len(sound) == N
