"""The serial link budget beside an autopilot: bytes per frame × rate against the baud rate.

A MAVLink 2 frame is a 10-byte header (STX, payload length, incompat and compat flags,
sequence, system, component, 3-byte message id), the payload, a 2-byte CRC and, on a signed
link, a 13-byte signature (link id, 6-byte timestamp, 6-byte signature). MAVLink 2 drops the
payload's trailing zero bytes, so the full payload (extensions included) is the worst case
used here. A UART sends 10 bits per byte (8N1: start, 8 data, stop), so a link carries
baud / 10 bytes per second.

``python -m ahrs_service.protocols.mavlink.link_budget`` prints the table of docs/autopilot.md
(tests/test_link_budget.py checks the frame sizes against frames pymavlink packs).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from ahrs_service.protocols.mavlink.dialect import mavlink

HEADER_BYTES = mavlink.HEADER_LEN_V2  # 10: STX, len, incompat, compat, seq, sysid, compid, msgid (3)
CRC_BYTES = 2
SIGNATURE_BYTES = mavlink.MAVLINK_SIGNATURE_BLOCK_LEN  # 13: link id (1), timestamp (6), signature (6)
BITS_PER_BYTE = 10  # 8N1 framing on a UART


def payload_bytes(name: str) -> int:
    """The full payload of message ``name`` (extension fields included), bytes."""
    cls = getattr(mavlink, f"MAVLink_{name.lower()}_message")
    return int(cls.unpacker.size)


def frame_bytes(name: str, *, signed: bool = False) -> int:
    """Bytes on the wire of one MAVLink 2 frame of ``name`` (untruncated payload)."""
    return HEADER_BYTES + payload_bytes(name) + CRC_BYTES + (SIGNATURE_BYTES if signed else 0)


@dataclass(frozen=True)
class Stream:
    """One message stream in one direction: ``name`` at ``rate_hz`` (``count`` messages per
    period, e.g. three NAMED_VALUE_FLOATs)."""

    direction: str  # "autopilot → companion" or "companion → autopilot"
    name: str
    rate_hz: float
    count: int = 1

    def bytes_per_s(self, signed: bool = False) -> float:
        return frame_bytes(self.name, signed=signed) * self.rate_hz * self.count


#: what flows beside an autopilot with source.type = "mavlink": the IMU stream at the rates
#: the autopilots offer, and what the service sends back (defaults of the configuration)
STREAMS: tuple[Stream, ...] = (
    Stream("autopilot → companion", "HIGHRES_IMU", 200.0),
    Stream("autopilot → companion", "HIGHRES_IMU", 500.0),
    Stream("autopilot → companion", "HIGHRES_IMU", 1000.0),
    Stream("autopilot → companion", "SCALED_IMU", 200.0),
    Stream("autopilot → companion", "RAW_IMU", 200.0),
    Stream("autopilot → companion", "ATTITUDE_QUATERNION", 50.0),
    Stream("autopilot → companion", "HEARTBEAT", 1.0),
    Stream("autopilot → companion", "TIMESYNC", 10.0),
    Stream("companion → autopilot", "ODOMETRY", 30.0),
    Stream("companion → autopilot", "ATTITUDE", 50.0),
    Stream("companion → autopilot", "ATTITUDE_QUATERNION", 50.0),
    Stream("companion → autopilot", "NAMED_VALUE_FLOAT", 5.0, count=3),
    Stream("companion → autopilot", "TIMESYNC", 10.0),
    Stream("companion → autopilot", "SYS_STATUS", 1.0),
    Stream("companion → autopilot", "HEARTBEAT", 1.0),
)

BAUDS = (921_600, 57_600)


def share(stream: Stream, baud: int, signed: bool = False) -> float:
    """The fraction of a ``baud`` UART (one direction) that ``stream`` takes."""
    return stream.bytes_per_s(signed) * BITS_PER_BYTE / baud


def table(signed: bool = False) -> str:
    """The link-budget table (Markdown) for :data:`STREAMS` at :data:`BAUDS`."""
    head = ["direction", "message", "Hz", "bytes/frame", "bytes/s"] + [f"% of {b} baud" for b in BAUDS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in STREAMS:
        n = f"{s.count} × " if s.count > 1 else ""
        cells = [s.direction, f"{n}{s.name}", f"{s.rate_hz:g}", str(frame_bytes(s.name, signed=signed)),
                 f"{s.bytes_per_s(signed):.0f}"] + [f"{100 * share(s, b, signed):.1f}" for b in BAUDS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    signed = "--signed" in argv
    print(f"MAVLink 2 frames{' (signed)' if signed else ''}, {BITS_PER_BYTE} bits per byte on the UART")
    print(table(signed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
