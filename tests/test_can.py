"""DroneCAN input: framing, reassembly, decoding, fault counting and the simulated node.

Everything runs over real python-can buses: the ``virtual`` interface inside this process,
and ``udp_multicast`` between two processes in a private network namespace.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
import threading
import uuid

import can
import dronecan
import numpy as np
import pytest

from ahrs_service.core.sample_clock import SensorClockMap
from ahrs_service.core.samples import ACC_SATURATED, ACC_VALID, GYR_SATURATED, GYR_VALID, MAG_NEW, MAG_VALID
from ahrs_service.protocols.dronecan import messages as dc
from ahrs_service.protocols.dronecan.imu_source import DroneCanConfig, DroneCanImuSource
from ahrs_service.protocols.dronecan.sim_node import SimulatedDroneCanImuNode

F16_RTOL = 2.0**-11  # float16 keeps 11 significant bits: half an ulp relative error at most
EPOCH_US = 5_000_000  # the simulated node's clock reads 5 s at simulation time 0


class ManualNs:
    """Host clock for the source, in ns, moved by hand."""

    def __init__(self, t_ns: int = 10**12) -> None:
        self.t = t_ns

    def __call__(self) -> int:
        return self.t


class RampImu:
    """Stand-in board: readings that differ at every t, so each sample is recognisable."""

    def __init__(self) -> None:
        from ahrs_service.drivers.sim.clock import ManualClock

        self.clock = ManualClock()

    def physics(self, t: float) -> dict:
        return {
            "gyr": np.array([0.1 + 0.5 * t, -0.2, 0.3 - 0.25 * t]),
            "acc": np.array([0.5, -0.3 + t, -9.7]),
            "mag": np.array([21.0 + 2.0 * t, -3.0, 44.0]),
            "temperature_c": 25.0,
        }


@pytest.fixture
def buses():
    """Two ends of one python-can virtual bus (unique channel per test)."""
    ch = f"ahrs-test-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=ch)
    rx = can.Bus(interface="virtual", channel=ch)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


def make(buses, **src_cfg):
    tx, rx = buses
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(**src_cfg), bus=rx, clock_ns=clock)
    src.open()
    return tx, src, clock


def raw_imu_msg(usec, gyr, acc, covariance=()):
    m = dronecan.uavcan.equipment.ahrs.RawIMU()
    m.timestamp.usec = usec
    m.integration_interval = -1.0
    m.rate_gyro_latest = [float(v) for v in gyr]
    m.accelerometer_latest = [float(v) for v in acc]
    m.covariance = [float(v) for v in covariance]
    return m


def send_all(bus, frames):
    for f in frames:
        bus.send(f)


def read_all(src):
    """Every pending sample, oldest first: ``read`` until None, as the service does."""
    return list(iter(src.read, None))


# ------------------------------------------------------------------------ protocol level


def test_can_id_layout():
    cid = dc.build_message_id(dc.RAW_IMU_ID, 42, priority=20)
    assert cid == (20 << 24) | (1003 << 8) | 42
    assert dc.parse_can_id(cid) == dc.CanId(20, 1003, 42, False)
    # the reference implementation agrees on the layout
    frames = dc.encode_message(raw_imu_msg(1, (0, 0, 0), (0, 0, -9.81)), 42, 3, priority=20)
    assert {f.arbitration_id for f in frames} == {cid}
    assert all(f.is_extended_id for f in frames)
    svc = dc.parse_can_id((16 << 24) | (11 << 16) | (1 << 15) | (7 << 8) | 0x80 | 5)
    assert svc.service and svc.data_type_id == 11 and svc.source_node_id == 5
    with pytest.raises(ValueError):
        dc.build_message_id(1003, 0)
    with pytest.raises(ValueError):
        dc.build_message_id(1003, 128)


def test_fast_encoder_and_decoder_match_dronecan():
    rng = np.random.default_rng(7)
    seed = dc.transfer_crc_seed(dc.RAW_IMU_ID)
    for i in range(40):
        usec = int(rng.integers(1, 2**50))
        gyr, acc = rng.normal(0, 3, 3), rng.normal(0, 15, 3)
        ref = dc.encode_message(raw_imu_msg(usec, gyr, acc), 42, i)
        fast = dc.transfer_frames(dc.build_message_id(dc.RAW_IMU_ID, 42), dc.pack_raw_imu(usec, gyr, acc), i, seed)
        assert [bytes(f.data) for f in fast] == [bytes(f.data) for f in ref]
        r = dc.TransferReassembler()
        done = [r.push(f.arbitration_id, f.data, 0) for f in ref]
        assert done[:-1] == [None] * (len(ref) - 1)
        tr = done[-1]
        usec2, gyr2, acc2 = dc.unpack_raw_imu(tr.payload)
        msg = dc.decode_payload(dc.RAW_IMU_ID, tr.payload)  # the slow reference decoder
        assert usec2 == usec == msg.timestamp.usec
        assert list(gyr2) == list(msg.rate_gyro_latest)
        assert list(acc2) == list(msg.accelerometer_latest)
        np.testing.assert_allclose(gyr2, gyr, rtol=F16_RTOL, atol=1e-7)
    m2 = dronecan.uavcan.equipment.ahrs.MagneticFieldStrength2(sensor_id=3, magnetic_field_ga=[0.21, -0.03, 0.44])
    (ref,) = dc.encode_message(m2, 42, 9)
    (fast,) = dc.transfer_frames(dc.build_message_id(dc.MAG2_ID, 42), dc.pack_mag2(3, (0.21, -0.03, 0.44)), 9)
    assert bytes(fast.data) == bytes(ref.data)
    # out-of-range values saturate as the DSDL "saturated float16" cast mode demands
    _, g, _ = dc.unpack_raw_imu(dc.pack_raw_imu(1, (1e6, -1e6, 0.0), (0, 0, 0)))
    assert g[:2] == (65504.0, -65504.0)


def test_reassembler_interleaved_long_transfers_and_faults():
    seed = dc.transfer_crc_seed(dc.RAW_IMU_ID)
    a = dc.encode_message(raw_imu_msg(111, (0.1, 0.2, 0.3), (1, 2, 3), covariance=range(36)), 10, 4)
    b = dc.encode_message(raw_imu_msg(222, (-0.1, -0.2, -0.3), (4, 5, 6)), 11, 4)
    assert len(a) > 16 and len(b) == 7  # 36 covariance entries make a long transfer
    r = dc.TransferReassembler(timeout_s=1.0)
    out = []
    for i in range(max(len(a), len(b))):  # two nodes' transfers interleaved frame by frame
        for frames in (a, b):
            if i < len(frames):
                tr = r.push(frames[i].arbitration_id, frames[i].data, i)
                if tr is not None:
                    out.append(tr)
    assert sorted((t.source_node_id, dc.unpack_raw_imu(t.payload)[0]) for t in out) == [(10, 111), (11, 222)]
    cov = list(dc.decode_payload(dc.RAW_IMU_ID, next(t for t in out if t.source_node_id == 10).payload).covariance)
    assert cov == [float(v) for v in range(36)]
    assert r.stats.transfers == 2 and r.stats.dropped_frames == 0

    # CRC error: one payload bit flipped
    bad = [can.Message(arbitration_id=f.arbitration_id, is_extended_id=True, data=bytes(f.data)) for f in b]
    bad[3].data = bytes([bad[3].data[0] ^ 1]) + bytes(bad[3].data[1:])
    assert [r.push(f.arbitration_id, f.data, 0) for f in bad] == [None] * 7
    assert r.stats.crc_errors == 1 and r.stats.dropped_frames == 7
    # a missing middle frame: toggle error, counted once, all its frames dropped
    assert all(r.push(f.arbitration_id, f.data, 0) is None for i, f in enumerate(b) if i != 3)
    assert r.stats.out_of_order == 1 and r.stats.dropped_frames == 7 + 6
    # continuation frames of a transfer whose start was never seen
    assert all(r.push(f.arbitration_id, f.data, 0) is None for f in b[2:])
    assert r.stats.out_of_order == 2 and r.stats.dropped_frames == 13 + 5
    # a transfer that never ends: dropped once its timeout has passed
    for f in b[:4]:
        r.push(f.arbitration_id, f.data, 0)
    assert r.open_transfers == 1
    assert r.expire(500_000_000) == 0
    assert r.expire(1_000_000_001) == 1
    assert r.stats.incomplete == 1 and r.open_transfers == 0
    # a malformed first frame (toggle set) and an empty frame
    assert r.push(b[0].arbitration_id, bytes(b[0].data[:-1]) + bytes([b[0].data[-1] | 0x20]), 0) is None
    assert r.push(b[0].arbitration_id, b"", 0) is None
    assert r.stats.malformed == 2
    # after all of that a clean transfer still goes through
    good = dc.transfer_frames(b[0].arbitration_id, dc.pack_raw_imu(333, (0, 0, 0), (0, 0, -9.81)), 5, seed)
    res = [r.push(f.arbitration_id, f.data, 2_000_000_000) for f in good]
    assert dc.unpack_raw_imu(res[-1].payload)[0] == 333
    assert r.stats.transfers == 3


# --------------------------------------------------------------------------- the source


def test_round_trip_values_flags_and_sensor_time(buses):
    tx, src, clock = make(buses, node_id=42)
    imu = RampImu()
    node = SimulatedDroneCanImuNode(tx, imu, node_id=42, rate_hz=100, mag_rate_hz=25, sensor_epoch_us=EPOCH_US)
    got = []
    for k in range(12):
        t = k / 100
        node.step(t)
        # host receive times jitter by up to 3 ms; the sample times must not
        clock.t = 10**12 + int(t * 1e9) + (0, 3_000_000, 1_000_000)[k % 3]
        s = src.read()
        assert s is not None
        assert src.read() is None  # never delivered twice
        got.append(s)
    for k, s in enumerate(got):
        ph = imu.physics(k / 100)
        np.testing.assert_allclose(s.gyr, ph["gyr"], rtol=F16_RTOL, atol=1e-6)
        np.testing.assert_allclose(s.acc, ph["acc"], rtol=F16_RTOL, atol=1e-6)
        mag_t = (k // 4) * 4 / 100  # the mag runs at a quarter of the IMU rate
        np.testing.assert_allclose(s.mag, imu.physics(mag_t)["mag"], rtol=F16_RTOL, atol=1e-4)
        assert s.flags & (GYR_VALID | ACC_VALID | MAG_VALID) == GYR_VALID | ACC_VALID | MAG_VALID
        assert bool(s.flags & MAG_NEW) == (k % 4 == 0)
        assert s.raw["sensor_time_us"] == EPOCH_US + round(k * 1e4)
        assert s.raw["node_id"] == 42
    steps = np.diff([s.t_ns for s in got])
    # the node's 10 ms sample spacing, despite 1-3 ms receive jitter (the offset estimate only
    # rises by a thousandth of the excess latency per sample)
    np.testing.assert_allclose(steps, 10_000_000, atol=5_000)
    assert src.diagnostics.samples == 12
    assert src.diagnostics.dropped_frames == 0


def test_deprecated_mag_message_and_read_all(buses):
    tx, src, clock = make(buses, node_id=7)
    m = dronecan.uavcan.equipment.ahrs.MagneticFieldStrength(magnetic_field_ga=[0.2, 0.05, -0.4])
    send_all(tx, dc.encode_message(m, 7, 0))
    for k in range(3):
        send_all(tx, dc.encode_message(raw_imu_msg(1000 + 2000 * k, (0.01 * k, 0, 0), (0, 0, -9.81)), 7, k))
    samples = read_all(src)
    assert [s.raw["sensor_time_us"] for s in samples] == [1000, 3000, 5000]
    assert [bool(s.flags & MAG_NEW) for s in samples] == [True, False, False]
    np.testing.assert_allclose(samples[2].mag, [20.0, 5.0, -40.0], rtol=F16_RTOL)
    assert samples[2].t_ns - samples[0].t_ns == 4_000_000


def test_read_returns_backlog_oldest_first_and_flags_fresh_mag(buses):
    tx, src, clock = make(buses, node_id=42)
    assert src.may_have_backlog
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=50)
    node.step(0.05)  # six RawIMU and three mag transfers queued before the first read
    s = src.read()
    assert s.raw["sensor_time_us"] == node.sensor_epoch_us
    assert s.flags & MAG_NEW
    rest = read_all(src)
    assert [s.raw["sensor_time_us"] - node.sensor_epoch_us for s in rest] == [10_000, 20_000, 30_000, 40_000, 50_000]
    assert [bool(s.flags & MAG_NEW) for s in rest] == [False, True, False, True, False]
    assert src.diagnostics.extra["superseded_samples"] == 0
    assert src.read() is None


def test_pending_overflow_drops_oldest(buses):
    tx, src, clock = make(buses, node_id=42, max_pending_samples=4)
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=0)
    node.step(0.05)  # six samples for room for four
    assert src.read().raw["sensor_time_us"] - node.sensor_epoch_us == 20_000
    node.step(0.07)  # two more arrive while three wait: one more overflow
    got = [s.raw["sensor_time_us"] - node.sensor_epoch_us for s in read_all(src)]
    assert got == [40_000, 50_000, 60_000, 70_000]
    assert src.diagnostics.extra["superseded_samples"] == 3
    assert src.diagnostics.samples == 5


def test_node_filter_counts_foreign_frames(buses):
    tx, src, clock = make(buses, node_id=42)
    imu = RampImu()
    other = SimulatedDroneCanImuNode(tx, imu, node_id=43, rate_hz=100, mag_rate_hz=100)
    mine = SimulatedDroneCanImuNode(tx, imu, node_id=42, rate_hz=100, mag_rate_hz=0)
    other.step(0.0)
    mine.step(0.0)
    s = src.read()
    assert s.raw["node_id"] == 42
    assert s.mag is None and not s.flags & MAG_VALID  # node 43's magnetometer is not ours
    d = src.diagnostics
    assert d.extra["foreign_frames"] == 7 + 1  # one RawIMU (7 frames) + one mag frame from 43
    assert d.dropped_frames == 8
    # NodeStatus and other traffic on a shared bus is no fault
    tx.send(can.Message(arbitration_id=dc.build_message_id(dc.NODE_STATUS_ID, 43), data=bytes(8)))
    # a GetNodeInfo (service 1) request from node 43 to node 42: a service frame, not IMU data
    tx.send(can.Message(arbitration_id=(30 << 24) | (1 << 16) | (1 << 15) | (42 << 8) | 0x80 | 43, data=b"\xc0"))
    assert src.read() is None and d.dropped_frames == 8


def test_locks_onto_first_node_and_separate_mag_node(buses):
    tx, src, clock = make(buses, mag_node_id=20)
    imu = RampImu()
    first = SimulatedDroneCanImuNode(tx, imu, node_id=30, rate_hz=100, mag_rate_hz=0)
    second = SimulatedDroneCanImuNode(tx, imu, node_id=31, rate_hz=100, mag_rate_hz=0)
    compass = SimulatedDroneCanImuNode(tx, imu, node_id=20, rate_hz=1, mag_rate_hz=1)
    first.step(0.0)
    second.step(0.0)
    m = dronecan.uavcan.equipment.ahrs.MagneticFieldStrength2(sensor_id=0, magnetic_field_ga=[0.1, 0.2, 0.3])
    send_all(tx, dc.encode_message(m, 20, 0))
    first.step(0.01)
    samples = read_all(src)
    assert src.node_id == 30
    assert [s.raw["node_id"] for s in samples] == [30, 30]
    np.testing.assert_allclose(samples[1].mag, [10.0, 20.0, 30.0], rtol=F16_RTOL)
    assert src.diagnostics.extra["foreign_frames"] == 7
    del compass


def test_faults_are_dropped_counted_and_survived(buses):
    tx, src, clock = make(buses, node_id=42, transfer_timeout_s=0.2)
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=0)
    delivered = []

    def step(k, fault=None):
        if fault:
            node.inject(fault)
        node.step(k / 100)
        s = src.read()
        if s is not None:
            delivered.append(s.raw["sensor_time_us"] - node.sensor_epoch_us)

    step(0)
    step(1, "corrupt")
    step(2, "drop_middle")
    step(3, "swap_middle")
    step(4, "foreign")
    step(5)
    d = src.diagnostics
    assert delivered == [0, 40_000, 50_000]  # 10, 20, 30 ms lost; 40 ms arrives, its foreign twin not
    assert d.extra["crc_errors"] == 1
    assert d.extra["out_of_order_transfers"] == 2
    assert d.extra["foreign_frames"] == 7
    assert d.dropped_frames == 7 + 6 + 7 + 7
    assert node.injected == {"corrupt": 1, "drop_middle": 1, "swap_middle": 1, "foreign": 1}

    # a transfer cut off after three frames: incomplete once the timeout has passed
    frames = dc.transfer_frames(
        dc.build_message_id(dc.RAW_IMU_ID, 42), dc.pack_raw_imu(9_999_999, (0, 0, 0), (0, 0, 0)), 17,
        dc.transfer_crc_seed(dc.RAW_IMU_ID),
    )
    send_all(tx, frames[:3])
    assert src.read() is None and d.incomplete_transfers == 0
    clock.t += 300_000_000
    assert src.read() is None and d.incomplete_transfers == 1

    # malformed frames: standard id, remote frame, a RawIMU too short to decode
    tx.send(can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01"))
    tx.send(can.Message(arbitration_id=dc.build_message_id(dc.RAW_IMU_ID, 42), is_remote_frame=True))
    send_all(tx, dc.transfer_frames(dc.build_message_id(dc.RAW_IMU_ID, 42), b"\x01\x02\x03", 3))
    assert src.read() is None
    assert d.extra["malformed_frames"] == 3
    # and the stream goes on
    step(6)
    assert delivered[-1] == 60_000
    assert d.samples == 4


def test_periodic_and_repeated_fault_injection(buses):
    tx, src, clock = make(buses, node_id=42)
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=0, faults={"corrupt": 3})
    node.inject("drop_middle", count=2)
    got = []
    for k in range(9):
        node.step(k / 100)
        got += [s.raw["sensor_time_us"] - node.sensor_epoch_us for s in read_all(src)]
    # transfers 0 and 1 lose a middle frame, every third (2, 5, 8) is corrupted
    assert got == [30_000, 40_000, 60_000, 70_000]
    assert node.injected["drop_middle"] == 2 and node.injected["corrupt"] == 3
    assert src.diagnostics.extra["out_of_order_transfers"] == 2
    assert src.diagnostics.extra["crc_errors"] == 3
    assert src.diagnostics.dropped_frames == 2 * 6 + 3 * 7


def test_node_status_once_a_second(buses):
    tx, rx = buses
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=10, mag_rate_hz=0, node_status=True)
    for k in range(26):
        node.step(k / 10)
    status = []
    for _ in range(1000):  # bounded drain of what the node sent
        msg = rx.recv(timeout=0)
        if msg is None:
            break
        cid = dc.parse_can_id(msg.arbitration_id)
        if cid.data_type_id == dc.NODE_STATUS_ID:
            assert cid.source_node_id == 42
            status.append(dc.decode_payload(dc.NODE_STATUS_ID, bytes(msg.data[:-1])).uptime_sec)
    assert status == [1, 2, 3]  # at t = 0, 1, 2 s; the node clock starts at 1 s


def test_duplicate_and_stale_transfers_not_delivered_twice(buses):
    tx, src, clock = make(buses, node_id=42)
    frames = dc.encode_message(raw_imu_msg(2_000_000, (0.1, 0, 0), (0, 0, -9.81)), 42, 1)
    send_all(tx, frames)
    assert src.read() is not None
    send_all(tx, dc.encode_message(raw_imu_msg(2_000_000, (0.1, 0, 0), (0, 0, -9.81)), 42, 2))
    send_all(tx, dc.encode_message(raw_imu_msg(1_999_000, (0.1, 0, 0), (0, 0, -9.81)), 42, 3))
    assert src.read() is None
    assert src.diagnostics.extra["stale_samples"] == 2
    # a node reboot (silent longer than stream_silence_s, then its clock far back) is accepted
    # and restarts the time mapping
    clock.t += 1_500_000_000
    send_all(tx, dc.encode_message(raw_imu_msg(1_000, (0.1, 0, 0), (0, 0, -9.81)), 42, 4))
    s = src.read()
    assert s is not None and s.raw["sensor_time_us"] == 1_000
    assert src.diagnostics.extra["sensor_clock_resets"] == 1


def test_sensor_clock_map_follows_minimum_latency():
    cm = SensorClockMap(rise_fraction=0.01)
    host0 = 7_000_000_000
    assert cm.map(1_000, host0 + 1_000_000 + 2_000_000) == host0 + 1_000_000 + 2_000_000
    # a lower-latency sample moves the offset down at once
    assert cm.map(2_000, host0 + 2_000_000 + 500_000) == host0 + 2_000_000 + 500_000
    # a late sample moves it up by 1 % of the excess only
    t = cm.map(3_000, host0 + 3_000_000 + 10_500_000)
    assert t == host0 + 3_000_000 + 500_000 + 100_000


class FailingBus(can.BusABC):
    """A bus whose receive fails the way a bus-off or unplugged adapter does."""

    def __init__(self, exc: Exception) -> None:
        super().__init__(channel="failing")
        self.exc = exc
        self.shut = False

    def _recv_internal(self, timeout):
        raise self.exc

    def send(self, msg, timeout=None):
        raise self.exc

    def shutdown(self):
        self.shut = True
        super().shutdown()


def test_bus_error_recovery_reopens_with_backoff(buses):
    tx, rx = buses
    made = []
    plan = [FailingBus(can.CanError("bus-off")), OSError("adapter unplugged"), rx]

    def factory():
        item = plan.pop(0)
        made.append(item)
        if isinstance(item, Exception):
            raise item
        return item

    clock = ManualNs()
    src = DroneCanImuSource(
        DroneCanConfig(node_id=42, reopen_backoff_s=0.1, reopen_backoff_max_s=1.0), bus=factory, clock_ns=clock
    )
    src.open()
    d = src.diagnostics
    assert src.read() is None  # recv raised: counted, not raised
    assert d.bus_errors == 1 and d.device_lost and "bus-off" in d.last_error
    assert made[0].shut
    clock.t += 50_000_000
    assert src.read() is None and len(made) == 1  # still backing off
    clock.t += 60_000_000
    assert src.read() is None and len(made) == 2  # reopen attempt failed: a retry
    assert d.retries == 1 and "unplugged" in d.last_error and d.device_lost
    clock.t += 150_000_000
    assert src.read() is None and len(made) == 2  # backoff doubled to 0.2 s
    clock.t += 100_000_000
    node = SimulatedDroneCanImuNode(tx, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=0)
    node.step(0.0)
    s = src.read()
    assert s is not None and len(made) == 3
    assert d.reinitialisations == 1 and not d.device_lost and d.bus_errors == 1
    src.close()


def test_reopen_after_fault_clears_device_lost_and_backoff():
    bus = FailingBus(can.CanError("bus-off"))
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(reopen_backoff_s=0.1), bus=bus, clock_ns=clock)
    src.open()
    d = src.diagnostics
    assert src.read() is None and d.device_lost  # a fault: the back-off doubles to 0.2 s
    src.close()
    src.open()
    assert not d.device_lost
    assert src.read() is None and d.bus_errors == 2 and d.device_lost
    clock.t += 100_000_000  # the back-off started over at 0.1 s
    assert src.read() is None and d.reinitialisations == 1
    src.close()
    bus.shutdown()


def test_given_bus_error_is_retried_on_same_bus():
    bus = FailingBus(OSError("ENETDOWN"))
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(reopen_backoff_s=0.01), bus=bus, clock_ns=clock)
    src.open()
    for i in range(3):
        assert src.read() is None
        clock.t += 1_000_000_000
    assert src.diagnostics.bus_errors == 3
    assert src.diagnostics.reinitialisations == 2
    assert not bus.shut  # the caller owns a bus object it passed in
    src.close()
    bus.shutdown()


def test_config_from_mapping_and_open_errors():
    ch = f"ahrs-test-{uuid.uuid4().hex}"
    src = DroneCanImuSource({"interface": "virtual", "channel": ch, "node_id": 5})
    with src:
        assert src.read() is None
        peer = can.Bus(interface="virtual", channel=ch)
        try:
            send_all(peer, dc.encode_message(raw_imu_msg(10, (0, 0, 0), (0, 0, -9.81)), 5, 0))
            assert src.read().raw["sensor_time_us"] == 10
        finally:
            peer.shutdown()
    with pytest.raises(ValueError, match="bitrat"):
        DroneCanConfig.from_mapping({"bitrat": 500000})
    bad = DroneCanImuSource({"interface": "no-such-interface", "channel": "x"})
    with pytest.raises(OSError, match="no-such-interface"):
        bad.open()


def test_negate_acc_option(buses):
    tx, src, clock = make(buses, node_id=42, negate_acc=True)
    send_all(tx, dc.encode_message(raw_imu_msg(10, (0, 0, 0), (0.5, 0, 9.81)), 42, 0))
    np.testing.assert_allclose(src.read().acc, [-0.5, 0, -9.81], rtol=F16_RTOL)


def test_node_thread_starts_and_stops(buses):
    from ahrs_service.drivers.sim.clock import MonotonicClock

    tx, rx = buses
    imu = RampImu()
    imu.clock = MonotonicClock()
    node = SimulatedDroneCanImuNode(tx, imu, node_id=42, rate_hz=200, mag_rate_hz=20, node_status=True)
    src = DroneCanImuSource(DroneCanConfig(node_id=42), bus=rx)
    src.open()
    got = []
    pause = threading.Event()
    node.start(duration_s=5.0)
    try:
        # bounded in count and time; how many arrive depends on the machine, not asserted
        for _ in range(2000):
            got += read_all(src)
            if len(got) >= 5 or not node.running:
                break
            pause.wait(0.005)
    finally:
        assert node.stop(timeout_s=5.0)
    assert not node.running
    assert len(got) >= 1
    assert all(np.diff([s.t_ns for s in got]) > 0)
    assert src.diagnostics.dropped_frames == 0


def test_end_to_end_madgwick_reproduces_simulator_truth(buses):
    pytest.importorskip("ahrs_service.drivers.sim.imu", reason="drivers/sim not available")
    from analytic import error_deg

    from ahrs_service import estimators
    from ahrs_service.drivers.sim.imu import ManualClock, SimulatedImu
    from ahrs_service.drivers.sim.motion import profile

    rate, mag_rate = 100, 50
    sim_clock = ManualClock()
    imu = SimulatedImu(profile("validation", hold=1.0, move=1.0), clock=sim_clock)
    tx, rx = buses
    node = SimulatedDroneCanImuNode(tx, imu, node_id=42, rate_hz=rate, mag_rate_hz=mag_rate)
    host = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(node_id=42), bus=rx, clock_ns=host)
    src.open()
    n = int(imu.trajectory.duration * rate)
    samples, truth = [], []
    for k in range(n):
        t = k / rate
        sim_clock.set(t)
        node.step(t)
        host.t = 10**12 + int(t * 1e9) + 2_000_000
        s = src.read()
        assert s is not None
        samples.append(s)
        truth.append(imu.physics(t)["truth"].q)
    assert src.diagnostics.samples == n and src.diagnostics.dropped_frames == 0
    gyr = np.array([s.gyr for s in samples])
    acc = np.array([s.acc for s in samples])
    mag = np.array([s.mag for s in samples])
    ts = np.array([s.t_ns for s in samples]) * 1e-9
    np.testing.assert_allclose(np.diff(ts), 1 / rate, atol=1e-6)
    q_can = estimators.run("madgwick", gyr, acc, mag, timestamps=ts)
    # the same filter on the simulator's float64 readings, magnetometer held as on the bus
    ph = [imu.physics(k / rate) for k in range(n)]
    hold = rate // mag_rate
    q_ref = estimators.run(
        "madgwick",
        np.array([p["gyr"] for p in ph]),
        np.array([p["acc"] for p in ph]),
        np.array([ph[(k // hold) * hold]["mag"] for k in range(n)]),
        rate_hz=rate,
    )
    settle = 2 * rate  # the filter starts at identity; skip its convergence
    via_can, _, _ = error_deg(q_can, q_ref)
    to_truth, _, _ = error_deg(q_can[settle:], np.array(truth)[settle:])
    ref_truth, _, _ = error_deg(q_ref[settle:], np.array(truth)[settle:])
    assert via_can.max() < 0.5  # float16 transport changes the estimate by a fraction of a degree
    assert to_truth.max() < 3.0  # Madgwick's own lag in the 90°/s turns, not the transport
    assert abs(to_truth.mean() - ref_truth.mean()) < 0.05


# ------------------------------------------------------------------ across two processes

_RX = """
import json, sys, time
from ahrs_service.protocols.dronecan.imu_source import DroneCanImuSource
src = DroneCanImuSource({{"interface": "udp_multicast", "channel": "{group}", "node_id": 42}})
src.open()
open("{ready}", "w").close()
got = []
deadline = time.monotonic() + 15
while len(got) < {n} and time.monotonic() < deadline:
    got += [[s.t_ns, s.raw["sensor_time_us"], list(s.gyr), list(s.acc), s.mag is not None]
            for s in iter(src.read, None)]
    time.sleep(0.001)
