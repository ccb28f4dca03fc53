"""DroneCAN (UAVCAN v0) on classic CAN: CAN ids, transfer framing and the IMU message payloads.

The ``dronecan`` package supplies the message definitions and the reference encoder
(:func:`encode_message` uses ``dronecan.transport.Transfer.to_frames``). The receive side is
written here because the service reads up to 1 kHz: ``Transfer.from_frames`` unpacks through
bit strings (≈0.7 ms per RawIMU), while :class:`TransferReassembler` plus the ``struct``
decoders below take a few microseconds. The tests check both against each other.

29-bit CAN id of a message frame (DroneCAN spec, "CAN bus transport layer")::

    bits 28..24 priority (0 highest … 31)
    bits 23..8  message data type id (16 bit)
    bit  7      service-not-message (0 here)
    bits 6..0   source node id (0 = anonymous, single-frame only)

Every frame ends with a tail byte: start-of-transfer (0x80), end-of-transfer (0x40),
toggle (0x20, 0 on the first frame and alternating), transfer id (0x1F). A transfer longer
than 7 bytes is split over several frames and prefixed with a CRC-16-CCITT of the payload,
seeded with the data type signature's CRC (``base_crc``).
"""

from __future__ import annotations

import binascii
import math
import struct
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import can
import dronecan
from dronecan import transport

#: message data type ids used by the IMU input
RAW_IMU_ID = 1003  # uavcan.equipment.ahrs.RawIMU
MAG2_ID = 1002  # uavcan.equipment.ahrs.MagneticFieldStrength2 (Gauss)
MAG_ID = 1001  # uavcan.equipment.ahrs.MagneticFieldStrength (deprecated, Gauss)
NODE_STATUS_ID = 341  # uavcan.protocol.NodeStatus

#: µT per Gauss; DroneCAN magnetometer messages carry Gauss because float16 cannot hold µT well
GAUSS_TO_UT = 100.0

DEFAULT_PRIORITY = 16  # "medium" in the DroneCAN priority table (0 highest … 31 lowest)

_FRAME_PAYLOAD = 7  # classic CAN: 8 data bytes minus the tail byte
_MAX_TRANSFER_BYTES = 1024  # longer than any DroneCAN message we accept; bounds memory per session


# --------------------------------------------------------------------------------- CAN ids


@dataclass(frozen=True, slots=True)
class CanId:
    """The fields of a DroneCAN message frame's 29-bit CAN id."""

    priority: int
    data_type_id: int
    source_node_id: int
    service: bool = False


def build_message_id(data_type_id: int, source_node_id: int, priority: int = DEFAULT_PRIORITY) -> int:
    """29-bit CAN id of a (non-anonymous) message frame; node id 1…127, data type id 0…65535."""
    if not 1 <= source_node_id <= 127:
        raise ValueError(f"source node id {source_node_id} outside 1..127")
    if not 0 <= data_type_id <= 0xFFFF:
        raise ValueError(f"message data type id {data_type_id} outside 0..65535")
    if not 0 <= priority <= 31:
        raise ValueError(f"priority {priority} outside 0..31")
    return (priority << 24) | (data_type_id << 8) | source_node_id


def parse_can_id(can_id: int) -> CanId:
    """Splits a 29-bit CAN id. For service frames ``data_type_id`` is the 8-bit service id;
    for anonymous messages (node 0) only the 2 low bits of the data type id are on the bus."""
    priority = (can_id >> 24) & 0x1F
    source = can_id & 0x7F
    if can_id & 0x80:
        return CanId(priority, (can_id >> 16) & 0xFF, source, True)
    if source == 0:
        return CanId(priority, (can_id >> 8) & 0x3, 0)
    return CanId(priority, (can_id >> 8) & 0xFFFF, source)


# ------------------------------------------------------------------------------------ CRC


def crc16(data: bytes | bytearray, initial: int) -> int:
    """CRC-16-CCITT (poly 0x1021, no reflection) as DroneCAN uses for multi-frame transfers:
    the standard library's ``binascii.crc_hqx`` (C, ~25× the table loop in Python)."""
    return binascii.crc_hqx(data, initial)


@lru_cache(maxsize=256)
def transfer_crc_seed(data_type_id: int, service: bool = False) -> int | None:
    """The CRC seed (``base_crc`` of the data type signature) of a known data type, else None."""
    kind = dronecan.dsdl.CompoundType.KIND_SERVICE if service else dronecan.dsdl.CompoundType.KIND_MESSAGE
    dtype = dronecan.DATATYPES.get((data_type_id, kind))
    return None if dtype is None else int(dtype.base_crc)


# -------------------------------------------------------------------------------- encoding


