"""Secrets kept out of everything the service writes down: flight logs, replays, the journal.

A configuration key whose name says it holds a secret (:func:`is_secret_key`: the MAVLink
``signing_key``, a ``token``, a ``password`` …, at any depth) is written as
:data:`REDACTED` wherever a configuration is recorded (``/config`` of a flight log or of a
replay, see docs/logs.md); an empty value stays empty, so a log still tells "signing off"
from "signing on". :func:`redact_config` is the one function every such path goes through,
and :func:`redact_text` takes the secret values out of a line of text (an error that quotes
the value it refused) before it reaches a STATUSTEXT or the journal.
"""

from __future__ import annotations

from typing import Any, Iterable, Mapping

#: what a recorded configuration holds in place of a secret value
REDACTED = "<redacted>"

#: key names that hold a secret wherever they appear, and name endings that do
SECRET_KEY_NAMES = frozenset({"signing_key", "token", "password", "secret", "passphrase"})
SECRET_KEY_SUFFIXES = ("_token", "_password", "_secret", "_signing_key")


def is_secret_key(name: str) -> bool:
    """Whether a configuration key called ``name`` (its last dotted part) holds a secret."""
    leaf = str(name).rsplit(".", 1)[-1].lower()
    return leaf in SECRET_KEY_NAMES or leaf.endswith(SECRET_KEY_SUFFIXES)


def _set(value: Any) -> bool:
    return value not in (None, "", b"")


def redact_config(config: Any) -> Any:
    """A copy of ``config`` (nested dicts and lists) with every non-empty secret value
    replaced by :data:`REDACTED`; other values are the same objects."""
    if isinstance(config, Mapping):
        return {k: (REDACTED if is_secret_key(k) and _set(v) else redact_config(v)) for k, v in config.items()}
    if isinstance(config, list):
        return [redact_config(v) for v in config]
    return config


def secret_values(config: Any) -> list[str]:
    """The non-empty secret values of ``config`` (nested dicts and lists), as text."""
    out: list[str] = []
    if isinstance(config, Mapping):
        for k, v in config.items():
            if is_secret_key(k) and _set(v) and not isinstance(v, (Mapping, list)):
                out.append(v.hex() if isinstance(v, bytes) else str(v))
            else:
                out += secret_values(v)
    elif isinstance(config, list):
        for v in config:
            out += secret_values(v)
    return out


def redact_text(text: str, secrets: Iterable[str]) -> str:
    """``text`` with every occurrence of each secret (and of its ``repr``) replaced by
    :data:`REDACTED`; the longest first, so a secret containing another goes whole."""
    for secret in sorted({s for s in secrets if s}, key=len, reverse=True):
        text = text.replace(repr(secret), repr(REDACTED)).replace(secret, REDACTED)
    return text
