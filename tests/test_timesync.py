"""TIMESYNC (#111): the estimate against a simulated remote clock, and against a real
pymavlink peer over UDP on 127.0.0.1 whose clock is ours offset by +123.456 s and running
50 ppm fast."""

from __future__ import annotations

import random
import time

import pytest

from ahrs_service.protocols.mavlink.timesync import (
    MAX_CONSECUTIVE_DEVIATIONS,
    MAX_RTT_NS,
    MIN_SAMPLES,
    TimeSync,
    TimesyncFields,
)
from timesync_peer import ClockPeer, link_to, sync

pytestmark = pytest.mark.timeout(60)

OFFSET_NS = 123_456_000_000
DRIFT = 50e-6


def remote(local_ns: int) -> int:
    return OFFSET_NS + int(round(local_ns * (1.0 + DRIFT)))


def exchange(ts: TimeSync, now_ns: int, up_ns: int, down_ns: int) -> None:
    """One request sent at ``now_ns`` that takes ``up_ns`` there and ``down_ns`` back."""
    req = ts.request(now_ns)
    reply = TimesyncFields(tc1=remote(now_ns + up_ns), ts1=req.ts1)
    assert ts.handle(reply, now_ns + up_ns + down_ns) is None


def test_offset_and_drift_from_a_simulated_clock_with_jittered_delays():
    ts = TimeSync()
    rng = random.Random(7)
    t = 1_000_000_000
    for k in range(MIN_SAMPLES - 1):
        exchange(ts, t, rng.randint(100_000, 900_000), rng.randint(100_000, 900_000))
        t += 100_000_000
    assert not ts.synced
    with pytest.raises(ValueError, match="not synced"):
        ts.to_remote_us(t)
    for k in range(200):
        exchange(ts, t, rng.randint(100_000, 900_000), rng.randint(100_000, 900_000))
        t += 100_000_000
    assert ts.synced
    # asymmetric delays of up to 0.4 ms bias single samples by up to 0.4 ms; the line averages
    assert abs(ts.to_remote_ns(t) - remote(t)) < 200_000
    assert abs(ts.drift_ppm - 50.0) < 5.0
    assert abs(ts.offset_ns - (remote(t - 100_000_000) - (t - 100_000_000))) < 500_000
    # and back: a remote stamp maps to the local time it was taken at
    assert abs(ts.to_local_ns(remote(t) // 1000) - t) < 200_000
    assert ts.counters.accepted == MIN_SAMPLES - 1 + 200
    assert ts.last_status.synced and ts.last_status.samples == MIN_SAMPLES - 1 + 200


def test_long_round_trips_foreign_replies_and_a_clock_jump():
    ts = TimeSync()
    t = 0
    for _ in range(MIN_SAMPLES):
        exchange(ts, t, 200_000, 200_000)
        t += 100_000_000
    before = ts.offset_ns
    # a round trip over 10 ms is discarded, however good its offset (PX4's MAX_RTT_SAMPLE)
    exchange(ts, t, MAX_RTT_NS, 1000)
    assert ts.counters.rtt_too_long == 1 and ts.counters.accepted == MIN_SAMPLES
    # a reply to a request we never sent is another system's
    ts.handle(TimesyncFields(tc1=remote(t), ts1=t + 17), t + 400_000)
    assert ts.counters.not_ours == 1
    assert ts.offset_ns == before
    # the remote clock jumps by 5 s (a reboot): deviating samples are ignored, and after five
    # in a row the estimate starts again
    global OFFSET_NS
    saved = OFFSET_NS
    OFFSET_NS = saved - 5_000_000_000
    try:
        for k in range(MAX_CONSECUTIVE_DEVIATIONS - 1):
            t += 100_000_000
            exchange(ts, t, 200_000, 200_000)
            assert ts.synced and abs(ts.offset_ns - before) < 1_000_000
        t += 100_000_000
        exchange(ts, t, 200_000, 200_000)
        assert not ts.synced and ts.counters.resets == 1
        for _ in range(MIN_SAMPLES):
            t += 100_000_000
            exchange(ts, t, 200_000, 200_000)
        assert ts.synced and abs(ts.to_remote_ns(t) - remote(t)) < 50_000
    finally:
        OFFSET_NS = saved


def test_requests_are_answered_in_the_presented_clock():
    ts = TimeSync()
    answer = ts.handle(TimesyncFields(tc1=0, ts1=42), 5_000)
    assert answer == TimesyncFields(tc1=5_000, ts1=42)  # ours until synced
    t = 0
    for _ in range(MIN_SAMPLES):
        exchange(ts, t, 200_000, 200_000)
        t += 100_000_000
    answer = ts.handle(TimesyncFields(tc1=0, ts1=43), t)
    assert answer.ts1 == 43 and abs(answer.tc1 - remote(t)) < 50_000  # the autopilot's after
    msg = answer.encode()
    assert msg.get_type() == "TIMESYNC" and msg.tc1 == answer.tc1


def test_sync_with_a_udp_peer_offset_and_drifting():
    peer = ClockPeer(offset_s=123.456, drift_ppm=50.0)
    conn = link_to(peer)
    ts = TimeSync()
    try:
        sync(conn, ts)  # bounded in count and time; receive times taken on arrival
        assert ts.synced, ts.counters
        now = time.monotonic_ns()
        assert abs(ts.to_remote_us(now) - peer.clock_ns(now) // 1000) <= 2000
        assert abs(ts.offset_ns - OFFSET_NS) < 100_000_000  # the drift since t_ref adds a little
        assert ts.counters.accepted + ts.counters.rtt_too_long + ts.counters.not_ours <= ts.counters.replies
    finally:
        conn.close()
        peer.close()