def encode_message(
    message: Any, source_node_id: int, transfer_id: int, priority: int = DEFAULT_PRIORITY
) -> list[can.Message]:
    """python-can frames (extended ids, classic CAN) of one DroneCAN message transfer.

    ``message`` is a ``dronecan`` message object, e.g. ``dronecan.uavcan.equipment.ahrs.RawIMU()``.
    ``transfer_id`` is taken modulo 32. Uses the reference ``Transfer.to_frames``.
    """
    t = transport.Transfer(
        transfer_id=transfer_id & 0x1F,
        source_node_id=source_node_id,
        payload=message,
        transfer_priority=priority,
    )
    return [
        can.Message(arbitration_id=f.message_id, is_extended_id=True, data=bytes(f.bytes))
        for f in t.to_frames()
    ]


def decode_payload(data_type_id: int, payload: bytes) -> Any:
    """A ``dronecan`` message object from a reassembled payload (general, slow path: tools, tests).

    Raises ``ValueError`` for unknown data types or payloads that do not unpack.
    """
    dtype = dronecan.DATATYPES.get((data_type_id, dronecan.dsdl.CompoundType.KIND_MESSAGE))
    if dtype is None:
        raise ValueError(f"unknown DroneCAN message type {data_type_id}")
    msg = dtype()
    try:
        msg._unpack(transport.bits_from_bytes(bytearray(payload)), True)  # noqa: SLF001 (dronecan API)
    except Exception as exc:  # dronecan raises assorted errors on short data
        raise ValueError(f"cannot unpack {dtype.full_name}: {exc}") from exc
    return msg


def transfer_frames(can_id: int, payload: bytes, transfer_id: int, crc_seed: int | None = None) -> list[can.Message]:
    """Frames of one transfer (classic CAN), the same bytes ``Transfer.to_frames`` produces.

    ``crc_seed`` (the data type's ``base_crc``, see :func:`transfer_crc_seed`) is needed when
    the payload does not fit one frame (more than 7 bytes).
    """
    tid = transfer_id & 0x1F
    if len(payload) <= _FRAME_PAYLOAD:
        return [can.Message(arbitration_id=can_id, is_extended_id=True, data=bytes(payload) + bytes((0xC0 | tid,)))]
    if crc_seed is None:
        raise ValueError("a multi-frame transfer needs the data type's CRC seed")
    crc = crc16(payload, crc_seed)
    rest = bytes((crc & 0xFF, crc >> 8)) + bytes(payload)
    out = []
    toggle = 0
    for i in range(0, len(rest), _FRAME_PAYLOAD):
        chunk = rest[i : i + _FRAME_PAYLOAD]
        tail = (0x80 if i == 0 else 0) | (0x40 if i + _FRAME_PAYLOAD >= len(rest) else 0) | toggle | tid
        out.append(can.Message(arbitration_id=can_id, is_extended_id=True, data=chunk + bytes((tail,))))
        toggle ^= 0x20
    return out


# ------------------------------------------------------------------ fast payload decoders

# All fields of these messages are byte aligned, so DroneCAN's little-endian bit packing equals
# plain little-endian struct packing. The trailing covariance arrays (tail array optimisation,
# no length prefix) are not needed and are ignored.
_RAW_IMU = struct.Struct("<f3e3f3e3f")  # after the 7-byte uint56 timestamp
RAW_IMU_MIN_BYTES = 7 + _RAW_IMU.size  # 47
_MAG2 = struct.Struct("<B3e")
_MAG = struct.Struct("<3e")


def unpack_raw_imu(payload: bytes | bytearray) -> tuple[int, tuple[float, float, float], tuple[float, float, float]]:
    """(timestamp µs, rate_gyro_latest rad/s, accelerometer_latest m/s²) of a RawIMU payload.

    Axes are the node's body frame as the DSDL defines it: x forward, y right, z down (FRD).
    A timestamp of 0 means the node does not know the time. Raises ``ValueError`` when short.
    """
    if len(payload) < RAW_IMU_MIN_BYTES:
        raise ValueError(f"RawIMU payload of {len(payload)} bytes, need {RAW_IMU_MIN_BYTES}")
    usec = int.from_bytes(payload[:7], "little")
    v = _RAW_IMU.unpack_from(payload, 7)
    return usec, (v[1], v[2], v[3]), (v[7], v[8], v[9])


def unpack_mag2(payload: bytes | bytearray) -> tuple[int, tuple[float, float, float]]:
    """(sensor_id, field in Gauss, body axes) of a MagneticFieldStrength2 payload."""
    if len(payload) < _MAG2.size:
        raise ValueError(f"MagneticFieldStrength2 payload of {len(payload)} bytes, need {_MAG2.size}")
    sid, x, y, z = _MAG2.unpack_from(payload)
    return sid, (x, y, z)


