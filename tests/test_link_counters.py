"""What the autopilot link counts as damage and what as a message of another dialect.

Over a real UDP socket on 127.0.0.1: the service's autopilot link (``udpin``) with the IMU
source on it, and a peer sending frames packed by pymavlink's ArduPilot dialect
(``ardupilotmega``): messages the service's ``common`` dialect does not define (AHRS2, as
ArduPilot streams), a frame of an id no dialect defines, and damaged frames. Only the damage is
bad data and dropped frames; the others are unknown messages, counted by id.
"""

from __future__ import annotations

import socket

import pytest
from pymavlink.dialects.v20 import ardupilotmega as apm

from ahrs_service.protocols.mavlink.autopilot_link import UNKNOWN_IDS_KEPT, UNKNOWN_IDS_REPORTED, AutopilotLink
from ahrs_service.protocols.mavlink.imu_source import MavlinkImuSource
from tests.test_autopilot import free_udp_port
from tests.test_source_identity import _wait

pytestmark = pytest.mark.timeout(60)

#: a message id that neither common nor ardupilotmega defines (MAVLink 2 ids go up to 2^24 - 1)
NO_DIALECT_ID = 0x00EEEE


def _frame_of_unlisted_id(seq: int, msg_id: int = NO_DIALECT_ID) -> bytes:
    """A well-formed MAVLink 2 frame of an id no dialect here defines (its CRC cannot be checked)."""
    payload = bytes(range(1, 9))
    header = bytes([0xFD, len(payload), 0, 0, seq & 0xFF, 1, 1, msg_id & 0xFF, msg_id >> 8 & 0xFF, msg_id >> 16 & 0xFF])
    crc = apm.x25crc(bytearray(header[1:] + payload) + b"\x00").crc
    return header + payload + crc.to_bytes(2, "little")


def _damaged(frame: bytes) -> bytes:
    """``frame`` with one payload byte flipped: its CRC fails."""
    damaged = bytearray(frame)
    damaged[12] ^= 0x5A
    return bytes(damaged)


def test_other_dialects_messages_are_counted_by_id_and_only_damage_is_bad_data():
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    source = MavlinkImuSource(link, message="highres", rate_hz=200.0)
    source.open()
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    packer = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        def send(frame: bytes) -> None:
            peer.sendto(frame, ("127.0.0.1", port))

        send(apm.MAVLink_heartbeat_message(apm.MAV_TYPE_QUADROTOR, apm.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                           0, 0, apm.MAV_STATE_STANDBY, 3).pack(packer))
        assert _wait(lambda: link.autopilot is not None, 10.0)
        ahrs2 = [apm.MAVLink_ahrs2_message(0.01 * k, 0.02, 1.5, 584.0, -353632610, 1491652300).pack(packer)
                 for k in range(6)]
        for frame in ahrs2[:5]:  # ArduPilot's own message, intact: unknown to common, not damage
            send(frame)
        send(_frame_of_unlisted_id(200))
        send(_frame_of_unlisted_id(201))
        send(_damaged(ahrs2[5]))  # ArduPilot's dialect knows its CRC: damage
        highres = apm.MAVLink_highres_imu_message(1_000_000, 0, 0, -9.81, 0, 0, 0, 0.2, 0, 0.4, 0, 0, 0, 25, 0).pack(packer)
        send(_damaged(highres))  # a message of our dialect, its CRC broken
        send(b"\x00\x11\x22" + apm.MAVLink_heartbeat_message(
            apm.MAV_TYPE_QUADROTOR, apm.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, apm.MAV_STATE_STANDBY, 3).pack(packer))
        stats = link.stats
        # one reader thread takes the datagrams in the order sent: the last one ends the lot
        assert _wait(lambda: stats.received.get("HEARTBEAT", 0) == 2, 10.0), stats.as_dict()
        source.read_block()  # the loop's call that brings the link's counters into the diagnostics
    finally:
        peer.close()
        source.close()
    # the two damaged frames and the bytes before the last HEARTBEAT, nothing else
    assert stats.bad_data == 3, stats.as_dict()
    assert stats.unknown_messages == 7
    assert stats.unknown == {str(apm.MAVLINK_MSG_ID_AHRS2): 5, str(NO_DIALECT_ID): 2}
    assert stats.messages == 2
    assert source.diagnostics.dropped_frames == 3
    assert source.diagnostics.extra["unknown_messages"] == 7
    assert link.status()["link"]["unknown"] == {"178": 5, str(NO_DIALECT_ID): 2}
    notices = [text for _, text in link.take_notices()]
    assert any("message id 178 (AHRS2 of ArduPilot's dialect)" in text for text in notices), notices
    assert any(f"message id {NO_DIALECT_ID} (in no dialect known here)" in text for text in notices), notices


def test_a_flood_of_unknown_ids_is_counted_in_bounded_memory_and_reported_a_few_times():
    port = free_udp_port()
    link = AutopilotLink(f"udpin:127.0.0.1:{port}")
    link.open()
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ids = [NO_DIALECT_ID + k for k in range(100)]
    try:
        for k, msg_id in enumerate(ids):
            peer.sendto(_frame_of_unlisted_id(k, msg_id), ("127.0.0.1", port))
        assert _wait(lambda: link.stats.unknown_messages == len(ids), 10.0), link.stats.unknown_messages
    finally:
        peer.close()
        link.close()
    assert link.stats.bad_data == 0
    assert len(link.stats.unknown) == UNKNOWN_IDS_KEPT
    assert list(link.stats.unknown) == [str(i) for i in ids[:UNKNOWN_IDS_KEPT]]
    assert len(link.take_notices()) == UNKNOWN_IDS_REPORTED
