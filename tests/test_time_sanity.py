"""Time that cannot be: TIMESYNC replies beyond what clocks can do, and a burst of first IMU
messages, from a simulated flight controller over real UDP on 127.0.0.1
(tests/sim_autopilot.py) to the autopilot link and its IMU source.

Bounds (docs/autopilot.md, "Who the link listens to"): two clocks drift apart by at most
±1 000 ppm; a TIMESYNC sample is within half its round trip of the truth; an IMU message
arrives at most 1 s after its sample at the least.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np
import pytest

from ahrs_service.protocols.mavlink.autopilot_link import AutopilotLink
from ahrs_service.protocols.mavlink.imu_source import MavlinkImuSource
from ahrs_service.protocols.mavlink.timesync import TimeSync, TimesyncFields
from tests.test_autopilot import free_udp_port
from tests.test_source_identity import PERIOD_US, _read_all, _still

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sim_autopilot import SimAutopilot, UdpTransport, mavlink  # noqa: E402

pytestmark = pytest.mark.timeout(120)

#: the documented bound on how fast two clocks drift apart, ppm
MAX_DRIFT_PPM = 1000.0



class _BadTimesync(SimAutopilot):
    """The simulated autopilot, its TIMESYNC replies' ``tc1`` rewritten by ``tc1(now_ns, i)``
    (``i``: the reply's number); its IMU stamps untouched."""

    def __init__(self, *args, tc1, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.tc1 = tc1

    def send(self, msg) -> None:
        if msg.get_type() == "TIMESYNC" and msg.tc1 != 0:
            msg = mavlink.MAVLink_timesync_message(int(self.tc1(int(msg.tc1), self.stats.timesync_replies)), msg.ts1)
        super().send(msg)


class _BurstyStart(SimAutopilot):
    """The simulated autopilot whose first ``burst`` HIGHRES_IMU stamps are 100 µs apart (a
    queue flushed at the start, stamped when sent), the rest its samples' own."""

    def __init__(self, *args, burst: int = 16, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.burst = burst

    def _send_imu(self, i: int) -> None:
        t_us = self.sample_time_us(0) + 100 * i if i < self.burst else self.sample_time_us(i)
        g, a, m = self.rec.gyr[i], self.rec.acc[i], self.rec.mag_gauss[i]
        self.send(mavlink.MAVLink_highres_imu_message(
            t_us, *map(float, a), *map(float, g), *map(float, m), 1013.0, 0.0, 0.0, 25.0, 0x1FFF, 0))
        self.stats.imu_sent["HIGHRES_IMU"] = self.stats.imu_sent.get("HIGHRES_IMU", 0) + 1


def _stream(sim_cls, n: int, **options) -> tuple[MavlinkImuSource, list, list]:
    """(source, samples handed out, notices): the autopilot's IMU source on a real UDP link
    while ``sim_cls`` streams ``n`` samples; read until all came, or the sender finished and
    0.3 s passed quietly (bounded by 30 s)."""
    port = free_udp_port()
    src = MavlinkImuSource(AutopilotLink(f"udpin:127.0.0.1:{port}"), rate_hz=1e6 / PERIOD_US)
    src.open()
    sim = sim_cls(UdpTransport(port), _still(n), **options).start()
    try:
        got = _read_all(src, sim, n, seconds=30.0)
        src.read_block()  # the diagnostics as of the end
        notices = src.link.take_notices()
    finally:
        sim.stop()
        src.close()
    return src, got, notices


def test_timesync_replies_that_jump_1e15_ns_do_not_drop_the_imu_samples():
    """Before: TIMESYNC replies that jump by 1e15 ns (the IMU stamps do not) made every later
    sample out_of_order (5 010 of 6 800 dropped), nothing said why. The jump is refused, then
    taken as a new TIMESYNC clock (it persists), whose offset the IMU arrivals contradict:
    the samples keep the arrivals' mapping, every one is handed out, and it is reported."""
    n = 1000  # 5 s: TIMESYNC syncs, then its clock jumps after its 20th reply (2 s)

    def tc1(tc1_ns: int, i: int) -> int:
        return tc1_ns + (10**15 if i >= 20 else 0)

    src, got, notices = _stream(_BadTimesync, n, tc1=tc1)
    ts, tl = src.link.timesync, src.link.timeline
    assert len(got) + src.out_of_order == n and src.out_of_order < 5
    assert src.diagnostics.lost.total == 0
    assert ts.counters.implausible >= 5 and ts.counters.jumps >= 1
    assert tl.timesync_refused > 0
    t = np.array([s.t_ns for s in got])
    assert np.all(np.diff(t) > 0) and np.all(np.abs(np.diff(t) - PERIOD_US * 1000) < 2_000_000)
    texts = [text for _, text in notices]
    jumps = [float(m.group(1)) for x in texts for m in [re.search(r"TIMESYNC: the autopilot's clock jumped by "
                                                                   r"([-+][0-9.]+) s; estimate restarted", x)] if m]
    assert jumps and abs(jumps[0] - 1e6) < 0.01, texts  # 1e15 ns, within the round trips
    assert any("TIMESYNC's offset disagrees with the IMU messages' arrivals" in x for x in texts), texts


def test_a_frozen_timesync_clock_is_refused_and_the_samples_flow():
    """Before: a TIMESYNC peer whose clock is frozen was accepted (drift −1 000 000 ppm):
    58 % of the samples dropped, dt up to 213 ms. Its replies move by 100 ms per 100 ms: they
    are refused one by one (counted, reported once), never synced; the samples are mapped by
    their arrivals, every one handed out, evenly spaced."""
    n = 800
    frozen: list[int] = []

    def tc1(tc1_ns: int, i: int) -> int:
        frozen.append(tc1_ns) if not frozen else None
        return frozen[0]

    src, got, notices = _stream(_BadTimesync, n, tc1=tc1)
    ts = src.link.timesync
    assert len(got) == n and src.out_of_order == 0 and src.diagnostics.lost.total == 0
    assert not ts.synced and ts.counters.implausible >= 20 and ts.counters.jumps == 0
    assert abs(ts.drift_ppm) <= MAX_DRIFT_PPM
    dt = np.diff([s.t_ns for s in got])
    assert np.all(np.abs(dt - PERIOD_US * 1000) < 1_000_000), (dt.min(), dt.max())
    refused = [text for _, text in notices if "TIMESYNC replies refused" in text]
    assert len(refused) == 1 and "±1000 ppm" in refused[0]


def test_the_fitted_drift_never_exceeds_the_bound():
    """Five replies 0.1 s apart, each within the stamping jitter of the one before, whose
    offsets climb by 0.4 ms each: a line 4 000 ppm steep. The drift used is clamped to
    ±MAX_DRIFT_PPM (no clock drifts faster)."""
    ts = TimeSync()
    t = 10**9
    for k in range(5):
        req = ts.request(t)
        ts.handle(TimesyncFields(tc1=t + 100_000 + k * 400_000, ts1=req.ts1), t + 200_000)
        t += 100_000_000
    assert ts.synced and ts.counters.accepted == 5
    assert ts.drift_ppm == MAX_DRIFT_PPM


def test_a_burst_of_first_imu_messages_does_not_set_the_sample_period():
    """Before: 16 warm-up IMU messages stamped 100 µs apart locked the sample clock at
    3.38 ms instead of 5 ms: ~96 phantom lost samples a second for the whole run. The start
    waits for 0.25 s of the stream and takes the median spacing: 5 ms, no sample counted
    lost, the stream's spacing kept after the burst."""
    n = 600
    src, got, _ = _stream(_BurstyStart, n)
    assert src._clock is not None and abs(src._clock.rate_hz - 200.0) < 2.0
    assert src.diagnostics.lost.total == 0
    assert len(got) == n and src.out_of_order == 0
    dt = np.diff([s.t_ns for s in got[40:]])  # well after the burst (and the warm-up)
    assert np.all(np.abs(dt - PERIOD_US * 1000) < 100_000), (dt.min(), dt.max())
