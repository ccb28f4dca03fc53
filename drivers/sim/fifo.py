"""The twins' FIFOs: whole frames (the ST parts, the ADXL345) or a byte stream of the part's
depth (today's IMUs), filled on a clock that runs ``clock_error`` off nominal.
"""

from __future__ import annotations

from collections import deque

from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice


class SimulatedFrameFifo:
    """The twins' FIFO of whole samples (frames of the data registers), with each sample's
    truth beside it (simulation only): the 32-level FIFOs of the ST parts and the ADXL345.

    ``push`` follows the part's mode: a full FIFO turns the new sample away (FIFO mode,
    ``keep_oldest``) or overwrites its oldest (stream mode). Counters for tests: ``overflowed``
    (samples overwritten or turned away), ``discarded`` (samples emptied unread by a reset).
    """

    def __init__(self, depth: int) -> None:
        self.depth = int(depth)
        self.frames: deque[bytes] = deque()
        self.truth: deque = deque()
        self.popped_truth: list = []  # the truth of the samples read since take_popped_truth()
        self.overflowed = 0
        self.discarded = 0

    def __len__(self) -> int:
        return len(self.frames)

    def push(self, frame: bytes, truth, keep_oldest: bool) -> None:
        if len(self.frames) >= self.depth:
            self.overflowed += 1
            if keep_oldest:
                return
            self.frames.popleft()
            self.truth.popleft()
        self.frames.append(frame)
        self.truth.append(truth)

    def head(self) -> bytes | None:
        """The oldest stored sample (what the data registers show), None when empty."""
        return self.frames[0] if self.frames else None

    def pop(self) -> None:
        """The oldest sample has been read out."""
        self.frames.popleft()
        self.popped_truth.append(self.truth.popleft())

    def reset(self) -> None:
        """Emptied unread (bypass mode)."""
        self.discarded += len(self.frames)
        self.frames.clear()
        self.truth.clear()

    def take_popped_truth(self) -> list:
        out, self.popped_truth = self.popped_truth, []
        return out


class SimulatedFifo:
    """A byte FIFO of ``capacity`` bytes holding whole samples of ``frame`` bytes.

    stop_on_full: a frame that does not fit is dropped (ICM-42688-P "stop-on-full",
    BMI088 "FIFO mode"); otherwise the oldest frames make room (stream mode).
    ``overflowed`` is set on the first lost frame; ``dropped`` counts them.
    """

    def __init__(self, capacity: int, stop_on_full: bool = True, frame: int = 1) -> None:
        self.capacity = int(capacity)
        self.frame = int(frame)  # bytes of one sample (packet)
        self.discarded = 0  # samples emptied unread by clear() (a flush), for tests
        self.stop_on_full = stop_on_full
        self.data = bytearray()
        self.overflowed = False
        self.dropped = 0

    @property
    def level(self) -> int:
        return len(self.data)

    def push(self, frame: bytes) -> bool:
        if len(self.data) + len(frame) > self.capacity:
            self.overflowed = True
            self.dropped += 1
            if self.stop_on_full:
                return False
            del self.data[:len(frame)]
        self.data += frame
        return True

    def pop(self, n: int) -> bytes:
        out = bytes(self.data[:n])
        del self.data[:n]
        return out

    def clear(self) -> None:
        """Emptied (a FIFO flush/reset): the whole samples in it are ``discarded`` unread."""
        self.discarded += len(self.data) // self.frame
        self.data.clear()
        self.overflowed = False


class SimulatedFifoDevice(SimulatedRegisterDevice):
    """Twin base of the SPI parts whose every due sample is latched (and pushed to its FIFO),
    in order, by the base's FIFO latching (``fifo_room`` from the FIFO's free bytes).

    clock_error: the part's oscillator error (+0.004 = 0.4 % fast; the name the I2C twins use): ``rate_hz()`` returns the
    nominal rate from the registers, the samples come at ``nominal · (1 + clock_error)``.
    Subclasses implement :meth:`nominal_rate_hz`, :meth:`latch` (data registers + FIFO) and
    :meth:`backlog_limit` (how many samples can matter at once: the FIFO's depth + 1).
    """

    CLOCK_ERROR = 0.0

    def __init__(self, source=None, address: int | None = None, clock_error: float | None = None) -> None:
        super().__init__(source, address)
        self.clock_error = self.CLOCK_ERROR if clock_error is None else float(clock_error)
        #: samples produced while the FIFO was full that were never computed (``samples_latched``
        #: counts the rest: produced = samples_latched + samples_unseen)
        self.samples_unseen = 0

    def nominal_rate_hz(self) -> float | None:
        return None

    def rate_hz(self) -> float | None:
        r = self.nominal_rate_hz()
        return None if not r else r * (1.0 + self.clock_error)

    def sampling_rate_hz(self) -> float | None:
        return self.rate_hz()  # rate_hz() is already the real rate here

    def backlog_limit(self) -> int:
        return 1

    # the base's FIFO latching (SimulatedRegisterDevice._update_fifo) through these hooks
    def fifo_room(self) -> int | None:
        if self.backlog_limit() <= 1:  # FIFO off: the newest sample only, as in polling
            return None
        fifo = self.fifo  # type: ignore[attr-defined]
        return max(0, (fifo.capacity - fifo.level) // fifo.frame)

    def fifo_keeps_oldest(self) -> bool:
        return self.fifo.stop_on_full  # type: ignore[attr-defined]

    def fifo_dropped(self, n: int) -> None:
        # samples that could only have overflowed the FIFO: counted, never computed
        self.samples_unseen += n
        self.skipped_unseen(n)

    def skipped_unseen(self, n: int) -> None:
        """``n`` samples produced while the FIFO was already full (hook: mark overflow)."""
