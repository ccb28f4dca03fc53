"""What the Foxglove live view costs the service: runs without and with viewers, alternating.

    python benchmarks/live_view.py [--pairs 3] [--seconds 20] [--rate 1000] [--viewers 3] [--markdown]

Each pair runs the real ``ahrs-service run`` process twice with the same configuration, once
with ``[live] enabled = false`` and once enabled with ``--viewers`` WebSocket clients (the
``websockets`` package, Foxglove's protocol) subscribed to every channel and reading all the
time; which of the two goes first alternates from pair to pair so a drift of the shared
machine cancels. Measured per run, after a 5 s warm-up: the service's CPU (one core = 100 %,
from /proc) and the loop's period-jitter p99 (median second, from the log's /loop). Printed:
every run, then the CPU difference with viewers (mean over pairs) against the target of
≤ 3 points, and the p99 with viewers against the spread (min–max) of the runs without.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import service as bench  # noqa: E402  (benchmarks/service.py: start_service, cpu_seconds)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def viewers(port: int, n: int, stop: threading.Event, received: list[int]) -> threading.Thread:
    import websockets

    async def one(i: int) -> None:
        async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                      max_size=None) as ws:
            subscribed = False
            while not stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except asyncio.TimeoutError:
                    continue
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        subs = [{"id": 1000 * i + k, "channelId": ch["id"]} for k, ch in enumerate(msg["channels"])]
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                        subscribed = True
                elif subscribed:
                    received[i] += 1

    async def all_() -> None:
        await asyncio.gather(*(one(i) for i in range(n)))

    t = threading.Thread(target=lambda: asyncio.run(all_()), daemon=True)
    t.start()
    return t


def one_run(tmp: Path, name: str, args: argparse.Namespace, live: bool) -> dict[str, float]:
    live_port = free_port()
    logs = tmp / f"logs-{name}"
    cfg = tmp / f"{name}.toml"
    cfg.write_text(
        f'[source]\ntype = "simulated"\nprofile = "figure8"\nboard = "mpu9250"\n\n'
        f'[estimator]\nname = "{args.estimator}"\n\n[rates]\nestimation_hz = {args.rate}\n\n'
        f'[mavlink]\nendpoints = ["udpout:127.0.0.1:{free_port()}"]\n\n[log]\ndirectory = "{logs}"\n\n'
        f'[live]\nenabled = {"true" if live else "false"}\nport = {live_port}\n'
    )
    proc, _ = bench.start_service(cfg, tmp)
    stop = threading.Event()
    received = [0] * args.viewers
    thread = viewers(live_port, args.viewers, stop, received) if live else None
    try:
        time.sleep(5.0)
        cpu0, wall0 = bench.cpu_seconds(proc.pid), time.monotonic()
        time.sleep(args.seconds)
        cpu = 100.0 * (bench.cpu_seconds(proc.pid) - cpu0) / (time.monotonic() - wall0)
    finally:
        stop.set()
        if thread is not None:
            thread.join(5)
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    loops = bench.loop_records(next(logs.glob("*.mcap")))
    steady = loops[5:] or loops
    return {"cpu": cpu, "p99": float(np.median([l["period_jitter_p99_us"] for l in steady])),
            "received": float(min(received)) if live else 0.0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--viewers", type=int, default=3)
    ap.add_argument("--estimator", default="madgwick")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    runs: list[tuple[int, bool, dict[str, float]]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for pair in range(args.pairs):
            order = (False, True) if pair % 2 == 0 else (True, False)
            for live in order:
                runs.append((pair, live, one_run(tmp, f"p{pair}-{'live' if live else 'none'}", args, live)))
    rows = [(f"pair {p} {'with ' + str(args.viewers) + ' viewers' if live else 'no viewers'}",
             f"CPU {r['cpu']:.1f} %, jitter p99 {r['p99']:.0f} µs" + (f", {r['received']:.0f} messages/viewer" if live else ""))
            for p, live, r in runs]
    with_v = {p: r for p, live, r in runs if live}
    without = {p: r for p, live, r in runs if not live}
    d_cpu = float(np.mean([with_v[p]["cpu"] - without[p]["cpu"] for p in with_v]))
    lo, hi = min(r["p99"] for r in without.values()), max(r["p99"] for r in without.values())
    p99_with = [r["p99"] for r in with_v.values()]
    rows += [
        ("CPU with viewers − without (mean of pairs)", f"{d_cpu:+.1f} points (target ≤ 3): {'ok' if d_cpu <= 3 else 'MISSED'}"),
        ("jitter p99 without viewers (spread)", f"{lo:.0f} – {hi:.0f} µs"),
        ("jitter p99 with viewers", " / ".join(f"{v:.0f}" for v in p99_with) + " µs: "
         + ("within the spread" if max(p99_with) <= hi else "ABOVE the spread")),
    ]
    if args.markdown:
        print("| measure | value |\n|---|---|")
        for k, v in rows:
            print(f"| {k} | {v} |")
    else:
        w = max(len(k) for k, _ in rows)
        for k, v in rows:
            print(f"{k:<{w}}  {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
