"""udpin peers benchmark: what many one-datagram senders cost a ``udpin`` link afterwards.

    python benchmarks/udpin_peers.py [--peers 2000 5000 20000] [--sends 500]

For each peer count, that many sockets on 127.0.0.1 each send one valid HEARTBEAT to a
component's ``udpin`` endpoint and close; the component reads them all; then ``--sends``
ATTITUDE messages go out (one publish's worth each). The CPU time of those sends is compared,
in the same run, between mavutil's own peer handling (every sender kept for good: the link
without peer tracking) and the endpoint's peer tracking (``endpoints.MAX_PEERS``, expiry after
``PEER_TIMEOUT_S``). Loopback only; bounded in count.
"""

from __future__ import annotations

import argparse
import socket
import time

from pymavlink.dialects.v20 import common as mavlink2

from ahrs_service.protocols.mavlink import Identity, MavlinkComponent
from ahrs_service.protocols.mavlink import endpoints as ep_mod


def _free_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def _run(peers: int, sends: int, tracked: bool) -> tuple[float, int]:
    port = _free_port()
    comp = MavlinkComponent([f"udpin:127.0.0.1:{port}"], Identity())
    ep = comp._endpoints[0]
    if not tracked:  # mavutil alone: its recv adds every sender to conn.clients for good
        ep.peers = None
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    frame = mav.heartbeat_encode(6, 8, 0, 0, 0).pack(mav)
    for _ in range(peers):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.sendto(frame, ("127.0.0.1", port))
        s.close()
        comp.poll(1000)
    for _ in range(50):
        comp.poll(100_000)
    served = len(ep.conn.clients) if not tracked else len(ep.peers)
    att = mavlink2.MAVLink_attitude_message(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    t0 = time.process_time()
    for _ in range(sends):
        ep.send_many([att])
    cpu = time.process_time() - t0
    comp.close()
    return cpu / sends, served


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peers", type=int, nargs="+", default=[2000, 5000, 20000])
    ap.add_argument("--sends", type=int, default=500)
    args = ap.parse_args()
    print(f"| peers sent once | mavutil alone: peers served | µs CPU per send | tracked: peers served | µs CPU per send | ratio |")
    print("|---:|---:|---:|---:|---:|---:|")
    for n in args.peers:
        old, old_served = _run(n, args.sends, tracked=False)
        new, new_served = _run(n, args.sends, tracked=True)
        print(f"| {n} | {old_served} | {old * 1e6:.1f} | {new_served} | {new * 1e6:.1f} | {old / new:.0f}x |")


if __name__ == "__main__":
    main()
