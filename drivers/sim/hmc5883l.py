"""The simulated HMC5883L and the Honeywell-style register block it shares with the
LSM303DLHC magnetometer: see :mod:`ahrs_service.drivers.parts.hmc5883l`.
"""

from __future__ import annotations

from ahrs_service.drivers.parts.hmc5883l import (
    CONTINUOUS,
    CRA,
    CRB,
    DATA,
    IDA,
    LOCK,
    MODE,
    OVERFLOW,
    RDY,
    STATUS,
    UT_PER_GAUSS,
)
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts


class SimulatedHoneywellStyleMagnetometer(SimulatedRegisterDevice):
    """Twin of the shared register layout: latches physics "mag" in continuous mode."""

    GAINS_XY: tuple[float, ...] = ()
    GAINS_Z: tuple[float, ...] = ()
    RATES: tuple[float, ...] = ()
    WRITABLE = frozenset({CRA, CRB, MODE})
    OVERFLOW_CODE: int | None = OVERFLOW

    def reset_state(self, now: float) -> None:
        self._data_read: set[int] = set()

    def rate_hz(self) -> float | None:
        if self.regs[MODE] & 0x03 != CONTINUOUS:
            return None
        return self.RATES[(self.regs[CRA] >> 2) & 0x07] or None

    def locked(self) -> bool:
        return bool(self.regs[STATUS] & LOCK)

    def _unlock(self) -> None:
        self.regs[STATUS] &= ~LOCK & 0xFF
        self._data_read.clear()

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg in (CRA, MODE):  # a configuration or mode change releases the lock
            self._unlock()
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        gain = self.regs[CRB] >> 5
        xy, z = self.GAINS_XY[gain], self.GAINS_Z[gain]
        bx, by, bz = (b / UT_PER_GAUSS for b in phys["mag"])
        values = []
        for b, g in ((bx, xy), (bz, z), (by, xy)):  # register order X, Z, Y
            c = to_counts(b, 1.0 / g, -32768, 32767)
            if not -2048 <= c <= 2047:
                c = self.OVERFLOW_CODE if self.OVERFLOW_CODE is not None else max(-2048, min(2047, c))
            values.extend(i16_bytes(c, True))
        self.regs[DATA:DATA + 6] = bytes(values)
        self.regs[STATUS] |= RDY

    def on_read(self, regs: list[int], now: float) -> None:
        for r in regs:
            if DATA <= r < DATA + 6:
                self._data_read.add(r)
            elif r == MODE:
                self.regs[STATUS] |= LOCK
        if len(self._data_read) == 6:
            self._unlock()
        elif self._data_read:
            self.regs[STATUS] |= LOCK


class SimulatedHMC5883L(SimulatedHoneywellStyleMagnetometer):
    """Simulated HMC5883L (ID 'H43', pointer wrap 0x09 → 0x03 and ≥ 0x0C → 0x00).

    RDY is modelled as set once the first measurement is in and never cleared by reads (the
    part's 250 µs low pulse while it writes is not modelled). Single-measurement and bias
    modes do not measure.
    """

    PART = "HMC5883L"
    DEFAULT_ADDRESS = 0x1E
    GAINS_XY = GAINS_Z = (1370.0, 1090.0, 820.0, 660.0, 440.0, 390.0, 330.0, 230.0)
    RATES = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 0.0)
    POWER_ON = {CRA: 0x10, CRB: 0x20, MODE: 0x01, IDA: 0x48, IDA + 1: 0x34, IDA + 2: 0x33}

    def next_pointer(self, reg: int) -> int:
        if reg == STATUS:
            return DATA
        if reg >= 0x0C:
            return 0x00
        return reg + 1

    def read_register(self, reg: int) -> int:
        return self.regs[reg] if reg <= 0x0C else 0  # invalid locations read 0