src.close()
print(json.dumps({{"samples": got, "diag": src.diagnostics.as_dict()}}))
"""

_TX = """
import os, sys, time
import can
sys.path.insert(0, "{tests}")
from test_can import RampImu
from ahrs_service.protocols.dronecan.sim_node import SimulatedDroneCanImuNode
deadline = time.monotonic() + 15
while not os.path.exists("{ready}") and time.monotonic() < deadline:
    time.sleep(0.01)
bus = can.Bus(interface="udp_multicast", channel="{group}")
node = SimulatedDroneCanImuNode(bus, RampImu(), node_id=42, rate_hz=100, mag_rate_hz=25)
for k in range({n}):
    node.step(k / 100)
    time.sleep(0.002)  # let the receiver keep up: a socket buffer is not a CAN controller
bus.shutdown()
"""


def _netns_unavailable() -> str | None:
    try:
        import msgpack  # noqa: F401  (python-can's udp_multicast interface needs it)
    except ImportError:
        return "python-can udp_multicast needs msgpack (pip install 'python-can[udp_multicast]')"
    if not shutil.which("unshare") or not shutil.which("ip"):
        return "unshare/ip not available"
    probe = subprocess.run(
        ["unshare", "-rn", "sh", "-c", "ip link set lo up && ip route add 224.0.0.0/4 dev lo"],
        capture_output=True, timeout=20,
    )
    if probe.returncode != 0:
        return f"cannot create a private network namespace: {probe.stderr.decode().strip()[:200]}"
    return None


def test_cross_process_udp_multicast_in_network_namespace(tmp_path):
    reason = _netns_unavailable()
    if reason:
        pytest.skip(reason)
    from pathlib import Path

    n = 60
    group = "239.74.163.2"
    ready = tmp_path / "rx-ready"
    fmt = dict(group=group, ready=ready, n=n, tests=Path(__file__).parent)
    (tmp_path / "rx.py").write_text(textwrap.dedent(_RX.format(**fmt)))
    (tmp_path / "tx.py").write_text(textwrap.dedent(_TX.format(**fmt)))
    py = sys.executable
    script = (
        "ip link set lo up && ip route add 224.0.0.0/4 dev lo && "
        f"({py} {tmp_path}/rx.py > {tmp_path}/rx.json & {py} {tmp_path}/tx.py; wait)"
    )
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")  # leave no __pycache__ in the repo
    res = subprocess.run(
        ["unshare", "-rn", "sh", "-c", script], capture_output=True, timeout=60, cwd=tmp_path, env=env
    )
    assert res.returncode == 0, res.stderr.decode()[-2000:]
    out = json.loads((tmp_path / "rx.json").read_text())
    samples = out["samples"]
    assert len(samples) >= n // 2, out["diag"]  # loopback multicast may lose a frame; never most
    assert out["diag"]["crc_errors"] == 0 and out["diag"]["foreign_frames"] == 0
    imu = RampImu()
    epoch = 1_000_000  # the node's default sensor_epoch_us
    for t_ns, usec, gyr, acc, _ in samples:
        t = (usec - epoch) / 1e6
        np.testing.assert_allclose(gyr, imu.physics(t)["gyr"], rtol=F16_RTOL, atol=1e-6)
        np.testing.assert_allclose(acc, imu.physics(t)["acc"], rtol=F16_RTOL, atol=1e-6)
    assert all(np.diff([s[0] for s in samples]) > 0)
    assert all(np.diff([s[1] for s in samples]) > 0)
    assert samples[-1][4]  # the magnetometer arrived too


def test_service_reads_can_sources_until_empty():
    """A CAN source hands out every sample in order: the service must drain it each tick."""
    from ahrs_service import config as config_mod
    from ahrs_service.sources import make_source

    for kind in ("can", "simulated_can"):
        cfg = config_mod.validate({"source": {"type": kind, "can_interface": "virtual"}})
        assert make_source(cfg.source, 200.0).may_have_backlog, kind


def test_float16_readings_beyond_any_imu_range_are_saturated_not_estimated(buses):
    """Issue 14 probe (14d): a node sending 65504 rad/s (float16's largest) or NaN: the reading
    is marked saturated (or invalid) and counted, never valid for the estimator
    (drivers.base.MAX_READING)."""
    tx, src, clock = make(buses, node_id=42)
    cid = dc.build_message_id(dc.RAW_IMU_ID, 42)
    readings = [((0.1, 0.0, 0.0), (0.0, 0.0, -9.8)), ((65504.0, 0.0, 0.0), (0.0, 0.0, -9.8)),
                ((0.1, 0.0, 0.0), (0.0, -60000.0, -9.8)), ((math.nan, 0.0, 0.0), (0.0, 0.0, -9.8)),
                ((-60.0, 60.0, 0.0), (300.0, 0.0, -9.8))]  # the last: fast but physical (3400 °/s, 31 g)
    got = []
    for k, (gyr, acc) in enumerate(readings):
        clock.t += 10_000_000
        send_all(tx, dc.transfer_frames(cid, dc.pack_raw_imu(EPOCH_US + k * 10_000, gyr, acc), k,
                                        dc.transfer_crc_seed(dc.RAW_IMU_ID)))
        got.append(src.read())
    flags = [s.flags & (GYR_VALID | ACC_VALID | GYR_SATURATED | ACC_SATURATED) for s in got]
    assert flags == [GYR_VALID | ACC_VALID, GYR_SATURATED | ACC_VALID, GYR_VALID | ACC_SATURATED, ACC_VALID,
                     GYR_VALID | ACC_VALID]
    assert src.diagnostics.saturated == 2 and src.diagnostics.non_finite == 1
