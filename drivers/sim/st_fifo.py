"""The twins' side of the 32-sample frame FIFO of the ST parts and the ADXL345 (modes,
watermark, overrun): see :mod:`ahrs_service.drivers.parts.st_fifo` for the registers.
"""

from __future__ import annotations

from typing import Any

from ahrs_service.drivers.parts.st_fifo import (
    CTRL_REG5,
    FIFO_CTRL_REG,
    FIFO_EN,
    FIFO_FRAMES,
    FIFO_SRC_REG,
    FM_BYPASS,
    FM_FIFO,
    FM_STREAM,
    FRAME_BYTES,
    OUT_X_L,
    OUT_Z_H,
    SRC_EMPTY,
    SRC_OVRN,
    SRC_WTM,
    WTM_MASK,
)
from ahrs_service.drivers.sim.fifo import SimulatedFrameFifo


class SimulatedFrameFifoTwin:
    """Twin side of a 32-sample FIFO of whole X, Y, Z frames (6 bytes from ``FIFO_DATA``), in
    the modes the ST parts and the ADXL345 number alike: 0 bypass, 1 FIFO (a full FIFO turns
    the new sample away), 2 stream (it overwrites its oldest). Mixed into the twins before
    :class:`SimulatedRegisterDevice`, it gives the base's FIFO latching its hooks; the twin
    tells :meth:`fifo_mode` and calls :meth:`_fifo_push` at the end of its ``latch``."""

    regs: bytearray
    #: the first data register: a frame is the 6 bytes from here
    FIFO_DATA = OUT_X_L

    def reset_state(self, now: float) -> None:
        super().reset_state(now)  # type: ignore[misc]
        self.fifo = SimulatedFrameFifo(FIFO_FRAMES)

    # the twin's counters for tests (samples overwritten/turned away, emptied unread)
    fifo_overflowed = property(lambda self: self.fifo.overflowed)
    fifo_discarded = property(lambda self: self.fifo.discarded)
    fifo_frames = property(lambda self: len(self.fifo))

    def fifo_mode(self) -> int | None:
        """The FIFO's mode (FM_BYPASS, FM_FIFO, FM_STREAM, …), None while it is off."""
        raise NotImplementedError

    def fifo_filling(self) -> bool:
        """Whether each new sample enters the FIFO (FIFO or stream mode)."""
        return self.fifo_mode() in (FM_FIFO, FM_STREAM)

    def fifo_room(self) -> int | None:
        return FIFO_FRAMES - len(self.fifo) if self.fifo_filling() else None

    def fifo_keeps_oldest(self) -> bool:
        return self.fifo_mode() == FM_FIFO

    def fifo_dropped(self, n: int) -> None:
        self.fifo.overflowed += n

    def _fifo_push(self, truth: Any) -> None:
        """The sample just latched into the data registers, into the FIFO when it fills."""
        if self.fifo_filling():
            self.fifo.push(bytes(self.regs[self.FIFO_DATA:self.FIFO_DATA + FRAME_BYTES]), truth,
                           self.fifo_keeps_oldest())

    def take_popped_truth(self) -> list[Any]:
        """The truth of the samples read from the FIFO since the last call, oldest first."""
        return self.fifo.take_popped_truth()


class SimulatedSTFifo(SimulatedFrameFifoTwin):
    """Twin side, mixed into the ST twins (before :class:`SimulatedRegisterDevice`, whose
    ``read_register``, ``next_pointer`` and ``on_write`` it extends): the 32-sample FIFO of
    the registers above, filled by every due sample (the base's FIFO latching), the
    stream/FIFO mode rules, the watermark and OVRN, the OUT_X_L … OUT_Z_H roll-over. The twin
    calls :meth:`_fifo_push` at the end of its ``latch``."""

    #: where FM sits in FIFO_CTRL_REG: bits 7:5 on the gyroscopes, 7:6 (bit 5: TR) on the
    #: LSM303DLHC — the same mode numbers either way
    FM_SHIFT = 5

    def fifo_mode(self) -> int | None:
        """FM of FIFO_CTRL_REG, or None while CTRL_REG5.FIFO_EN is clear."""
        if not self.regs[CTRL_REG5] & FIFO_EN:
            return None
        return self.regs[FIFO_CTRL_REG] >> self.FM_SHIFT

    def _fifo_src(self) -> int:
        level = len(self.fifo)
        src = min(level, FIFO_FRAMES - 1)
        if level >= FIFO_FRAMES:
            src |= SRC_OVRN
        if level == 0:
            src |= SRC_EMPTY
        wtm = self.regs[FIFO_CTRL_REG] & WTM_MASK
        if wtm and level >= wtm:
            src |= SRC_WTM
        return src

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        """FIFO_CTRL_REG: bypass mode empties the FIFO (§5.2.1). The twins call this first."""
        if reg == FIFO_CTRL_REG and value >> self.FM_SHIFT == FM_BYPASS:
            self.fifo.reset()

    def read_register(self, reg: int) -> int:
        if reg == FIFO_SRC_REG:
            return self._fifo_src()
        head = self.fifo.head()
        if self.fifo_mode() is None or not OUT_X_L <= reg <= OUT_Z_H or head is None:
            return self.regs[reg]
        if reg == OUT_Z_H:  # the sample is read: the next one moves up (§5.2.6)
            self.fifo.pop()
        return head[reg - OUT_X_L]

    def next_pointer(self, reg: int) -> int:
        # with the FIFO on, an auto-increment read rolls OUT_Z_H over to OUT_X_L
        if self.fifo_mode() is not None and reg == OUT_Z_H:
            return OUT_X_L
        return super().next_pointer(reg)  # type: ignore[misc]
