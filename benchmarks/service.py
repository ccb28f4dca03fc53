"""Service benchmark: the real ``ahrs-service run`` process at a fixed rate, measured from outside.

    python benchmarks/service.py [--seconds 60] [--rate 1000] [--estimator robust] [--source recorded] [--no-truth]
                                 [--floor-seconds S]
    python benchmarks/service.py --fifo-pairs 5 [--seconds 20] [--rate 1000] [--fifo-truth]

``--fifo-pairs N``: the simulated MPU-9250 on the simulated I2C bus at 1 kHz, every sample
estimated and logged (raw + estimate, as a real sensor's log is:
``log.truth = false``; ``--fifo-truth`` logs the simulator's ground truth too), ATTITUDE + ATTITUDE_QUATERNION at ``--publish`` Hz, read through its
FIFO (drained at 100 Hz: the loop wakes 100 times a second, a block each) and polled one
sample per tick (``board_options = { fifo = false }``, the reference), with the empty loop at
the FIFO's wake-up rate as the jitter reference: N alternating triples run back to back.
Prints each run (CPU of the process, and of it the simulated part's — its bus's transfers and
the twin making its samples, from /loop's ``simulation_cpu_s`` — and the service's own work,
the rest; wake-up jitter, lost samples, latency from a sample's time to the
ATTITUDE_QUATERNION carrying it), then the stall case (SIGSTOP of 20 ms — within the FIFO's
42 ms — and of 200 ms, FIFO and polling), then a table of the medians and ratios.

What runs: the service as a subprocess (its scheduler, estimator, MAVLink over UDP to a
pymavlink ground station in this process, MCAP logging to a temporary folder), started under
a fake systemd NOTIFY_SOCKET. The default source replays a 1 kHz recording of the simulator
(generated once into ``benchmarks/.cache``) in real time, so the figures are the service's own
cost. The recording carries the simulator's ground truth, which the service logs as a third
message per sample; ``--no-truth`` replays one without it, the logging load of a real sensor;
``--source simulated`` runs the live simulator instead (its physics cost included).

Printed: start-up time to READY=1 (of this run, and of the embedded default), CPU use of the
service process (one core = 100 %, from /proc after a 5 s warm-up), period jitter and overruns
from the log's /loop channel (one message a second, each describing that second: the median
second's p50, the median and the worst second's p99, the largest single deviation), the ATTITUDE/ATTITUDE_QUATERNION rates the ground
station saw — and, as references measured in the same run: the service estimating only
(same source and estimator, no log, no attitude streams), which separates what logging and
publishing add from what waking 1000 times a second and estimating cost; the same
scheduler pacing an empty loop: the timing floor of the machine (on a shared VM its vCPU
stalls dominate); and one estimator step timed back to back and right after a sleep, which
shows how much dearer everything is at the start of a tick than in a micro-benchmark.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

HERE = Path(__file__).resolve().parent
CACHE = HERE / ".cache"


def recording_1khz(seconds: float, truth: bool = True) -> Path:
    """A 1 kHz simulated flight (figure-eight, MPU-9250 error models) as an MCAP log, with the
    simulator's ground truth or (``truth`` False) without it, as a real sensor's log is."""
    path = CACHE / f"sim-figure8-1khz-{int(seconds)}s{'' if truth else '-notruth'}.mcap"
    if path.exists():
        return path
    from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID
    from ahrs_service.drivers.sim.imu import ManualClock, SimulatedImu
    from ahrs_service.drivers.sim.motion import profile
    from ahrs_service.drivers.sim.sensor_model import PART_MODELS
    from ahrs_service.logs.writer import FlightLogWriter

    CACHE.mkdir(exist_ok=True)
    imu = SimulatedImu(
        profile("figure8", looping=True),
        {"gyr": PART_MODELS["MPU9250_GYRO"], "acc": PART_MODELS["MPU9250_ACC"], "mag": PART_MODELS["AK8963"]},
        clock=ManualClock(),
    )
    n = int(seconds * 1000)
    tmp = CACHE / "recording"
    with FlightLogWriter(tmp, queue_size=10 * n, fsync=False, tf_rate_hz=1.0) as f:
        f.write_config(0, {"estimator": {"name": "madgwick", "params": {}}}, reason="benchmark recording")
        mag = np.full(3, np.nan)
        for i in range(n):
            t = i / 1000.0
            p = imu.physics(t)
            flags = GYR_VALID | ACC_VALID | MAG_VALID
            if i % 10 == 0:  # a 100 Hz magnetometer, held in between as the service does
                mag = p["mag"]
                flags |= MAG_NEW
            row = np.concatenate([p["gyr"], p["acc"], mag, [0.001]])
            t_ns = int(round(t * 1e9))
            f.write_raw(t_ns, row, flags)
            if truth:
                f.write_truth(t_ns, p["truth"].q)
    next(tmp.glob("*.mcap")).rename(path)
    tmp.rmdir()
    return path


def startup_to_ready(repeats: int = 3) -> list[float]:
    """Seconds from exec to READY=1 of ``ahrs-service run`` on its embedded default."""
    times = []
    exe = Path(sys.executable).with_name("ahrs-service")
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as tmp:
            sock_path = str(Path(tmp) / "notify.sock")
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            sock.bind(sock_path)
            sock.settimeout(0.01)
            t0 = time.monotonic()
            proc = subprocess.Popen(
                [str(exe), "run", "--log-dir", str(Path(tmp) / "logs")],
                env=dict(os.environ, NOTIFY_SOCKET=sock_path),
                stderr=subprocess.DEVNULL,
            )
            try:
                while time.monotonic() - t0 < 120:
                    try:
                        if b"READY=1" in sock.recv(4096):
                            times.append(time.monotonic() - t0)
                            break
                    except socket.timeout:
                        pass
            finally:
                proc.send_signal(signal.SIGTERM)
                proc.wait(30)
                sock.close()
    return times


def run_python(code: str) -> dict:
    """Runs ``code`` in a fresh interpreter; returns the JSON its last output line printed."""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def bare_loop(seconds: float, rate_hz: float) -> dict[str, float]:
    """The machine's floor: the service's scheduler pacing an empty loop, in its own process."""
    code = (
        "import time, json\n"
        "from ahrs_service.scheduler import FixedRateScheduler\n"
        f"s = FixedRateScheduler({rate_hz})\n"
        "c0, w0 = time.process_time(), time.monotonic()\n"
        f"end = w0 + {seconds}\n"
        "p50, p99, jmax, nxt = [], [], 0.0, w0 + 1.0\n"
        "while time.monotonic() < end:\n"
        "    s.wait(); s.done()\n"
        "    if time.monotonic() >= nxt:\n"  # once a second, as the service does
        "        nxt += 1.0; st = s.stats()\n"
        "        p50.append(st.period_jitter_p50_us); p99.append(st.period_jitter_p99_us)\n"
        "        jmax = max(jmax, st.period_jitter_max_us)\n"
        "d = s.stats().as_dict()\n"
        "p50.sort(); p99.sort()\n"
        "d.update(period_jitter_p50_us=p50[len(p50) // 2], period_jitter_p99_us=p99[-1],\n"
        "         period_jitter_p99_median_us=p99[len(p99) // 2], period_jitter_max_us=jmax)\n"
        "d['cpu'] = 100 * (time.process_time() - c0) / (time.monotonic() - w0)\n"
        "print(json.dumps(d))\n"
    )
    return run_python(code)


def source_only(cfg: Path, seconds: float) -> dict[str, float]:
    """The reference for the service's own work: the configured source alone in its own
    process, woken as the service wakes (its scheduler at the same loop rate) and read the
    same way (one block a wake-up), nothing else — for a simulated board that is the register
    twin and its physics, which the service process pays too but a real part does not."""
    code = (
        "import time, json\n"
        "from ahrs_service import config as config_mod\n"
        "from ahrs_service.scheduler import FixedRateScheduler\n"
        "from ahrs_service.sources import make_source\n"
        f"cfg = config_mod.load({str(cfg)!r})\n"
        "src = make_source(cfg.source, cfg.rates['estimation_hz']); src.open()\n"
        "s = FixedRateScheduler(src.wakeup_rate_hz or cfg.rates['estimation_hz'])\n"
        "n = 0\n"
        f"end = time.monotonic() + 5.0 + {seconds}\n"
        "c0 = w0 = None\n"
        "while time.monotonic() < end:\n"
        "    s.wait()\n"
        "    b = src.read_block(64 if src.may_have_backlog else 1)\n"
        "    if c0 is None and time.monotonic() >= end - " + f"{seconds}" + ":\n"
        "        c0, w0, n = time.process_time(), time.monotonic(), 0\n"
        "    n += len(b)\n"
        "    s.done()\n"
        "print(json.dumps({'cpu': 100 * (time.process_time() - c0) / (time.monotonic() - w0),\n"
        "                  'samples_per_s': n / (time.monotonic() - w0)}))\n"
    )
    return run_python(code)


def start_service(cfg: Path, tmp: Path) -> tuple[subprocess.Popen, float]:
    """``ahrs-service run --config cfg`` under a fake systemd; returns it at READY=1 and the
    seconds that took."""
    notify_path = str(tmp / f"notify-{cfg.stem}.sock")
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(notify_path)
    notify.settimeout(0.05)
    exe = Path(sys.executable).with_name("ahrs-service")
    t_start = time.monotonic()
    with open(tmp / f"{cfg.stem}.log", "w") as service_log:
        proc = subprocess.Popen([str(exe), "run", "--config", str(cfg)],
                                env=dict(os.environ, NOTIFY_SOCKET=notify_path), stderr=service_log)
    try:
        while time.monotonic() - t_start < 120:
            try:
                if b"READY=1" in notify.recv(4096):
                    return proc, time.monotonic() - t_start
            except socket.timeout:
                pass
        proc.kill()
        raise SystemExit("the service did not get READY within 120 s")
    finally:
        notify.close()


def stop_service(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL if it has not ended within 30 s."""
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()


