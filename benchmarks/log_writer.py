"""Log-writer benchmark: what one 1 kHz sample costs the flight-log writer, per stage.

    python benchmarks/log_writer.py [--samples 20000] [--markdown]

One sample is what the service logs at its rate: /imu/raw, /attitude and /attitude/truth
(the simulator's truth), built from random float64 values (full 17-digit floats, like real
data). Each stage is timed beside the slower way it replaced, alternately, best of
``--repeats``, so the VM's drift cancels in the ratio:

* encode: ``schemas.encode`` (orjson) against ``json.dumps`` of the same three messages;
* MCAP: ``McapLogFile.write_encoded`` (the file layer, ``logs/mcap_file.py``, on the ``mcap``
  library's public API) against the library's ``Writer.add_message`` called directly (same
  bytes, zstd chunks of 128 KiB): what the file layer adds (channel lookup, sequence numbers);
* caller: ``FlightLogWriter.write_sample`` (one queue entry) against ``write_raw`` +
  ``write_attitude`` + ``write_truth`` — the service loop's own cost, writer thread stopped;
* writer thread at 8 kHz: ``write_block`` of 8-sample bursts written as one message per burst
  and channel (``block_messages_above_hz``, /imu/raw_block …) against one message per sample —
  the writer thread's wall time from a full queue to the file closed (no fsync).
"""

from __future__ import annotations

import argparse
import collections
import io
import json
import shutil
import sys
import tempfile
import time
from typing import Callable

import numpy as np
from mcap.writer import CompressionType, Writer

from ahrs_service.logs.schemas import attitude_message, encode, raw_message, truth_message
from ahrs_service.logs.mcap_file import McapLogFile
from ahrs_service.logs.writer import FlightLogWriter


