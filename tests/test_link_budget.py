"""The link budget's frame sizes are those of frames pymavlink packs (MAVLink 2, signed and not)."""

from __future__ import annotations

from pymavlink.dialects.v20 import common as mavlink2

from ahrs_service.protocols.mavlink import link_budget


#: a value without zero bytes per field type (MAVLink 2 drops the payload's trailing zeros)
_NO_ZERO_BYTES = {"int8_t": 1, "uint8_t": 1, "int16_t": 0x0101, "uint16_t": 0x0101, "int32_t": 0x01010101,
                  "uint32_t": 0x01010101, "int64_t": 0x0101010101010101, "uint64_t": 0x0101010101010101,
                  "float": 1.0, "double": 1.0}


def _full(name: str):
    """A message of ``name`` with no zero byte in any field (so MAVLink 2 truncates nothing)."""
    cls = getattr(mavlink2, f"MAVLink_{name.lower()}_message")
    # array_lengths follows the wire order (ordered_fieldnames); the constructor takes fieldnames
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    args = []
    for field, kind in zip(cls.fieldnames, cls.fieldtypes):
        length = lengths[field]
        if kind == "char":
            args.append(b"x" * max(1, length))
        elif length:
            args.append([_NO_ZERO_BYTES[kind]] * length)
        else:
            args.append(_NO_ZERO_BYTES[kind])
    return cls(*args)


def test_frame_sizes_match_packed_frames():
    plain = mavlink2.MAVLink(None, srcSystem=1, srcComponent=200)
    signed = mavlink2.MAVLink(None, srcSystem=1, srcComponent=200)
    signed.signing.secret_key = bytes(range(32))
    signed.signing.sign_outgoing = True
    signed.signing.timestamp = 1
    for name in {s.name for s in link_budget.STREAMS}:
        assert len(_full(name).pack(plain)) == link_budget.frame_bytes(name), name
        assert len(_full(name).pack(signed)) == link_budget.frame_bytes(name, signed=True), name


def test_shares_at_the_two_baud_rates():
    hr = link_budget.Stream("autopilot → companion", "HIGHRES_IMU", 200.0)
    # 75 bytes × 200 Hz × 10 bits = 150 kbit/s: 16 % of 921 600 baud, 2.6 times 57 600 baud
    assert link_budget.frame_bytes("HIGHRES_IMU") == 75
    assert abs(link_budget.share(hr, 921_600) - 150_000 / 921_600) < 1e-12
    assert link_budget.share(hr, 57_600) > 1.0
    assert "| companion → autopilot | ODOMETRY | 30 | 245 |" in link_budget.table()