def loop_records(path: Path) -> list[dict]:
    """The log's /loop messages (one a second, each describing that second), decoded."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/loop"])]


def service_cpu(cfg: Path, tmp: Path, seconds: float) -> float:
    """CPU (one core = 100 %) of the service run with ``cfg``, over ``seconds`` after a 5 s warm-up."""
    proc, _ = start_service(cfg, tmp)
    try:
        time.sleep(5.0)
        cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
        time.sleep(seconds)
        return 100.0 * (cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - wall0)
    finally:
        stop_service(proc)


def measured_run(cfg: Path, tmp: Path, logs: Path, gcs, seconds: float,
                 stalls_s: tuple[float, ...] = ()) -> dict[str, float]:
    """One service run: CPU over ``seconds`` after a 5 s warm-up (one core = 100 %), the loop's
    wake-up jitter (p99 of the median second, /loop), lost samples by cause, and the latency
    from a sample's time to the ATTITUDE_QUATERNION carrying it (p50/p99, ms). ``stalls_s``:
    SIGSTOP the service for these many seconds each, one per second of the run, SIGCONT after.

    Latency: each ATTITUDE_QUATERNION received is matched to the logged sample whose estimate
    it carries (same quaternion to float32 precision, the newest such sample not after the
    receive time); the receive time is this process's monotonic clock (system-wide, as the
    service's), so the figure includes the ground station's own receive delay."""
    from ahrs_service.logs.reader import read_log

    proc, _ = start_service(cfg, tmp)
    received: list[tuple[int, list[float]]] = []
    try:
        end_warm = time.monotonic() + 5.0
        while time.monotonic() < end_warm:
            gcs.recv_match(blocking=True, timeout=0.05)
        cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
        stalls = list(stalls_s)
        next_stall = wall0 + 1.0
        while time.monotonic() - wall0 < seconds:
            if stalls and time.monotonic() >= next_stall:
                os.kill(proc.pid, signal.SIGSTOP)
                time.sleep(stalls.pop(0))
                os.kill(proc.pid, signal.SIGCONT)
                next_stall = time.monotonic() + 1.0
            m = gcs.recv_match(blocking=True, timeout=0.02)
            if m is not None and m.get_type() == "ATTITUDE_QUATERNION":
                received.append((time.monotonic_ns(), [m.q1, m.q2, m.q3, m.q4]))
        cpu = 100.0 * (cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - wall0)
    finally:
        stop_service(proc)
    log = read_log(next(logs.glob("flight-*.mcap")))
    loops = loop_records(log.path)
    steady = loops[5:] or loops
    lost = loops[-1]["source"].get("lost", {}) if loops else {}
    # the simulated part's share, from /loop's CPU counters over the same steady seconds (the
    # record written at close left out): what a real part would not cost the process
    timed = [m for m in steady[:-1] if "simulation_cpu_s" in m]
    if len(timed) >= 2:
        span_s = (timed[-1]["t_ns"] - timed[0]["t_ns"]) / 1e9
        process_s = timed[-1]["process_cpu_s"] - timed[0]["process_cpu_s"]
        simulated_s = timed[-1]["simulation_cpu_s"] - timed[0]["simulation_cpu_s"]
        own = {"own_cpu": 100.0 * (process_s - simulated_s) / span_s, "simulated_cpu": 100.0 * simulated_s / span_s}
    else:
        own = {"own_cpu": float("nan"), "simulated_cpu": float("nan")}
    q32 = log.attitudes.astype(np.float32)
    latency = []
    for t_recv, q in received:
        hi = int(np.searchsorted(log.t_ns, t_recv, side="right"))
        lo = int(np.searchsorted(log.t_ns, t_recv - 300_000_000))
        if hi <= lo:
            continue
        same = np.flatnonzero(np.all(q32[lo:hi] == np.asarray(q, dtype=np.float32), axis=1))
        if same.size:
            latency.append((t_recv - int(log.t_ns[lo + same[-1]])) / 1e6)
    return {
        "cpu": cpu,
        **own,
        "jitter_p99_us": float(np.median([l["period_jitter_p99_us"] for l in steady])) if steady else float("nan"),
        "overruns": loops[-1]["overruns"] if loops else -1,
        "lost": int(lost.get("total", 0)),
        "lost_by_cause": {k: v for k, v in lost.items() if k != "total" and v},
        "logged": len(log),
        "latency_p50_ms": float(np.percentile(latency, 50)) if latency else float("nan"),
        "latency_p99_ms": float(np.percentile(latency, 99)) if latency else float("nan"),
        "matched": len(latency),
        "received": len(received),
    }


def fifo_pairs(args: argparse.Namespace) -> int:
    """FIFO against polling on the simulated MPU-9250, and the FIFO loop's wake-up jitter
    against the empty loop at the same rate: N alternating pairs; then the stall case."""
    fifo_read_hz = 100.0
    results: dict[str, list[dict]] = {"fifo": [], "polling": [], "empty": [], "fifo source": [],
                                      "polling source": []}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0")
        port = gcs.port.getsockname()[1]

        def config(name: str, fifo: bool) -> tuple[Path, Path]:
            logs = tmp / f"logs-{name}"
            cfg = tmp / f"{name}.toml"
            options = f"fifo = true, fifo_read_hz = {fifo_read_hz}" if fifo else "fifo = false"
            cfg.write_text(
                f'[source]\ntype = "simulated_i2c"\nprofile = "figure8"\nboard = "mpu9250"\n'
                f'board_options = {{ {options} }}\n\n'
                f'[estimator]\nname = "{args.estimator}"\n\n'
                f"[rates]\nestimation_hz = {args.rate}\nattitude_hz = {args.publish}\n"
                f"attitude_quaternion_hz = {args.publish}\n\n"
                f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{port}"]\n\n[log]\ndirectory = "{logs}"\n'
                f"truth = {'true' if args.fifo_truth else 'false'}\n")
            return cfg, logs

        for i in range(args.fifo_pairs):
            for kind in ("fifo", "polling", "empty", "fifo source", "polling source"):
                if kind == "empty":
                    floor = bare_loop(args.seconds, fifo_read_hz)
                    r = {"cpu": floor["cpu"], "jitter_p99_us": floor["period_jitter_p99_median_us"]}
                elif kind.endswith("source"):
                    r = source_only(config(f"{kind.replace(' ', '-')}-{i}", kind.startswith("fifo"))[0], args.seconds)
                else:
                    cfg, logs = config(f"{kind}-{i}", kind == "fifo")
                    r = measured_run(cfg, tmp, logs, gcs, args.seconds)
                results[kind].append(r)
                print(f"pair {i + 1}: {kind:8s} " + ", ".join(
                    f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()), flush=True)
        stall = {}
        for kind in ("fifo", "polling"):
            cfg, logs = config(f"stall-{kind}", kind == "fifo")
            stall[kind] = measured_run(cfg, tmp, logs, gcs, max(args.seconds, 6.0), stalls_s=(0.02, 0.02, 0.2, 0.2))
            print(f"stall case {kind}: " + ", ".join(f"{k} {v}" for k, v in stall[kind].items()), flush=True)

    def med(kind: str, key: str) -> float:
        return float(np.median([r[key] for r in results[kind]]))

    n = args.fifo_pairs
    watermark_ms = 1e3 / fifo_read_hz
    pair_ratios = [f["own_cpu"] / p["own_cpu"] for f, p in zip(results["fifo"], results["polling"])]
    rows = [
        ("setup", f"simulated MPU-9250, simulated I2C, {args.rate:.0f} Hz, {args.estimator}, every sample "
                  f"estimated and logged (raw + estimate{' + the simulator’s truth' if args.fifo_truth else ''}), ATTITUDE + ATTITUDE_QUATERNION {args.publish:.0f} Hz; "
                  f"FIFO drained at {fifo_read_hz:.0f} Hz; {n} alternating runs of each, {args.seconds:.0f} s after "
                  f"5 s warm-up"),
        ("CPU, FIFO (median)", f"{med('fifo', 'cpu'):.1f} %"),
        ("CPU, polling one sample per tick (median)", f"{med('polling', 'cpu'):.1f} %"),
        ("CPU ratio FIFO / polling, whole process", f"{med('fifo', 'cpu') / med('polling', 'cpu'):.2f}"),
        ("of it, the simulated part (its bus's transfers and samples, /loop `simulation_cpu_s`), FIFO / polling "
         "(median)", f"{med('fifo', 'simulated_cpu'):.1f} % / {med('polling', 'simulated_cpu'):.1f} %"),
        ("**the service's own work** (process − simulated part), FIFO / polling (median)",
         f"{med('fifo', 'own_cpu'):.1f} % / {med('polling', 'own_cpu'):.1f} %"),
        ("**own-work ratio FIFO / polling** (target ≤ 0.5): of the medians; the median of the pairs' ratios (each pair's)",
         f"**{med('fifo', 'own_cpu') / med('polling', 'own_cpu'):.3f}**; **{float(np.median(pair_ratios)):.3f}** "
         f"({', '.join(f'{r:.2f}' for r in pair_ratios)})"),
        ("samples logged per second, FIFO / polling (median)",
         f"{med('fifo', 'logged') / (args.seconds + 5):.0f} / {med('polling', 'logged') / (args.seconds + 5):.0f} "
         "(approximate: the log spans start-up to stop)"),
        ("the source alone (simulated twin + driver), FIFO / polling: CPU (median)",
         f"{med('fifo source', 'cpu'):.1f} % / {med('polling source', 'cpu'):.1f} %"),
        ("service minus its source, FIFO / polling (median of each; ratio)",
         f"{med('fifo', 'cpu') - med('fifo source', 'cpu'):.1f} % / "
         f"{med('polling', 'cpu') - med('polling source', 'cpu'):.1f} % "
         f"({(med('fifo', 'cpu') - med('fifo source', 'cpu')) / (med('polling', 'cpu') - med('polling source', 'cpu')):.2f})"),
        (f"wake-up jitter p99 (median second), FIFO loop at {fifo_read_hz:.0f} Hz (median)",
         f"{med('fifo', 'jitter_p99_us'):.0f} µs"),
        (f"wake-up jitter p99 (median second), empty loop at {fifo_read_hz:.0f} Hz (median)",
         f"{med('empty', 'jitter_p99_us'):.0f} µs"),
        ("jitter ratio FIFO / empty loop (target ≤ 2)", f"{med('fifo', 'jitter_p99_us') / med('empty', 'jitter_p99_us'):.2f}"),
        ("latency sample → ATTITUDE_QUATERNION carrying it, p50 / p99 (median of runs)",
         f"{med('fifo', 'latency_p50_ms'):.1f} / {med('fifo', 'latency_p99_ms'):.1f} ms "
         f"(target p99 ≤ {watermark_ms + 2:.0f} ms)"),
        ("lost samples per run, FIFO / polling (median)", f"{med('fifo', 'lost'):.0f} / {med('polling', 'lost'):.0f}"),
        ("stall case, FIFO: 2 × 20 ms + 2 × 200 ms SIGSTOP", f"lost {stall['fifo']['lost']} "
         f"{stall['fifo']['lost_by_cause']}, logged {stall['fifo']['logged']}"),
        ("stall case, polling: the same stops", f"lost {stall['polling']['lost']} "
         f"{stall['polling']['lost_by_cause']}, logged {stall['polling']['logged']}"),
    ]
    print("| measure | value |\n|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")
    return 0


def step_after_sleep_us(estimator: str, n: int = 300) -> tuple[float, float]:
    """Median µs of one ``update_row`` of ``estimator`` called back to back, and called right
    after a 0.8 ms sleep (as the service calls it): the cost of starting each tick cold."""
    from ahrs_service import estimators

    est = estimators.create(estimator)
    row = np.array([0.01, 0.02, -0.01, 0.1, 0.2, -9.8, 20.0, 1.0, 45.0, 0.001])
    for _ in range(1000):
        est.update_row(row)
    warm, cold = [], []
    for i in range(2 * n):
        if i % 2:
            time.sleep(0.0008)
        t0 = time.perf_counter_ns()
        est.update_row(row)
        (cold if i % 2 else warm).append(time.perf_counter_ns() - t0)
    return float(np.median(warm)) / 1e3, float(np.median(cold)) / 1e3


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=1000.0, help="estimation rate, Hz")
    ap.add_argument("--publish", type=float, default=100.0, help="ATTITUDE and ATTITUDE_QUATERNION rate, Hz")
    ap.add_argument("--estimator", default="madgwick")
    ap.add_argument("--source", choices=("recorded", "simulated", "simulated_i2c"), default="recorded")
    ap.add_argument("--no-truth", action="store_true",
                    help="replay the recording without its ground truth, as a real sensor's log is "
                         "(two log messages a sample instead of three)")
    ap.add_argument("--floor-seconds", type=float, default=None, metavar="S",
                    help="length of the empty-loop reference run, e.g. as long as the run to compare "
                         "overruns (default: the run's length, at most 30 s)")
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--fifo-truth", action="store_true",
                    help="--fifo-pairs: log the simulator's ground truth too (a third message a sample; "
                         "the default logs raw + estimate, as a real sensor's log)")
    ap.add_argument("--fifo-pairs", type=int, default=0, metavar="N",
                    help="only compare the MPU-9250 read through its FIFO against polling, N alternating pairs")
    args = ap.parse_args(argv)
    if args.fifo_pairs:
        return fifo_pairs(args)
    floor_s = min(args.seconds, 30.0) if args.floor_seconds is None else args.floor_seconds

    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        gcs = mavutil.mavlink_connection("udpin:127.0.0.1:0")
        port = gcs.port.getsockname()[1]
        if args.source == "recorded":
            source = f'type = "recorded"\nrecorded_path = "{recording_1khz(args.seconds + 30, truth=not args.no_truth)}"\nrecorded_realtime = true'
        else:
            source = f'type = "{args.source}"\nprofile = "figure8"\nboard = "mpu9250"'
        def config(name: str, publish_hz: float, log: str) -> Path:
            path = tmp / name
            path.write_text(
                f"[source]\n{source}\n\n[estimator]\nname = \"{args.estimator}\"\n\n"
                f"[rates]\nestimation_hz = {args.rate}\nattitude_hz = {publish_hz}\nattitude_quaternion_hz = {publish_hz}\n\n"
                f"[mavlink]\nendpoints = [\"udpout:127.0.0.1:{port}\"]\n\n[log]\n{log}\n"
            )
            return path

        cfg = config("bench.toml", args.publish, f"directory = \"{tmp / 'logs'}\"")
        proc, ready_s = start_service(cfg, tmp)
        try:
            counts: dict[str, list[int]] = {"ATTITUDE": [], "ATTITUDE_QUATERNION": []}
            warm_end = time.monotonic() + 5.0
            cpu0 = None
            t_end = time.monotonic() + args.seconds
            while time.monotonic() < t_end:
                if cpu0 is None and time.monotonic() >= warm_end:
                    cpu0, wall0 = cpu_seconds(proc.pid), time.monotonic()
                m = gcs.recv_match(blocking=True, timeout=0.05)
                if m is not None and m.get_type() in counts:
                    counts[m.get_type()].append(m.time_boot_ms)
            cpu = 100.0 * (cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - wall0)
            proc.send_signal(signal.SIGTERM)
            t_stop = time.monotonic()
            proc.wait(30)
            stop_s = time.monotonic() - t_stop
        finally:
            if proc.poll() is None:
                proc.kill()
        from ahrs_service.logs.reader import read_log

        log_file = next((tmp / "logs").glob("flight-*.mcap"))
        loops = loop_records(log_file)
        log = read_log(log_file)
        steady = loops[5:] or loops
        p50 = float(np.median([l["period_jitter_p50_us"] for l in steady]))
        p99 = float(max(l["period_jitter_p99_us"] for l in steady))
        p99_median = float(np.median([l["period_jitter_p99_us"] for l in steady]))
        jmax = float(max(l["period_jitter_max_us"] for l in steady))
        overruns = loops[-1]["overruns"]
        load = float(np.mean([l["load_percent"] for l in steady]))
        rates = {
            k: (len(v) - 1) / ((v[-1] - v[0]) / 1e3) if len(v) > 1 else 0.0 for k, v in counts.items()
        }
        floor = bare_loop(floor_s, args.rate)
        estimation_only = service_cpu(config("estimation-only.toml", 0.0, "enabled = false"), tmp,
                                      min(args.seconds, 30.0))
        ready = startup_to_ready()
        step_warm, step_cold = step_after_sleep_us(args.estimator)
        rows = [
            ("source", args.source + (" (no ground truth)" if args.no_truth and args.source == "recorded" else "")),
            ("estimator", args.estimator),
            ("estimation rate", f"{args.rate:.0f} Hz"),
            ("run", f"{args.seconds:.0f} s"),
            ("start-up to READY, embedded default (median of 3)", f"{float(np.median(ready)):.2f} s"),
            ("start-up to READY, this run (reads the recording first)", f"{ready_s:.2f} s"),
            ("CPU (one core = 100 %)", f"{cpu:.1f} %"),
            ("loop busy (load)", f"{load:.1f} %"),
            ("period jitter p50", f"{p50:.0f} µs"),
            ("period jitter p99, median second", f"{p99_median:.0f} µs"),
            ("period jitter p99, worst second", f"{p99:.0f} µs"),
            ("period jitter max", f"{jmax:.0f} µs"),
            ("overruns", str(overruns)),
            ("same machine, the service estimating only (no log, no attitude streams): CPU",
             f"{estimation_only:.1f} %"),
            ("same machine, empty loop: CPU", f"{floor['cpu']:.1f} %"),
            (f"same machine, one {args.estimator} step: back to back / right after a 0.8 ms sleep (median)",
             f"{step_warm:.1f} / {step_cold:.1f} µs"),
            ("same machine, empty loop: jitter p50 / p99 median second / p99 worst second / max",
             f"{floor['period_jitter_p50_us']:.0f} / {floor['period_jitter_p99_median_us']:.0f} / "
             f"{floor['period_jitter_p99_us']:.0f} / {floor['period_jitter_max_us']:.0f} µs"),
            ("same machine, empty loop: overruns", f"{floor['overruns']} in {floor_s:.0f} s"),
            ("ATTITUDE seen by the GCS", f"{rates['ATTITUDE']:.1f} Hz"),
            ("ATTITUDE_QUATERNION seen by the GCS", f"{rates['ATTITUDE_QUATERNION']:.1f} Hz"),
            ("samples logged", str(len(log.t_ns))),
            ("stop after SIGTERM", f"{stop_s:.2f} s"),
        ]
        width = max(len(k) for k, _ in rows)
        if args.markdown:
            print("| measure | value |\n|---|---|")
            for k, v in rows:
                print(f"| {k} | {v} |")
        else:
            for k, v in rows:
                print(f"{k:<{width}}  {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
