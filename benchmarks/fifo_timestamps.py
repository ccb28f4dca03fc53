"""FIFO timestamps against the simulator's true sample times: a part running off nominal, a
host that reads late by a jittering amount.

    python benchmarks/fifo_timestamps.py [--seconds 20] [--clock-error 0.01] [--seed 1]

Each board below runs on a simulated clock (no wall time: the result is the same on a busy
machine): the simulated part samples at (1 + clock_error) × its nominal rate; the host calls
``read_block`` every 1 ms plus a jitter (|N(0, 150 µs)|, and 1 % of the calls a further
0.5–3 ms: a busy host); each bus transfer takes its wire time (400 kHz I2C, 8 MHz SPI).
Every row carries its true sample time (the stand-in physics puts it in the truth), so the
error of each row's ``t_ns`` is exact. Printed: p50 / p99 / max |error| over the rows after
``--settle`` s (10 s; the target is p99 ≤ 50 µs), beside the reference in the same
run: the same rows stamped at the host's read time, one nominal period apart back from the
newest (what a driver without the sensor clock does).
"""

from __future__ import annotations

import argparse
import math
import random
from types import SimpleNamespace

import numpy as np

from ahrs_service.drivers.sim.clock import ManualClock

#: (board name, bus, board options, what it is)
BOARDS = (
    ("mpu9250", "i2c", {"rate_hz": 1000, "fifo_read_hz": 100}, "MPU-9250 1 kHz, FIFO drained at 100 Hz"),
    ("gy80", "i2c", {"gyro_rate_hz": 800, "acc_rate_hz": 800}, "GY-80 L3G4200D 800 Hz, drained at 200 Hz"),
    ("minimu9v2", "i2c", {}, "MinIMU-9 v2 L3GD20 760 Hz, drained at 200 Hz"),
    ("icm42688p", "spi", {"odr_hz": 1000, "fifo_read_hz": 100}, "ICM-42688-P 1 kHz SPI, watermark 10"),
)


class TruthClockImu:
    """Readings whose truth is the time they were taken; a clock the host moves."""

    def __init__(self) -> None:
        self.clock = ManualClock()
        self.advance = self.clock.advance

    def physics(self, t: float) -> dict:
        return {"gyr": (0.01, -0.02, 0.03), "acc": (0.1, 0.2, -9.8), "mag": (20.0, -5.0, 40.0),
                "temperature_c": 30.0, "truth": SimpleNamespace(q=np.array([1.0, t, 0.0, 0.0]))}


def _timed_transfers(bus, src: TruthClockImu, seconds_per_byte: float, overhead_s: float) -> None:
    """Each transfer on ``bus`` takes its wire time on the simulated clock, and the part
    answers where a real one latches: after the transfer's set-up and its command phase
    (I2C: address, register, address again — 3 bytes; SPI: the command byte), before the
    data bytes are clocked out."""
    for name in ("read_byte_data", "read_i2c_block_data", "write_byte_data", "transfer"):
        inner = getattr(bus, name, None)
        if inner is None:
            continue

        def timed(*args, _inner=inner, _name=name):
            if _name == "transfer":
                command, data = 1, len(args[-1]) - 1
            else:
                command, data = (2, 1) if _name == "write_byte_data" else \
                    (3, args[-1] if _name == "read_i2c_block_data" else 1)
            src.advance(overhead_s + command * seconds_per_byte)
            out = _inner(*args)
            src.advance(data * seconds_per_byte)
            return out

        setattr(bus, name, timed)


def run(board_name: str, bus_kind: str, options: dict, clock_error: float, seconds: float,
        settle_s: float, seed: int) -> dict[str, np.ndarray]:
    """Errors (ns) of the rows after ``settle_s``: {"sensor_clock": …, "host_read": …}."""
    from ahrs_service.drivers.boards import make_simulated_board, make_transport_board

    rng = random.Random(seed)
    src = TruthClockImu()
    if bus_kind == "spi":
        board = make_transport_board(board_name, "spi", simulated_imu=src, **options)
        bus = board.transport.bus
        twins = [bus.device(board.transport.cs)]
        _timed_transfers(bus, src, 8 / 8e6, 2e-6)
        nominal = board.odr_hz
    else:
        board = make_simulated_board(board_name, src, **options)
        bus = board.bus
        twins = [bus.device(a) for a in bus.addresses()]
        _timed_transfers(bus, src, 9 / 400e3, 50e-6)  # 9 clocks a byte at 400 kHz
        nominal = board.parts["gyro"].rate_hz
    for twin in twins:
        if getattr(twin, "CLOCK_ERROR", 0.0) or hasattr(twin, "fifo"):
            twin.clock_error = clock_error
    board.open()
    sensor, host = [], []
    while src.clock.now() < seconds:
        delay = abs(rng.gauss(0.0, 150e-6))
        if rng.random() < 0.01:
            delay += rng.uniform(0.5e-3, 3e-3)
        src.advance(1e-3 + delay)
        read_at = src.clock.now()
        block = board.read_block()
        if not len(block) or block.truth_q is None:
            continue
        true_ns = np.rint(block.truth_q[:, 1] * 1e9).astype(np.int64)
        keep = true_ns > settle_s * 1e9
        sensor.append((block.t_ns - true_ns)[keep])
        naive = np.rint(read_at * 1e9 - (len(block) - 1 - np.arange(len(block))) * 1e9 / nominal)
        host.append((naive.astype(np.int64) - true_ns)[keep])
    return {"sensor_clock": np.concatenate(sensor), "host_read": np.concatenate(host)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--settle", type=float, default=10.0)
    ap.add_argument("--clock-error", type=float, default=0.01, help="the part's oscillator error (0.01 = 1 %% fast)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    print(f"| board (part {args.clock_error * 100:+.1f} % off nominal, host jitter; rows after "
          f"{args.settle:.0f} s of {args.seconds:.0f} s) | rows | sensor clock p50 / p99 / max, µs "
          f"| host read time (reference) p50 / p99 / max, µs |")
    print("|---|---:|---|---|")
    for name, bus, options, what in BOARDS:
        err = run(name, bus, options, args.clock_error, args.seconds, args.settle, args.seed)
        cells = []
        for key in ("sensor_clock", "host_read"):
            a = np.abs(err[key]) / 1e3
            cells.append(f"{np.percentile(a, 50):.1f} / {np.percentile(a, 99):.1f} / {a.max():.1f}")
        print(f"| {what} | {len(err['sensor_clock'])} | {cells[0]} | {cells[1]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
