"""The simulated L3G4200D gyroscope, with its 32-level FIFO: see
:mod:`ahrs_service.drivers.parts.l3g4200d`.
"""

from __future__ import annotations

from ahrs_service.drivers.device import DEG2RAD
from ahrs_service.drivers.parts.l3g4200d import (
    BLE,
    CTRL_REG1,
    CTRL_REG2,
    CTRL_REG3,
    CTRL_REG4,
    CTRL_REG5,
    OUT_TEMP,
    OUT_X_L,
    STATUS_REG,
    WHO_AM_I,
    ZYXDA,
    ZYXOR,
)
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts
from ahrs_service.drivers.sim.st_fifo import SimulatedSTFifo


class SimulatedL3G4200D(SimulatedSTFifo, SimulatedRegisterDevice):
    """Simulated L3G4200D: latches physics "gyr" at the DR rate while CTRL_REG1.PD is set;
    with CTRL_REG5.FIFO_EN every sample also enters the 32-level FIFO (:mod:`.st_fifo`)."""

    CLOCK_ERROR = -0.0060  # this simulated unit runs 0.6 % slow
    PART = "L3G4200D"
    DEFAULT_ADDRESS = 0x69
    ST_SUBADDRESS = True
    WHO_AM_I_VALUE = 0xD3
    RATES = (100.0, 200.0, 400.0, 800.0)
    SENS_DPS = (8.75e-3, 17.5e-3, 70e-3, 70e-3)
    POWER_ON = {WHO_AM_I: WHO_AM_I_VALUE, CTRL_REG1: 0x07}
    WRITABLE = frozenset({CTRL_REG1, CTRL_REG2, CTRL_REG3, CTRL_REG4, CTRL_REG5,
                          0x25, 0x2E, 0x30, 0x32, 0x33, 0x34, 0x35, 0x36, 0x37, 0x38})

    def reset_state(self, now: float) -> None:
        super().reset_state(now)
        self.regs[WHO_AM_I] = self.WHO_AM_I_VALUE

    def rate_hz(self) -> float:
        return self.RATES[self.regs[CTRL_REG1] >> 6]

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        super().on_write(reg, value, old, now)  # the FIFO's registers
        if reg == CTRL_REG1:
            if value & 0x08 and (not old & 0x08 or (value ^ old) & 0xC0):
                self.restart_measurement(now)
            elif not value & 0x08:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        ctrl4 = self.regs[CTRL_REG4]
        lsb = self.SENS_DPS[(ctrl4 >> 4) & 0b11] * DEG2RAD
        big = bool(ctrl4 & BLE)
        status = self.regs[STATUS_REG]
        over = (status & 0x0F) << 4  # an unread axis being overwritten is an overrun
        if skipped:
            over = 0xF0
        self.regs[STATUS_REG] = (status & 0xF0) | over | 0x0F
        for i, w in enumerate(phys["gyr"]):
            c = to_counts(w, lsb, -32768, 32767)
            self.regs[OUT_X_L + 2 * i: OUT_X_L + 2 * i + 2] = bytes(i16_bytes(c, big))
        temp = phys.get("temperature_c")
        if temp is not None:  # 8-bit, −1 LSB/°C; the offset is not specified, 25 °C reads 0 here
            self.regs[OUT_TEMP] = to_counts(25.0 - temp, 1.0, -128, 127) & 0xFF
        self._fifo_push(phys.get("truth"))

    def on_read(self, regs: list[int], now: float) -> None:
        status = self.regs[STATUS_REG]
        if not status:
            return
        # high byte of an axis (little-endian: odd addresses; big-endian: even) clears its bits
        high_first = bool(self.regs[CTRL_REG4] & BLE)
        for axis in range(3):
            hi = OUT_X_L + 2 * axis + (0 if high_first else 1)
            if hi in regs:
                status &= ~((1 << axis) | (0x10 << axis)) & 0xFF
        if not status & 0x07:
            status &= ~ZYXDA & 0xFF
        if not status & 0x70:
            status &= ~ZYXOR & 0xFF
        self.regs[STATUS_REG] = status
