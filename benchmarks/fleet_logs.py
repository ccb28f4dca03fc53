"""Writes a simulated fleet of flight logs, deterministic by seed: the input of a fleet replay.

    python benchmarks/fleet_logs.py OUT --count 1000 [--seed 0] [--min-s 10] [--max-s 600] [--long-fraction 1]
                                    [--truncated 0.03] [--corrupt 0.03] [--processes 2]

Each log is a flight of the simulator (``drivers/sim``: the figure-eight profile, a board's
sensor error models, seeded noise) recorded by the service's own ``FlightLogWriter`` as the
service records one: its /config naming the estimator, every sample's /imu/raw, the estimate
on /attitude (Madgwick, direct Mahony or the full complementary filter, run over the samples as they come), the exact truth on
/attitude/truth. What varies, drawn from the seed: the length (log-uniform between ``--min-s``
and ``--max-s`` seconds; with ``--long-fraction P`` only a fraction P of the logs, the others
up to twice ``--min-s``), the board (GY-80, MinIMU-9v2, MPU9250), the rate (100, 200 or
400 Hz), the estimator. A fraction of the logs is then damaged as a crash or a bad card
leaves one: **truncated** (cut at 30–90 % of the file, no footer: the writer did not finish)
or **corrupt** (64 bytes overwritten inside the data). Log ``i`` depends only on
``(seed, i)``: the same command writes the same logs, and ``--count 40`` writes the first 40
of ``--count 1000``.

``generate`` is what the tests and ``benchmarks/fleet_replay.py`` call.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BOARDS = ("GY-80", "MinIMU-9v2", "MPU9250")
RATES_HZ = (100.0, 200.0, 400.0)
ESTIMATORS = ("madgwick", "mahony_direct", "complementary_full")
#: samples simulated and written per block (bounds the generator's memory whatever the length)
BLOCK = 2000


@dataclass(frozen=True)
class FleetLog:
    """One simulated log: its file name, flight length (s), board, rate (Hz), estimator, and the
    damage done to it afterwards ("truncated", "corrupt" or None)."""

    name: str
    seconds: float
    board: str
    rate_hz: float
    estimator: str
    fault: str | None

    @property
    def samples(self) -> int:
        return int(round(self.seconds * self.rate_hz))


def plan(count: int, seed: int = 0, min_s: float = 10.0, max_s: float = 600.0,
         truncated: float = 0.03, corrupt: float = 0.03, long_fraction: float = 1.0) -> list[FleetLog]:
    """The fleet's logs, each drawn from ``(seed, i)`` alone. ``long_fraction`` < 1: only that
    fraction of the logs is drawn from the whole range, the others are short (log-uniform up
    to twice ``min_s``: a ground test, a hop), as in a real fleet's folder."""
    if not 0 < min_s <= max_s:
        raise ValueError(f"need 0 < min_s <= max_s, got {min_s} and {max_s}")
    if not 0.0 <= long_fraction <= 1.0:
        raise ValueError(f"need 0 <= long_fraction <= 1, got {long_fraction}")
    logs = []
    for i in range(count):
        rng = np.random.default_rng([seed, i])
        longest = max_s
        if long_fraction < 1.0 and rng.uniform() >= long_fraction:  # no extra draw by default
            longest = min(max_s, 2.0 * min_s)
        seconds = float(round(math.exp(rng.uniform(math.log(min_s), math.log(longest))), 2))
        u = rng.uniform()
        fault = "truncated" if u < truncated else "corrupt" if u < truncated + corrupt else None
        logs.append(FleetLog(
            name=f"flight_{i:05d}.mcap", seconds=seconds, board=str(rng.choice(BOARDS)),
            rate_hz=float(rng.choice(RATES_HZ)), estimator=str(rng.choice(ESTIMATORS)), fault=fault,
        ))
    return logs


