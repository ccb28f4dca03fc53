"""8 kHz ICM-42688-P over the simulated SPI bus: what the service's own work costs.

    python benchmarks/spi_8khz.py [--seconds 20] [--odr 8000] [--loop-hz 500] [--estimator madgwick]
                                  [--publish 200] [--drdy] [--stall-ms 0] [--log-messages per-sample]

What runs, in this process: the service (scheduler, driver reading the FIFO in bursts over the
simulated SPI bus, estimator on every sample, MCAP log of every sample, ATTITUDE and
ATTITUDE_QUATERNION at ``--publish`` Hz over UDP to a pymavlink peer on 127.0.0.1). The
simulated part is fed from a **precomputed recording** of the simulator (figure-eight, the
ICM-42688-P's error models, sampled at the part's real rate), so the motion simulator's
physics costs nothing during the run; what the twin still does per sample (quantise, pack
the 20-byte packet, keep the FIFO) is measured apart, on the same recording, and printed
beside the total: the service's own work is the difference.

``--drdy`` wakes the loop on the simulated FIFO watermark line instead of the timer;
``--stall-ms`` stops the loop once a second for that long (a host stall) to show what the
FIFO holds: lost samples are counted by cause (``diagnostics.lost``).

Printed: CPU of this process (one core = 100 %) over the run, the twin's CPU apart, the
service's own CPU, samples estimated and logged against the samples the part produced, lost
samples by cause, the rate the part ran at and the tracked one, ATTITUDE messages seen, and
the FIFO's view of the host: every read is timed from the previous one, so each overflow is
shown with the time the FIFO went without a read before it — the rule checked is that every
loss follows a host stall longer than the FIFO's depth (12.7 ms at 8 kHz), none a shorter one.

The log is written one message per FIFO burst at 8 kHz (``log.block_messages_above_hz``);
``--log-messages per-sample`` writes one /imu/raw + /attitude per sample, for comparison.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402


class RecordedImu:
    """The simulator's output, precomputed at the part's sample instants; ``physics(t)`` looks
    the nearest one up (the twin asks exactly at those instants). A run longer than the
    recording repeats it (the motion jumps at each repeat: this benchmark measures cost and
    loss, not accuracy), so a 10-minute run does not hold 10 minutes of samples in memory."""

    def __init__(self, seconds: float, rate_hz: float, clock) -> None:
        from ahrs_service.drivers.sim.imu import SimulatedImu
        from ahrs_service.drivers.sim.motion import profile
        from ahrs_service.drivers.sim.sensor_model import PART_MODELS

        self.clock, self.rate_hz = clock, rate_hz
        imu = SimulatedImu(profile("figure8", looping=True),
                           {"gyr": PART_MODELS["ICM42688P_GYRO"].analog(),
                            "acc": PART_MODELS["ICM42688P_ACC"].analog(), "mag": PART_MODELS["ideal"]},
                           clock=clock, seed=1)
        n = int(seconds * rate_hz) + 1
        self.rows = []
        for k in range(n):
            p = imu.physics(k / rate_hz)
            self.rows.append({"gyr": np.array(p["gyr"]), "acc": np.array(p["acc"]), "mag": np.zeros(3),
                              "temperature_c": 25.0, "truth": {"q": np.array(p["truth"].q)}})

    def physics(self, t: float) -> dict:
        return self.rows[int(round(t * self.rate_hz)) % len(self.rows)]


def twin_cost_us(recording: RecordedImu, odr: float, n_samples: int) -> float:
    """CPU µs per sample of the twin alone (latch, pack, FIFO) on the recording."""
    from ahrs_service.drivers.sim.clock import ManualClock
    from ahrs_service.drivers.sim.icm42688p import SimulatedICM42688P

    clock = ManualClock()
    saved, recording.clock = recording.clock, clock
    twin = SimulatedICM42688P(recording)
    twin.regs[0x4F] = twin.regs[0x50] = {8000: 3, 4000: 4, 2000: 5, 1000: 6}[int(odr)]
    twin.regs[0x16], twin.regs[0x5F], twin.regs[0x4E] = 0x80, 0x3F, 0x0F
    twin.restart_measurement(0.0)
    c0 = time.process_time()
    for _ in range(int(n_samples / odr * 1000)):
        twin.update(clock.advance(0.001))
        twin.bus_read(0x30, twin.fifo.level, clock.now())  # drained as the driver does
        twin.take_popped_truth()
    cost = (time.process_time() - c0) / max(1, twin.samples_latched) * 1e6
    recording.clock = saved
    return cost


def thread_cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) of each live thread of this process, by name (Linux)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for t in threading.enumerate():
        try:
            with open(f"/proc/self/task/{t.native_id}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[t.name] = (int(fields[11]) + int(fields[12])) / tick
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--odr", type=float, default=8000.0)
    ap.add_argument("--loop-hz", type=float, default=None,
                    help="timer rate of the loop (FIFO bursts; default the board's fifo_read_hz, 500 Hz)")
    ap.add_argument("--estimator", default="madgwick")
    ap.add_argument("--publish", type=float, default=200.0)
    ap.add_argument("--drdy", action="store_true", help="wake on the simulated watermark line")
    ap.add_argument("--stall-ms", type=float, default=0.0, help="stop the loop this long once a second")
    ap.add_argument("--log-messages", choices=("config", "per-sample"), default="config",
                    help="config: the default log.block_messages_above_hz (one message per burst at 8 kHz); "
                         "per-sample: one /imu/raw + /attitude per sample, for comparison")
    args = ap.parse_args(argv)
    if args.loop_hz is None:
        from ahrs_service.drivers.boards.transport import ICM42688PBoard

        args.loop_hz = ICM42688PBoard.FIFO_READ_HZ

    from ahrs_service import config, sources
    from ahrs_service import service as service_mod
    from ahrs_service.drivers.boards import make_transport_board
    from ahrs_service.drivers.parts.icm42688p import FIFO_DATA, INT_STATUS, STATUS_BYTES
    from ahrs_service.drivers.sim.bus import twin_behind
    from ahrs_service.drivers.sim.drdy import SimulatedDataReadyLine
    from ahrs_service.drivers.sim.imu import MonotonicClock

    clock = MonotonicClock()
    real_rate = args.odr * 1.0042  # the twin's oscillator error
    recorded_s = min(args.seconds + 15, 60.0)
    print(f"precomputing {recorded_s:.0f} s of the simulator at {real_rate:.1f} Hz …", flush=True)
    recording = RecordedImu(recorded_s, real_rate, clock)
    twin_us = twin_cost_us(recording, args.odr, min(80_000, int(args.odr * 5)))

    gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0")
    port = gcs.port.getsockname()[1]
    seen = {"ATTITUDE": 0, "ATTITUDE_QUATERNION": 0}
    stop = threading.Event()

    def listen() -> None:
        while not stop.is_set():
            m = gcs.recv_match(blocking=True, timeout=0.05)
            if m is not None and m.get_type() in seen:
                seen[m.get_type()] += 1

    boards = []
    stalls: list[tuple[float, bool]] = []  # injected: (host time without a FIFO read, s; overflowed)
    overflow_gaps: list[float] = []  # every read that found an overflow: the time without a FIFO read before it, s
    # the driver's drains of the FIFO, seen on the bus: (host time of the level read, of the first data read)
    drains: list[tuple[float, float]] = []
    status_read = [0.0]
    part_time = [0.0]  # simulation time (s) of the part's state: see make_source

    simulated_ns = [0]  # CPU of the thread that ran them, inside the simulated bus and part

    def make_source(source_cfg, estimation_hz, system_id=1):  # sources.make_source's signature
        board = make_transport_board("icm42688p", "spi", simulated_imu=recording,
                                     odr_hz=args.odr, fifo_read_hz=args.loop_hz)
        bus = board.transport.bus
        transfer = bus.transfer
        # the simulation time up to which the part has made its samples (its FIFO's state is
        # that of this instant): a transfer's latch or pop is timed by it, not by the host's
        # clock when the call returns — a loop thread preempted between the part's catch-up
        # and its latch (the GIL held by the log writer, say) read a level as old as the
        # catch-up, and timed at the return the window looked that much shorter
        part = twin_behind(board.transport)
        make_samples = part.update

        def timed_update(now: float) -> None:
            part_time[0] = max(part_time[0], now)
            make_samples(now)

        part.update = timed_update

        def timed_transfer(cs, data):  # what a real spidev ioctl would replace: measured apart
            c = time.thread_time_ns()
            try:
                answer = transfer(cs, data)
            finally:
                simulated_ns[0] += time.thread_time_ns() - c
            # each end is the instant of the part's state the transfer saw: the simulated part
            # makes its due samples first (catch_up, inside the call, milliseconds of Python
            # at 8 kHz), then latches the level or pops the FIFO
            level_read = data[0] == 0x80 | INT_STATUS and len(data) == 1 + STATUS_BYTES
            if level_read:  # the driver reads the FIFO's level: a drain starts
                status_read[0] = part_time[0]
            elif data[0] in (0x80 | INT_STATUS, 0x80 | FIFO_DATA) and status_read[0]:
                # its first data transfer (from INT_STATUS on, as PX4's) pops the FIFO
                drains.append((status_read[0], part_time[0]))
                status_read[0] = 0.0
            return answer

        now_ns = bus.now_ns

        def timed_now_ns():  # the simulated bus has its part make the due samples here too
            c = time.thread_time_ns()
            try:
                return now_ns()
            finally:
                simulated_ns[0] += time.thread_time_ns() - c

        bus.transfer, bus.now_ns = timed_transfer, timed_now_ns
        if args.drdy:
            board.data_ready_line = SimulatedDataReadyLine(twin_behind(board.transport), clock)
        boards.append(board)
        return board

    with tempfile.TemporaryDirectory() as tmp:
        cfg = config.validate({
            "source": {"type": "simulated_spi", "board": "icm42688p",
                       "board_options": {"odr_hz": args.odr, "fifo_read_hz": args.loop_hz}},
            "estimator": {"name": args.estimator},
            "rates": {"estimation_hz": min(args.loop_hz, 2000.0), "attitude_hz": args.publish,
                      "attitude_quaternion_hz": args.publish},
            "mavlink": {"endpoints": [f"udpout:127.0.0.1:{port}"]},
            "log": {"directory": str(Path(tmp) / "logs"),
                    **({"block_messages_above_hz": 1_000_000.0} if args.log_messages == "per-sample" else {})},
        })
        service_mod.make_source = make_source  # the recording-fed twin instead of the live simulator
        sources.make_source = make_source
        svc = service_mod.Service(cfg, duration_s=args.seconds)
        svc.start()
        listener = threading.Thread(target=listen, daemon=True, name="gcs-peer")
        listener.start()
        # every drain of the FIFO (seen on the bus) is timed from the previous one: the host
        # stalls the FIFO saw (the injected ones with --stall-ms, and the busy host's own), and
        # what each overflow followed. A drain pops the samples its level read counted, so the
        # FIFO fills from the previous drain's *level read* to this drain's *data read*: the
        # window that must stay under the FIFO's depth. (The simulated part computes its
        # samples in Python, a few ms of real time at 8 kHz, at the start of each transfer and
        # when the host reads the bus clock, before it latches or pops; both ends are the
        # instants up to which it had made them, make_source's ``part_time``. Timed by the
        # host's clock around the transfers instead, 2 overflows of a 10-minute run showed
        # after windows of 9.7 and 12.0 ms, and 12 of another after 9.1–12.2 ms. A real
        # part's samples cost nothing and its level read takes microseconds.) The
        # driver leaves the FIFO undrained while it holds 4 FIFO depths of rows the loop has
        # not taken yet (a loop slower than the part): that shows as a long window too.
        board = boards[0]
        inner = board.read_block
        next_stall = [time.monotonic() + 1.0]
        depth_s = 2048 // 20 / real_rate  # the ICM-42688-P's FIFO: 102 packets of 20 bytes

        in_run = [False]
        marks: dict[str, dict] = {}  # the counts after the loop's first and last reads

        def timed_read(max_samples=128):
            injected = args.stall_ms > 0 and time.monotonic() >= next_stall[0]
            if injected:  # a host stall: the loop thread is held inside the source's read once a second
                next_stall[0] += 1.0
                time.sleep(args.stall_ms / 1000)
            overflows = board.diagnostics.extra["fifo_overflows"]
            block = inner(max_samples)
            overflowed = board.diagnostics.extra["fifo_overflows"] > overflows
            # what the FIFO saw: the longest time without a drain among this call's and the one
            # before (the part's FIFO_FULL flag is counted once the FIFO is drained, which can be
            # the drain after the one that found it full), sleeps and the host's own delays
            gap = max((b[1] - a[0] for a, b in zip(drains[-3:], drains[-2:])), default=0.0)
            if injected:
                stalls.append((gap, overflowed))
            if overflowed:
                overflow_gaps.append(gap)
            # the counts as this read left them: the run's figures go from the loop's first
            # read to its last (before the first, the part's FIFO fills while the service sets
            # up, and the driver flushes those samples as older than its consumer; after the
            # last, the part goes on while the service shuts down)
            if in_run[0]:
                counts = _counts(len(block))
                marks.setdefault("first", counts)
                marks["last"] = counts
            return block

        def _counts(rows_to_estimate: int) -> dict:
            twin, diag = twin_behind(board.transport), board.diagnostics
            return {"produced": twin.samples_latched + twin.samples_unseen - twin.fifo.level // 20,
                    "dropped": twin.fifo.dropped + twin.fifo.discarded, "read": diag.samples,
                    "lost": (diag.lost.fifo_overflow, diag.lost.bus_error, diag.extra["fifo_overflows"]),
                    "estimated": svc.pipeline.samples + rows_to_estimate}

        board.read_block = timed_read
        # the source opens before the log and MAVLink: drain what the FIFO gathered meanwhile
        # (a start-up overflow), and count from the loop's start
        board = boards[0]
        while len(board.read_block()):
            pass
        overflow_gaps.clear()
        del drains[:-1]
        in_run[0] = True
        threads0 = thread_cpu_s()
        sim0 = simulated_ns[0]
        c0, w0 = time.process_time(), time.monotonic()
        svc.run()
        cpu = 100 * (time.process_time() - c0) / (time.monotonic() - w0)
        wall = time.monotonic() - w0
        threads = {name: 100 * (s - threads0.get(name, 0.0)) / wall for name, s in thread_cpu_s().items()}
        sim_pct = 100 * (simulated_ns[0] - sim0) / 1e9 / wall
        diag = board.diagnostics
        first, last = marks["first"], marks["last"]
        produced = last["produced"] - first["produced"]
        dropped = last["dropped"] - first["dropped"]
        read = last["read"] - first["read"]
        estimated = svc.pipeline.samples - first["estimated"]
        lost = tuple(b - a for a, b in zip(first["lost"], last["lost"]))
        svc.close()
        stop.set()
        listener.join(1.0)
    twin_pct = twin_us * real_rate / 1e4
    log_layout = "per sample" if args.log_messages == "per-sample" else f"per burst above {cfg.log['block_messages_above_hz']:g} Hz"
    loop_pct = threads.get("MainThread", 0.0) - sim_pct
    writer_pct = threads.get("flight-log-writer", 0.0)
    peer_pct = threads.get("gcs-peer", 0.0)
    print()
    print(f"| {args.odr:.0f} Hz ICM-42688-P, simulated SPI, {args.estimator}, publish {args.publish:.0f} Hz, "
          f"{'data-ready line' if args.drdy else f'timer {args.loop_hz:.0f} Hz'}"
          f"{f', {args.stall_ms:.0f} ms stall a second' if args.stall_ms else ''}, log {log_layout} | value |")
    print("|---|---|")
    print(f"| wall time of the run, s | {wall:.1f} |")
    print(f"| CPU of the process (service + twin), % of one core | {cpu:.1f} |")
    print(f"| the twin alone, measured on its own (pack + FIFO: {twin_us:.1f} µs/sample), % | {twin_pct:.1f} |")
    print(f"| in the run: inside the simulated SPI bus and part (the loop thread's CPU there), % | {sim_pct:.1f} |")
    print(f"| in the run: the benchmark's ground-station peer (its thread), % | {peer_pct:.1f} |")
    print(f"| **the service's own work** (process − simulated bus and part − peer), % of one core | "
          f"**{cpu - sim_pct - peer_pct:.1f}** |")
    own_us = (cpu - sim_pct - peer_pct) / 100 * wall / max(estimated, 1) * 1e6
    print(f"| the service's own work per sample estimated, µs / at every sample of the part's rate, % of one core | "
          f"{own_us:.1f} / {own_us * real_rate / 1e4:.1f} |")
    print(f"| of which: loop thread (outside the bus) / log writer thread / others, % | {loop_pct:.1f} / "
          f"{writer_pct:.1f} / {cpu - sim_pct - peer_pct - loop_pct - writer_pct:.1f} |")
    print(f"| from the loop's first read to its last: samples the part produced (less those still in its FIFO) / read by the driver / estimated and logged | "
          f"{produced} / {read} / {estimated} |")
    print(f"| lost: FIFO overflow / bus error (overflow events: {lost[2]}) / the part's own count of the samples it turned away or had flushed unread | "
          f"{lost[0]} / {lost[1]} / {dropped} |")
    print(f"| part rate (true) / tracked, Hz | {real_rate:.2f} / {board.clock.rate_hz:.2f} |")
    depth_ms = depth_s * 1e3
    gaps_s = np.array([b[1] - a[0] for a, b in zip(drains, drains[1:])] or [0.0])
    print(f"| FIFO drains / longest time without one, ms / drains after more than the FIFO's depth ({depth_ms:.1f} ms) | "
          f"{len(drains)} / {gaps_s.max() * 1e3:.1f} / {int((gaps_s > depth_s).sum())} |")
    short = sorted(g * 1e3 for g in overflow_gaps if g <= depth_s)
    print(f"| overflow events after more than the FIFO's depth without a drain / after less (ms) | "
          f"{len(overflow_gaps) - len(short)} / {len(short)}{': ' + ', '.join(f'{g:.1f}' for g in short[:10]) if short else ''} |")
    if stalls:
        gaps = sorted(g * 1e3 for g, _ in stalls)
        print(f"| stalls: count / longest time without a FIFO read, ms (FIFO depth {depth_ms:.1f} ms) | "
              f"{len(stalls)} / {gaps[-1]:.1f} |")
        print(f"| overflowed stalls: longer / shorter than the FIFO depth | "
              f"{sum(1 for g, o in stalls if o and g * 1e3 > depth_ms)} / "
              f"{sum(1 for g, o in stalls if o and g * 1e3 <= depth_ms)} |")
    print(f"| ATTITUDE / ATTITUDE_QUATERNION received | {seen['ATTITUDE']} / {seen['ATTITUDE_QUATERNION']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
