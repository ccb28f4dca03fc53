"""DroneCAN source identity: which node feeds the IMU, and a second sender with its node id.

Simulated nodes publish on a real python-can virtual bus; the source reads the other end.
"""

from __future__ import annotations

import logging
import uuid

import can
import numpy as np
import pytest

from ahrs_service.core.samples import MAG_VALID
from ahrs_service.protocols.dronecan.imu_source import DroneCanConfig, DroneCanImuSource
from ahrs_service.protocols.dronecan.sim_node import SimulatedDroneCanImuNode

from tests.test_can import ManualNs

F16_RTOL = 2.0**-11
RATE_HZ = 100
G = 9.81


class StillImu:
    """A vehicle at rest, rolled by ``roll_rad``; a field of its own so a node can be recognised."""

    def __init__(self, roll_rad: float = 0.0, field_ut: tuple[float, float, float] = (20.0, 0.0, 40.0)) -> None:
        self.acc = np.array([0.0, G * np.sin(roll_rad), -G * np.cos(roll_rad)])
        self.field = np.array(field_ut)

    def physics(self, t: float) -> dict:
        return {"gyr": np.zeros(3), "acc": self.acc, "mag": self.field}


@pytest.fixture
def buses():
    ch = f"ahrs-test-{uuid.uuid4().hex}"
    tx = can.Bus(interface="virtual", channel=ch)
    rx = can.Bus(interface="virtual", channel=ch)
    yield tx, rx
    tx.shutdown()
    rx.shutdown()


def test_a_compass_node_speaking_first_does_not_take_the_imu_place(buses):
    """``can_node_id`` unset: the IMU node is the first node sending RawIMU, not the compass
    that spoke first; the field is the IMU node's own, the compass's frames are foreign."""
    tx, rx = buses
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(), bus=rx, clock_ns=clock)
    src.open()
    compass = SimulatedDroneCanImuNode(tx, StillImu(field_ut=(-30.0, 10.0, 25.0)), node_id=10, rate_hz=RATE_HZ,
                                       mag_rate_hz=RATE_HZ, publish_imu=False)
    imu = SimulatedDroneCanImuNode(tx, StillImu(), node_id=20, rate_hz=RATE_HZ, mag_rate_hz=RATE_HZ / 2)
    n = 50
    got = []
    for k in range(n):
        t = k / RATE_HZ
        compass.step(t)  # the compass speaks first, every time
        imu.step(t)
        clock.t = 10**12 + int(t * 1e9)
        got += list(iter(src.read, None))
    assert src.node_id == 20
    assert len(got) == n and src.diagnostics.samples == n
    assert {s.raw["node_id"] for s in got} == {20}
    assert all(s.flags & MAG_VALID for s in got)  # the IMU node's field from its very first sample
    np.testing.assert_allclose([s.mag for s in got], np.tile([20.0, 0.0, 40.0], (n, 1)), rtol=F16_RTOL)
    # every compass frame after the IMU node was known: one MagneticFieldStrength2 frame each
    assert src.diagnostics.extra["foreign_frames"] == n - 1
    assert src.diagnostics.extra["node_id_conflicts"] == 0


@pytest.mark.parametrize("node_id", [42, None], ids=["configured", "first-sending-rawimu"])
@pytest.mark.parametrize(
    "second",
    [
        # (its clock's reading at the first sender's t = 0 in s, its rate, when it joins in s)
        (11.0, RATE_HZ, 0.0),  # a clock 10 s ahead (a node booted 10 s earlier), same rate
        (-9.0, RATE_HZ, 0.0),  # a clock 10 s behind: its timestamps go back
        (1.003, 2 * RATE_HZ, 0.5),  # 3 ms apart at twice the rate, joining later
    ],
    ids=["clock-ahead", "clock-behind", "twice-the-rate"],
)
def test_a_second_sender_with_the_node_id_is_reported_once_and_not_merged(buses, caplog, node_id, second):
    """Two nodes with node id 42 — the first still and level, the second rolled 30°: the
    delivered stream is the first's alone (its values, its 10 ms steps), the second's samples
    are dropped and counted, and the conflict is reported once."""
    epoch_offset_s, rate_b, joins_s = second
    tx, rx = buses
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(node_id=node_id), bus=rx, clock_ns=clock)
    src.open()
    epoch_a_us = 10_000_000
    first = SimulatedDroneCanImuNode(tx, StillImu(), node_id=42, rate_hz=RATE_HZ, mag_rate_hz=0,
                                     sensor_epoch_us=epoch_a_us)
    other = SimulatedDroneCanImuNode(tx, StillImu(roll_rad=np.radians(30.0)), node_id=42, rate_hz=rate_b,
                                     mag_rate_hz=0, sensor_epoch_us=epoch_a_us + int(epoch_offset_s * 1e6))
    n = 200
    got = []
    with caplog.at_level(logging.WARNING, logger="ahrs_service.protocols.dronecan.imu_source"):
        for k in range(n):
            t = k / RATE_HZ
            first.step(t)
            if t >= joins_s:
                other.step(t - joins_s)
            clock.t = 10**12 + int(t * 1e9) + 1_000_000
            got += list(iter(src.read, None))
    e = src.diagnostics.extra
    assert len(got) == n
    np.testing.assert_allclose([s.acc for s in got], np.tile([0.0, 0.0, -G], (n, 1)), rtol=F16_RTOL, atol=1e-6)
    assert np.all(np.diff([s.raw["sensor_time_us"] for s in got]) == 1_000_000 // RATE_HZ)
    assert np.all(np.diff([s.t_ns for s in got]) == 1_000_000_000 // RATE_HZ)
    assert e["node_id_conflicts"] == 1
    assert e["conflict_samples"] == other.sent_transfers
    assert e["conflict_samples_delivered"] == 0
    warnings = [r for r in caplog.records if "second sender" in r.getMessage()]
    assert len(warnings) == 1 and "node 42" in warnings[0].getMessage()
    assert "second sender" in src.diagnostics.last_error


def test_a_reboot_without_a_pause_is_taken_after_three_periods_not_as_a_conflict(buses):
    """The node's clock and transfer ids start again at once: after three of its periods alone
    the new sequence is the node's stream; nothing is reported as a second sender."""
    tx, rx = buses
    clock = ManualNs()
    src = DroneCanImuSource(DroneCanConfig(node_id=42), bus=rx, clock_ns=clock)
    src.open()
    before = SimulatedDroneCanImuNode(tx, StillImu(), node_id=42, rate_hz=RATE_HZ, mag_rate_hz=0,
                                      sensor_epoch_us=50_000_000)
    after = SimulatedDroneCanImuNode(tx, StillImu(), node_id=42, rate_hz=RATE_HZ, mag_rate_hz=0,
                                     sensor_epoch_us=1_000)
    got = []
    for k in range(30):
        t = k / RATE_HZ
        if k < 10:
            before.step(t)
        else:
            after.step(t - 0.1)
        clock.t = 10**12 + int(t * 1e9)
        got += list(iter(src.read, None))
    times = [s.raw["sensor_time_us"] for s in got]
    assert times[:10] == [50_000_000 + 10_000 * k for k in range(10)]
    assert times[10:] == [1_000 + 10_000 * j for j in range(3, 20)]  # three held, then the new stream
    e = src.diagnostics.extra
    assert e["node_restarts"] == 1 and e["node_id_conflicts"] == 0
    assert e["stale_samples"] == 3 and e["sensor_clock_resets"] == 1
    assert np.all(np.diff([s.t_ns for s in got]) > 0)
