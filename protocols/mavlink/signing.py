"""MAVLink 2 signing policy of the component (https://mavlink.io/en/guide/message_signing.html).

With a 32-byte key every outgoing message is signed. Incoming messages that would change
something on this component — :data:`SIGNED_ONLY` — are accepted only with a valid signature;
everything else (heartbeats, PARAM_REQUEST_LIST/READ) is accepted unsigned, so a ground
station without the key can still watch but not write.
"""

from __future__ import annotations

import hashlib

from ahrs_service.protocols.mavlink.dialect import message_id

KEY_LENGTH = 32

#: message ids accepted only with a valid signature when signing is on
SIGNED_ONLY: frozenset[int] = frozenset(
    mid for mid in (message_id(n) for n in ("PARAM_SET", "PARAM_EXT_SET", "COMMAND_LONG", "COMMAND_INT",
                                             "SETUP_SIGNING", "PARAM_MAP_RC"))
    if mid is not None
)


def key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte key MAVProxy's ``signing key <passphrase>`` derives: SHA-256 of the
    passphrase's bytes (MAVProxy takes ASCII passphrases; UTF-8 is the same for those)."""
    return hashlib.sha256(passphrase.encode("utf-8")).digest()


def check_key(key: bytes) -> bytes:
    """``key`` as bytes; ValueError unless it is exactly 32 bytes long."""
    key = bytes(key)
    if len(key) != KEY_LENGTH:
        raise ValueError(f"MAVLink signing key must be {KEY_LENGTH} bytes, got {len(key)}")
    return key
