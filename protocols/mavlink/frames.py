"""MAVLink 2 frames packed straight from a payload, for the streams sent many times a second.

pymavlink builds a message object per send, then a header object, then the frame byte by
byte in Python, most of a 100 Hz attitude stream's cost. A
:class:`PackedMessage` holds the payload already packed with the message class's own
``struct`` layout and frames it with one header ``struct`` call and one CRC call — the same
bytes pymavlink sends (MAVLink 2, trailing zero bytes of the payload trimmed, CRC-16/MCRF4XX
with the message's CRC_EXTRA), which a test checks byte for byte.

Unsigned links only: on a signed link the component sends pymavlink's own message objects,
which sign themselves.
"""

from __future__ import annotations

import struct
from typing import Any

from ahrs_service.protocols.mavlink.dialect import mavlink

_HEADER = struct.Struct("<BBBBBBBHB")  # STX, len, incompat, compat, seq, sysid, compid, msgid (24 bit)
_CRC = struct.Struct("<H")
_STX_V2 = 253


class PackedMessage:
    """One message of pymavlink class ``msg_class`` whose payload is already packed.

    Duck-types the two methods a link's sender uses: ``get_type()`` (the message name) and
    ``pack(mav)`` (the wire frame with ``mav``'s sequence number and system/component ids;
    the caller advances ``mav.seq`` as it does for pymavlink messages).
    """

    __slots__ = ("msg_class", "payload")

    def __init__(self, msg_class: Any, payload: bytes) -> None:
        self.msg_class = msg_class
        self.payload = payload

    def get_type(self) -> str:
        return self.msg_class.msgname

    def pack(self, mav: "mavlink.MAVLink") -> bytes:
        if mav.signing.sign_outgoing:
            raise RuntimeError("a signed link needs pymavlink's message objects, which sign themselves")
        # MAVLink 2 drops the payload's trailing zero bytes, keeping at least one
        payload = self.payload.rstrip(b"\0") or self.payload[:1]
        msg_id = self.msg_class.id
        header = _HEADER.pack(
            _STX_V2, len(payload), 0, 0, mav.seq, mav.srcSystem, mav.srcComponent, msg_id & 0xFFFF, msg_id >> 16
        )
        body = header[1:] + payload  # the CRC covers everything after STX, then CRC_EXTRA
        crc = mavlink.x25crc(body + bytes((self.msg_class.crc_extra,))).crc
        return header[:1] + body + _CRC.pack(crc)