def _timed(fn: Callable[[], None]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _paired(new: Callable[[], None], old: Callable[[], None], n: int, repeats: int) -> tuple[float, float]:
    a: list[float] = []
    b: list[float] = []
    for _ in range(repeats):
        a.append(_timed(new) * 1e6 / n)
        b.append(_timed(old) * 1e6 / n)
    return min(a), min(b)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    n = args.samples
    rng = np.random.default_rng(1)
    rows = rng.normal(size=(n, 10))
    rows[::10, 6:9] = np.nan  # the magnetometer slower than the gyro
    qs = rng.normal(size=(n, 4))
    qs /= np.linalg.norm(qs, axis=1)[:, None]
    state = rng.normal(size=60)
    row_l, q_l = rows.tolist(), qs.tolist()
    messages = [
        (
            raw_message(i * 1_000_000, row_l[i], 7, None, None, i),
            attitude_message(i * 1_000_000, q_l[i], "robust", row_l[i][:3], None),
            truth_message(i * 1_000_000, q_l[i]),
        )
        for i in range(n)
    ]

    def encode_orjson() -> None:
        for m in messages:
            encode(m[0]), encode(m[1]), encode(m[2])

    def encode_json() -> None:
        dumps = json.JSONEncoder(separators=(",", ":")).encode
        for m in messages:
            dumps(m[0]).encode(), dumps(m[1]).encode(), dumps(m[2]).encode()

    data = [tuple(encode(x) for x in m) for m in messages]

    def mcap_file() -> None:
        with McapLogFile(f"{tmp}/bench.mcap", chunk_size=128 * 1024) as f:
            write = f.write_encoded
            for i, (a, b, c) in enumerate(data):
                t = i * 1_000_000
                write("/imu/raw", t, a, t)
                write("/attitude", t, b, t)
                write("/attitude/truth", t, c, t)

    def mcap_with(cls: type) -> Callable[[], None]:
        def run() -> None:
            w = cls(io.BytesIO(), chunk_size=128 * 1024, compression=CompressionType.ZSTD)
            w.start(profile="", library="bench")
            sid = w.register_schema("s", "jsonschema", b"{}")
            ch = [w.register_channel(t, "json", sid) for t in ("/imu/raw", "/attitude", "/attitude/truth")]
            add = w.add_message
            for i, (a, b, c) in enumerate(data):
                t = i * 1_000_000
                add(ch[0], t, a, t, i)
                add(ch[1], t, b, t, i)
                add(ch[2], t, c, t, i)
            w.finish()

        return run

    def caller(one_call: bool) -> Callable[[], None]:
        def run() -> None:
            w = FlightLogWriter(tmp, queue_size=4 * n)
            # the writer thread holds its own reference to the queue: swapping it keeps the
            # thread idle, so only the caller's side is timed
            thread_queue, w._q = w._q, collections.deque()
            for i in range(n):
                t = i * 1_000_000
                if one_call:
                    w.write_sample(t, rows[i], 7, q=qs[i], estimator="robust", bias=rows[i, :3], state=state, truth_q=qs[i])
                else:
                    w.write_raw(t, rows[i], 7)
                    w.write_attitude(t, qs[i], "robust", rows[i, :3], None, state=state)
                    w.write_truth(t, qs[i])
            w._q = thread_queue
            w.close()

        return run

    def writer_thread(one_message: bool, burst: int = 8) -> Callable[[], None]:
        t_all = np.arange(n, dtype=np.int64) * 125_000  # 8 kHz
        burst_rows = rows.copy()
        burst_rows[:, 9] = 1 / 8000

        def run() -> None:
            w = FlightLogWriter(tmp, queue_size=4 * n, fsync=False,
                                block_messages_above_hz=1500.0 if one_message else None)
            thread_queue, w._q = w._q, collections.deque()  # filled first: only the thread is timed
            for i in range(0, n, burst):
                s = slice(i, i + burst)
                w.write_block(t_all[s], burst_rows[s], np.full(len(t_all[s]), 7), q=qs[s], estimator="robust",
                              bias=rows[i, :3], truth_q=qs[s])
            queued, w._q = w._q, thread_queue
            t0 = time.perf_counter()
            w._q.extend(queued)
            w.close()
            timings.append(time.perf_counter() - t0)

        return run

    timings: list[float] = []
    tmp = tempfile.mkdtemp(prefix="log-writer-bench-")
    results = [
        ("encode 3 messages", "orjson", "json.dumps", *_paired(encode_orjson, encode_json, n, args.repeats)),
        ("MCAP add 3 messages", "McapLogFile", "mcap Writer", *_paired(mcap_file, mcap_with(Writer), n, args.repeats)),
        ("caller (service loop)", "write_sample", "3 write_* calls", *_paired(caller(True), caller(False), n, args.repeats)),
    ]
    # the writer thread at 8 kHz, bursts of 8: one message per burst and channel against per sample
    burst_new: list[float] = []
    burst_old: list[float] = []
    for _ in range(args.repeats):
        for one_message, out in ((True, burst_new), (False, burst_old)):
            timings.clear()
            writer_thread(one_message)()
            out.append(timings[0] * 1e6 / n)
    burst_line = ("writer thread, 8 kHz bursts of 8", "per burst", "per sample", min(burst_new), min(burst_old))
    shutil.rmtree(tmp, ignore_errors=True)
    header = ("stage", "now", "µs/sample", "before", "µs/sample", "speed-up")
    lines = [(s, a, f"{x:.2f}", b, f"{y:.2f}", f"{y / x:.1f}×") for s, a, b, x, y in results]
    total_new = sum(r[3] for r in results)
    total_old = sum(r[4] for r in results)
    lines.append(("total", "", f"{total_new:.2f}", "", f"{total_old:.2f}", f"{total_old / total_new:.1f}×"))
    s, a, b, x, y = burst_line
    lines.append((s, a, f"{x:.2f}", b, f"{y:.2f}", f"{y / x:.1f}×"))
    print(f"{n} samples (3 messages each), best of {args.repeats}, timed alternately; Python {sys.version.split()[0]}")
    if args.markdown:
        print("| " + " | ".join(header) + " |\n|---|---|---:|---|---:|---:|")
        for line in lines:
            print("| " + " | ".join(line) + " |")
    else:
        widths = [max(len(h), *(len(line[i]) for line in lines)) for i, h in enumerate(header)]
        for line in (header, *lines):
            print("  ".join(v.ljust(w) for v, w in zip(line, widths)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
