"""The simulated AK8963 (the MPU-9250's magnetometer), register for register: see
:mod:`ahrs_service.drivers.parts.ak8963`.
"""

from __future__ import annotations

from typing import Any

from ahrs_service.drivers.parts.ak8963 import (
    ASAX,
    ASTC,
    BIT_16,
    BITM,
    CNTL1,
    CNTL2,
    DOR,
    DRDY,
    FUSE_ROM,
    HOFL,
    HXL,
    INFO,
    OVERFLOW_UT,
    ST1,
    ST2,
    UT_PER_LSB,
    WIA,
    WIA_VALUE,
)
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts


class SimulatedAK8963(SimulatedRegisterDevice):
    """Simulated AK8963: physics "mag" (µT, MPU-9250 axes) → die axes and counts.

    asa: fuse-ROM sensitivity adjustment values; the raw counts are divided by the matching
    adjustment, so a driver that applies ASA gets the true field back.
    """

    PART = "AK8963"
    DEFAULT_ADDRESS = 0x0C
    POWER_ON = {WIA: WIA_VALUE, INFO: 0x9A}
    WRITABLE = frozenset({CNTL1, CNTL2, ASTC, 0x0D, 0x0E, 0x0F})

    def __init__(self, source: Any = None, address: int | None = None,
                 asa: tuple[int, int, int] = (176, 177, 165)) -> None:
        self.asa = tuple(int(a) for a in asa)
        super().__init__(source, address)

    def rate_hz(self) -> float | None:
        mode = self.regs[CNTL1] & 0x0F
        return {0x02: 8.0, 0x06: 100.0}.get(mode)

    def locked(self) -> bool:
        return self._reading

    def reset_state(self, now: float) -> None:
        self._reading = False  # between an ST1 read showing DRDY and the ST2 read

    def read_register(self, reg: int) -> int:
        if ASAX <= reg <= ASAX + 2:  # fuse ROM is only readable in fuse-ROM access mode
            return self.asa[reg - ASAX] if self.regs[CNTL1] & 0x0F == FUSE_ROM else 0
        return self.regs[reg] if reg <= 0x12 else 0

    def next_pointer(self, reg: int) -> int:
        return reg + 1 if reg < 0x12 else 0x00

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == CNTL2 and value & 0x01:
            self.power_on_reset(now)
        elif reg == CNTL1:
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        bx, by, bz = phys["mag"]
        die = (by, bx, -bz)  # MPU-9250 axes → AK8963 die axes
        bits16 = bool(self.regs[CNTL1] & BIT_16)
        lsb = UT_PER_LSB[16 if bits16 else 14]
        lim = 32760 if bits16 else 8190
        out = []
        for b, a in zip(die, self.asa):
            out.extend(i16_bytes(to_counts(b, lsb * ((a - 128) / 256.0 + 1.0), -lim, lim), False))
        self.regs[HXL:HXL + 6] = bytes(out)
        overflow = abs(bx) + abs(by) + abs(bz) > OVERFLOW_UT
        self.regs[ST2] = (BITM if bits16 else 0) | (HOFL if overflow else 0)
        st1 = self.regs[ST1]
        self.regs[ST1] = DRDY | (DOR if st1 & DRDY or skipped else 0)

    def on_read(self, regs: list[int], now: float) -> None:
        if ST1 in regs and self.regs[ST1] & DRDY:
            self._reading = True
        if any(HXL <= r <= ST2 for r in regs):
            self.regs[ST1] = 0
        if ST2 in regs:
            self._reading = False
