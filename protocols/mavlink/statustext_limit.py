"""Rate limit of STATUSTEXT per kind of message, with repeats summarised.

Anything a peer can trigger (an unsigned PARAM_SET with an unknown name, a rejected value, a
refused command) answers with a STATUSTEXT on every link; without a limit, a flood of such
requests becomes a flood to every ground station. Each *kind* (a short key the caller gives,
e.g. ``"unknown parameter"``) gets a token bucket: ``burst`` texts at once, then one per
``period_s``. A text over the limit is counted, not sent; the next text of that kind that goes
out carries the count ("… (+N more)"). Time is the monotonic clock in ns, passed
in by the caller so tests drive it without sleeping.
"""

from __future__ import annotations

from dataclasses import dataclass

BURST = 5  # texts of one kind sent at once before the limit applies
PERIOD_S = 1.0  # then at most one text of that kind per this many seconds
MAX_KINDS = 64  # kinds tracked; beyond that the oldest is forgotten (kinds are the caller's, few)


@dataclass
class _Bucket:
    tokens: float
    last_ns: int
    suppressed: int = 0


class StatusTextLimiter:
    """Decides per kind whether a STATUSTEXT goes out now; counts those that do not."""

    def __init__(self, burst: int = BURST, period_s: float = PERIOD_S) -> None:
        self.burst = int(burst)
        self.period_ns = int(period_s * 1e9)
        self._buckets: dict[str, _Bucket] = {}
        self.suppressed_total = 0  # texts not sent since start, all kinds

    def admit(self, kind: str, text: str, now_ns: int) -> str | None:
        """The text to send now (``text``, with the count of suppressed repeats of ``kind``
        appended if any), or None when ``kind`` is over its limit (the text is counted)."""
        b = self._buckets.get(kind)
        if b is None:
            if len(self._buckets) >= MAX_KINDS:
                self._buckets.pop(next(iter(self._buckets)))
            b = self._buckets[kind] = _Bucket(float(self.burst), now_ns)
        b.tokens = min(float(self.burst), b.tokens + max(0, now_ns - b.last_ns) / self.period_ns)
        b.last_ns = now_ns
        if b.tokens < 1.0:
            b.suppressed += 1
            self.suppressed_total += 1
            return None
        b.tokens -= 1.0
        if b.suppressed:
            text, b.suppressed = f"{text} (+{b.suppressed} more)", 0
        return text
