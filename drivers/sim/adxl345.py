"""The simulated ADXL345: its registers, FIFO and interrupt source, behind the driver of
:mod:`ahrs_service.drivers.parts.adxl345`.
"""

from __future__ import annotations

from ahrs_service.drivers.device import STANDARD_GRAVITY
from ahrs_service.drivers.parts.adxl345 import (
    BW_RATE,
    DATA_FORMAT,
    DATA_READY,
    DATAX0,
    DEVID,
    DEVID_VALUE,
    FIFO_BYPASS,
    FIFO_CTL,
    FIFO_ENTRIES,
    FIFO_STATUS,
    FULL_RES,
    INT_SOURCE,
    LSB_PER_G,
    MEASURE,
    OVERRUN,
    POWER_CTL,
    WATERMARK,
)
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts
from ahrs_service.drivers.sim.st_fifo import SimulatedFrameFifoTwin


class SimulatedADXL345(SimulatedFrameFifoTwin, SimulatedRegisterDevice):
    """Simulated ADXL345: latches physics "acc" at BW_RATE while POWER_CTL.Measure is set;
    with FIFO_CTL in FIFO or stream mode every sample also enters the 32-entry FIFO, whose
    oldest entry the data registers show (popped when a read of them ends). Counters for
    tests: ``fifo_overflowed`` (entries overwritten or turned away), ``fifo_discarded``
    (entries emptied unread by bypass mode)."""

    CLOCK_ERROR = +0.0090  # this simulated unit runs 0.9 % fast
    FIFO_DATA = DATAX0  # a FIFO entry is DATAX0…DATAZ1
    PART = "ADXL345"
    DEFAULT_ADDRESS = 0x53
    POWER_ON = {DEVID: DEVID_VALUE, BW_RATE: 0x0A, INT_SOURCE: 0x02}
    WRITABLE = frozenset({BW_RATE, POWER_CTL, DATA_FORMAT} | set(range(0x1D, 0x2B))
                         | {0x2E, 0x2F, FIFO_CTL})

    def rate_hz(self) -> float:
        return 3200.0 / 2 ** (15 - (self.regs[BW_RATE] & 0x0F))

    # ---------------------------------------------------------------- FIFO
    def fifo_mode(self) -> int:
        return self.regs[FIFO_CTL] >> 6

    def _fifo_flags(self) -> None:
        """INT_SOURCE Watermark / Overrun and FIFO_STATUS Entries from the FIFO's level."""
        level = len(self.fifo)
        status = self.regs[INT_SOURCE] & ~(WATERMARK | OVERRUN)
        wm = self.regs[FIFO_CTL] & 0x1F
        if wm and level >= wm:
            status |= WATERMARK
        if level >= FIFO_ENTRIES:
            status |= OVERRUN
        self.regs[INT_SOURCE] = status
        self.regs[FIFO_STATUS] = level

    def read_register(self, reg: int) -> int:
        head = self.fifo.head()
        if head is not None and DATAX0 <= reg <= DATAX0 + 5 and self.fifo_mode() != FIFO_BYPASS:
            return head[reg - DATAX0]
        return self.regs[reg]

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == POWER_CTL:
            if value & MEASURE and not old & MEASURE:
                self.restart_measurement(now)
            elif not value & MEASURE:
                self.stop_measurement()
        elif reg == BW_RATE and self._t0 is not None:
            self.restart_measurement(now)
        elif reg == FIFO_CTL and self.fifo_mode() == FIFO_BYPASS:
            self.fifo.reset()
            self._fifo_flags()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        fmt = self.regs[DATA_FORMAT]
        rng = 2 << (fmt & 0b11)
        if fmt & FULL_RES:
            lsb_per_g, bits = LSB_PER_G, 10 + (fmt & 0b11)
        else:  # 10-bit mode: the scale follows the range
            lsb_per_g, bits = 512.0 / rng, 10
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        lsb = STANDARD_GRAVITY / lsb_per_g
        status = self.regs[INT_SOURCE]
        if status & DATA_READY or skipped:
            status |= OVERRUN
        self.regs[INT_SOURCE] = status | DATA_READY
        for i, a in enumerate(phys["acc"]):
            c = to_counts(a, lsb, lo, hi)
            if fmt & 0x04:  # left-justified (MSB) mode
                c <<= 16 - bits
            self.regs[DATAX0 + 2 * i: DATAX0 + 2 * i + 2] = bytes(i16_bytes(c, False))
        if self.fifo_filling():
            self._fifo_push(phys.get("truth"))
            self._fifo_flags()

    def on_read(self, regs: list[int], now: float) -> None:
        if not any(DATAX0 <= r <= DATAX0 + 5 for r in regs):
            return
        if self.fifo_mode() != FIFO_BYPASS:
            if len(self.fifo):  # the read of the data registers has ended: the entry is popped
                self.fifo.pop()
            self._fifo_flags()
            if not len(self.fifo):
                self.regs[INT_SOURCE] &= ~DATA_READY & 0xFF
            return
        self.regs[INT_SOURCE] &= ~(DATA_READY | OVERRUN) & 0xFF