def unpack_mag(payload: bytes | bytearray) -> tuple[float, float, float]:
    """Field in Gauss (body axes) of a deprecated MagneticFieldStrength payload."""
    if len(payload) < _MAG.size:
        raise ValueError(f"MagneticFieldStrength payload of {len(payload)} bytes, need {_MAG.size}")
    return _MAG.unpack_from(payload)


_F16_MAX = 65504.0


def _f16(v: float) -> float:
    # DSDL float16 fields are "saturated": out-of-range values clamp (NaN passes through)
    return v if -_F16_MAX <= v <= _F16_MAX or v != v else math.copysign(_F16_MAX, v)


def pack_raw_imu(
    usec: int, gyr: Sequence[float], acc: Sequence[float], integration_interval: float = -1.0
) -> bytes:
    """RawIMU payload with the latest samples only (integrals zero, no covariance).

    usec: node time, µs (uint56). gyr rad/s, acc m/s², body FRD. The fast encoder of the
    simulated node; the tests check it against the ``dronecan`` reference encoder.
    """
    return (usec & 0xFFFFFFFFFFFFFF).to_bytes(7, "little") + _RAW_IMU.pack(
        integration_interval,
        _f16(gyr[0]), _f16(gyr[1]), _f16(gyr[2]),
        0.0, 0.0, 0.0,
        _f16(acc[0]), _f16(acc[1]), _f16(acc[2]),
        0.0, 0.0, 0.0,
    )


def pack_mag2(sensor_id: int, field_ga: Sequence[float]) -> bytes:
    """MagneticFieldStrength2 payload without covariance; field in Gauss, body FRD."""
    return _MAG2.pack(sensor_id & 0xFF, _f16(field_ga[0]), _f16(field_ga[1]), _f16(field_ga[2]))


# ---------------------------------------------------------------------------- reassembly


@dataclass(slots=True)
class Transfer:
    """A complete, CRC-checked transfer: ``payload`` without CRC and tail bytes.

    ``t_ns`` is the host time (ns) at which its first frame was pushed.
    """

    source_node_id: int
    data_type_id: int
    transfer_id: int
    priority: int
    payload: bytes
    t_ns: int


@dataclass
class ReassemblerStats:
    """Counters of a :class:`TransferReassembler`.

    ``dropped_frames`` counts every frame that did not end in a delivered transfer; the others
    count transfers (or orphan runs of frames) once each, by cause.
    """

    frames: int = 0
    transfers: int = 0
    dropped_frames: int = 0
    malformed: int = 0  # empty frame, bad tail bits on a first frame, too short, too long, unknown type
    out_of_order: int = 0  # toggle error, or frames of a transfer whose start was not seen
    crc_errors: int = 0
    incomplete: int = 0  # started but never ended: timed out, or superseded by a new start


class _Session:
    __slots__ = ("tid", "toggle", "start_ns", "crc", "seed", "buf", "frames", "priority")

    def __init__(self, tid: int, start_ns: int, crc: int, seed: int, buf: bytearray, priority: int) -> None:
        self.tid = tid
        self.toggle = 0x20  # the second frame carries toggle 1
        self.start_ns = start_ns
        self.crc = crc
        self.seed = seed
        self.buf = buf
        self.frames = 1
        self.priority = priority