def write_log(log: FleetLog, out_dir: Path, seed: int, index: int) -> Path:
    """Simulates and records ``log`` into ``out_dir / log.name``, then damages it if asked."""
    from ahrs_service import estimators
    from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID
    from ahrs_service.drivers.sim.imu import ManualClock, SimulatedImu
    from ahrs_service.drivers.sim.motion import profile
    from ahrs_service.drivers.sim.sensor_model import board_models
    from ahrs_service.logs.writer import FlightLogWriter

    run_seed = seed * 1_000_003 + index
    imu = SimulatedImu(profile("figure8"), board_models(log.board, seed=run_seed), clock=ManualClock(), seed=run_seed)
    est = estimators.create(log.estimator)
    n = log.samples
    t0_ns = 1_000_000_000
    flags = np.full(BLOCK, GYR_VALID | ACC_VALID | MAG_VALID | MAG_NEW, dtype=np.int64)
    with tempfile.TemporaryDirectory(dir=out_dir) as tmp:
        writer = FlightLogWriter(tmp, fsync=False, metadata={"fleet_seed": str(seed), "board": log.board})
        writer.write_config(t0_ns, {"estimator": {"name": log.estimator, "params": est.get_params()},
                                    "rate_hz": log.rate_hz, "board": log.board})
        for start in range(0, n, BLOCK):
            t = np.arange(start, min(n, start + BLOCK)) / log.rate_hz
            block = imu.physics_block(t, period=1.0 / log.rate_hz)
            dt = np.full(len(t), 1.0 / log.rate_hz)
            rows = np.column_stack([block.gyr, block.acc, block.mag, dt])
            q = est.run_rows(rows)
            t_ns = t0_ns + np.round(t * 1e9).astype(np.int64)
            truth = np.array([state.q for state in block.truth])
            writer.write_block(t_ns, rows, flags[: len(t)], q=q, estimator=est.name, truth_q=truth,
                               bias=est.gyro_bias, state=est.state)
            while writer.stats()["queued"] > 4:  # the writer thread keeps up: memory stays a few blocks
                time.sleep(0.005)
        writer.close()
        if writer.status != "closed" or writer.dropped or len(writer.files) != 1:
            raise RuntimeError(f"writing {log.name} failed: {writer.stats()}")
        path = out_dir / log.name
        shutil.move(str(writer.files[0]), path)
    if log.fault:
        data = bytearray(path.read_bytes())
        rng = np.random.default_rng([seed, index, 1])
        at = int(len(data) * rng.uniform(0.3, 0.9))
        if log.fault == "truncated":
            del data[at:]
        else:
            data[at:at + 64] = rng.integers(0, 256, 64, dtype=np.uint8).tobytes()
        path.write_bytes(bytes(data))
    return path


def _write_one(args: tuple[FleetLog, Path, int, int]) -> Path:
    return write_log(*args)


def generate(out_dir: str | Path, count: int, seed: int = 0, *, min_s: float = 10.0, max_s: float = 600.0,
             long_fraction: float = 1.0,
             truncated: float = 0.03, corrupt: float = 0.03, processes: int = 1) -> list[FleetLog]:
    """Writes the fleet's ``count`` logs into ``out_dir`` (a log already there is kept: the
    logs are deterministic) and returns their plan."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    logs = plan(count, seed, min_s, max_s, truncated, corrupt, long_fraction)
    todo = [(log, out, seed, i) for i, log in enumerate(logs) if not (out / log.name).exists()]
    if processes > 1 and len(todo) > 1:
        with ProcessPoolExecutor(processes) as pool:
            list(pool.map(_write_one, todo, chunksize=1))
    else:
        for job in todo:
            _write_one(job)
    return logs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="folder for the logs")
    parser.add_argument("--count", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--min-s", type=float, default=10.0, help="shortest flight (s)")
    parser.add_argument("--max-s", type=float, default=600.0, help="longest flight (s)")
    parser.add_argument("--long-fraction", type=float, default=1.0,
                        help="fraction of logs drawn between --min-s and --max-s; the others last up to 2 x --min-s")
    parser.add_argument("--truncated", type=float, default=0.03, help="fraction of logs cut short")
    parser.add_argument("--corrupt", type=float, default=0.03, help="fraction of logs with overwritten bytes")
    parser.add_argument("--processes", type=int, default=1, help="logs written in parallel")
    args = parser.parse_args()
    t0 = time.perf_counter()
    logs = generate(args.out, args.count, args.seed, min_s=args.min_s, max_s=args.max_s, long_fraction=args.long_fraction,
                    truncated=args.truncated, corrupt=args.corrupt, processes=args.processes)
    hours = sum(log.seconds for log in logs) / 3600
    samples = sum(log.samples for log in logs)
    faults = {k: sum(log.fault == k for log in logs) for k in ("truncated", "corrupt")}
    print(f"{len(logs)} logs in {args.out}: {hours:.2f} h of flight, {samples} samples, "
          f"{faults['truncated']} truncated, {faults['corrupt']} corrupt ({time.perf_counter() - t0:.1f} s)")
    (args.out / "fleet_plan.jsonl").write_text("".join(json.dumps(asdict(log)) + "\n" for log in logs), encoding="utf-8")


if __name__ == "__main__":
    main()
