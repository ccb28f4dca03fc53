"""A pymavlink peer that speaks for an autopilot's clock: answers TIMESYNC requests with its
own time (ours offset by ``offset_s`` and running ``drift_ppm`` fast), over real UDP on
127.0.0.1, from a thread. Also collects every other message it receives (ODOMETRY …) with the
peer-clock time it arrived at. Used by test_timesync.py and test_odometry.py, with
:func:`link_to` (our side of the link) and :func:`sync` (TIMESYNC exchanges until converged)."""

from __future__ import annotations

import threading
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2


class ClockPeer:
    """``udpin`` on a free loopback port; ``port`` is where the service side sends to."""

    def __init__(self, offset_s: float = 123.456, drift_ppm: float = 50.0, answer: bool = True) -> None:
        self.offset_ns = int(round(offset_s * 1e9))
        self.rate = 1.0 + drift_ppm * 1e-6
        self.answer = answer
        self.t_ref = time.monotonic_ns()  # drift accumulates from here
        self.conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.conn.mav = mavlink2.MAVLink(self.conn, srcSystem=1, srcComponent=1)
        self.conn.mav.robust_parsing = True
        self.port = self.conn.port.getsockname()[1]
        self.received: list[tuple[int, object]] = []  # (peer clock ns at arrival, message)
        self.answered = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def clock_ns(self, local_ns: int | None = None) -> int:
        """The peer's clock at our monotonic ``local_ns`` (now when None), ns."""
        t = time.monotonic_ns() if local_ns is None else local_ns
        return self.t_ref + self.offset_ns + int(round((t - self.t_ref) * self.rate))

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.05)
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            now = self.clock_ns()
            if msg.get_type() == "TIMESYNC" and msg.tc1 == 0:
                if self.answer:
                    self.conn.mav.timesync_send(now, msg.ts1)
                    self.answered += 1
                continue
            with self._lock:
                self.received.append((now, msg))

    def messages(self, name: str) -> list[tuple[int, object]]:
        with self._lock:
            return [(t, m) for t, m in self.received if m.get_type() == name]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.conn.close()


def link_to(peer: ClockPeer):
    """Our side: a MAVLink 2 ``udpout`` connection to ``peer`` (system 1, component 197)."""
    conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{peer.port}", source_system=1, source_component=197)
    conn.mav = mavlink2.MAVLink(conn, srcSystem=1, srcComponent=197)
    return conn


def sync(conn, ts, accepted: int = 20, seconds: float = 20.0) -> None:
    """Requests TIMESYNC on ``conn`` every 50 ms and hands every reply to ``ts`` (a
    ``TimeSync``) with its receive time taken on arrival, until ``accepted`` samples were
    accepted (bounded by ``seconds``)."""
    deadline = time.monotonic() + seconds
    while ts.counters.accepted < accepted and time.monotonic() < deadline:
        conn.mav.send(ts.request(time.monotonic_ns()).encode())
        end = time.monotonic() + 0.05
        while time.monotonic() < end:
            msg = conn.recv_match(type="TIMESYNC", blocking=True, timeout=0.02)
            if msg is not None:
                ts.handle(msg, time.monotonic_ns())