class TransferReassembler:
    """Turns message frames into complete transfers; every faulty frame is dropped and counted.

    One session per (source node, data type): DroneCAN allows a node one transfer of a type in
    flight at a time, and the 5-bit transfer id ties a frame to it. A continuation frame whose
    transfer id does not match, whose toggle bit is wrong, or whose start was never seen is
    dropped (``out_of_order``, once per broken transfer); a transfer still open
    ``timeout_s`` after its first frame, or restarted by a new first frame, is ``incomplete``;
    a multi-frame transfer whose CRC does not match is dropped (``crc_errors``).
    Service frames and anonymous multi-frame transfers are not expected here and count as
    malformed.
    """

    def __init__(self, timeout_s: float = 0.5) -> None:
        self.timeout_ns = int(timeout_s * 1e9)
        self.stats = ReassemblerStats()
        self._sessions: dict[int, _Session] = {}
        # key -> transfer id already reported broken, so its remaining frames count only as frames
        self._broken: dict[int, int] = {}

    def push(self, can_id: int, data: bytes | bytearray, now_ns: int) -> Transfer | None:
        """Feeds one frame (29-bit id, data with tail byte); returns a transfer when one completes."""
        st = self.stats
        st.frames += 1
        n = len(data)
        if n == 0 or can_id & 0x80:
            st.malformed += 1
            st.dropped_frames += 1
            return None
        tail = data[n - 1]
        tid = tail & 0x1F
        key = can_id & 0xFFFFFF  # priority is not part of a session's identity
        if tail & 0x80:  # start of transfer
            if tail & 0x20:  # the first frame's toggle bit must be 0
                st.malformed += 1
                st.dropped_frames += 1
                return None
            old = self._sessions.pop(key, None)
            if old is not None:
                st.incomplete += 1
                st.dropped_frames += old.frames
            self._broken.pop(key, None)
            source = can_id & 0x7F
            dtid = (can_id >> 8) & 0xFFFF
            if tail & 0x40:  # single-frame transfer: no CRC
                st.transfers += 1
                return Transfer(source, dtid, tid, (can_id >> 24) & 0x1F, bytes(data[: n - 1]), now_ns)
            seed = transfer_crc_seed(dtid) if source else None
            if n < 4 or seed is None:
                st.malformed += 1
                st.dropped_frames += 1
                return None
            self._sessions[key] = _Session(
                tid, now_ns, data[0] | (data[1] << 8), seed, bytearray(data[2 : n - 1]), (can_id >> 24) & 0x1F
            )
            return None

        s = self._sessions.get(key)
        if s is not None and now_ns - s.start_ns > self.timeout_ns:
            del self._sessions[key]
            st.incomplete += 1
            st.dropped_frames += s.frames
            self._broken[key] = s.tid
            s = None
        if s is None or s.tid != tid or (tail & 0x20) != s.toggle:
            st.dropped_frames += 1
            if s is not None and s.tid == tid:  # toggle error inside a live transfer
                del self._sessions[key]
                st.dropped_frames += s.frames
            elif s is not None:
                return None  # a stray frame of another transfer id; the live one may still finish
            if self._broken.get(key) != tid:
                st.out_of_order += 1
                self._broken[key] = tid
            if tail & 0x40:  # that transfer is over: a later one with the same id is a new fault
                del self._broken[key]
            return None
        s.buf += data[: n - 1]
        s.frames += 1
        s.toggle ^= 0x20
        if len(s.buf) > _MAX_TRANSFER_BYTES:
            del self._sessions[key]
            st.malformed += 1
            st.dropped_frames += s.frames
            self._broken[key] = tid
            return None
        if not tail & 0x40:
            return None
        del self._sessions[key]
        if crc16(s.buf, s.seed) != s.crc:
            st.crc_errors += 1
            st.dropped_frames += s.frames
            return None
        st.transfers += 1
        return Transfer(can_id & 0x7F, (can_id >> 8) & 0xFFFF, tid, s.priority, bytes(s.buf), s.start_ns)

    def expire(self, now_ns: int) -> int:
        """Drops transfers open longer than the timeout; returns how many (also in ``incomplete``)."""
        stale = [k for k, s in self._sessions.items() if now_ns - s.start_ns > self.timeout_ns]
        for k in stale:
            s = self._sessions.pop(k)
            self.stats.incomplete += 1
            self.stats.dropped_frames += s.frames
            self._broken[k] = s.tid
        return len(stale)

    def reset(self) -> int:
        """Forgets all open transfers (e.g. after the bus was reopened); they count as incomplete."""
        n = len(self._sessions)
        for s in self._sessions.values():
            self.stats.dropped_frames += s.frames
        self.stats.incomplete += n
        self._sessions.clear()
        self._broken.clear()
        return n

    def discard(self, data_type_ids: Collection[int], keep_sources: Collection[int]) -> int:
        """Forgets the open transfers of ``data_type_ids`` from every node not in ``keep_sources``
        (nodes found not to be the ones listened to); returns their frames, counted as dropped
        but not as incomplete transfers."""
        gone = [k for k in self._sessions if (k >> 8) & 0xFFFF in data_type_ids and k & 0x7F not in keep_sources]
        frames = 0
        for k in gone:
            frames += self._sessions.pop(k).frames
            self._broken.pop(k, None)
        self.stats.dropped_frames += frames
        return frames

    @property
    def open_transfers(self) -> int:
        """Number of transfers currently being reassembled."""
        return len(self._sessions)


__all__ = [
    "CanId",
    "DEFAULT_PRIORITY",
    "GAUSS_TO_UT",
    "MAG2_ID",
    "MAG_ID",
    "NODE_STATUS_ID",
    "RAW_IMU_ID",
    "RAW_IMU_MIN_BYTES",
    "ReassemblerStats",
    "Transfer",
    "TransferReassembler",
    "build_message_id",
    "crc16",
    "decode_payload",
    "encode_message",
    "pack_mag2",
    "pack_raw_imu",
    "transfer_frames",
    "parse_can_id",
    "transfer_crc_seed",
    "unpack_mag",
    "unpack_mag2",
    "unpack_raw_imu",
]
