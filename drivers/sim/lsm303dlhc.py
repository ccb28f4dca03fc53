"""The simulated LSM303DLHC: accelerometer (with its FIFO) and magnetometer, two addresses:
see :mod:`ahrs_service.drivers.parts.lsm303dlhc`.
"""

from __future__ import annotations

from ahrs_service.drivers.device import STANDARD_GRAVITY
from ahrs_service.drivers.parts.lsm303dlhc import (
    ACC_RATES_BY_CODE,
    BLE,
    CTRL_REG1_A,
    CTRL_REG4_A,
    HR,
    OUT_X_L_A,
    STATUS_REG_A,
    ZYXDA,
    ZYXOR,
)
from ahrs_service.drivers.sim.hmc5883l import SimulatedHoneywellStyleMagnetometer
from ahrs_service.drivers.sim.register_device import SimulatedRegisterDevice, i16_bytes, to_counts
from ahrs_service.drivers.sim.st_fifo import SimulatedSTFifo

#: the accelerometer's mg per LSB at ±2/4/8/16 g (the FS code indexes it)
ACC_MG_PER_LSB = (1.0, 2.0, 4.0, 12.0)


class SimulatedLSM303DLHCAcc(SimulatedSTFifo, SimulatedRegisterDevice):
    """Simulated LSM303DLHC accelerometer: latches physics "acc" at the CTRL_REG1_A rate;
    with CTRL_REG5_A.FIFO_EN every sample also enters the 32-level FIFO (:mod:`.st_fifo`)."""

    FM_SHIFT = 6

    CLOCK_ERROR = -0.0110  # this simulated unit runs 1.1 % slow
    PART = "LSM303DLHC accelerometer"
    DEFAULT_ADDRESS = 0x19
    ST_SUBADDRESS = True
    POWER_ON = {CTRL_REG1_A: 0x07}
    WRITABLE = frozenset(set(range(0x20, 0x27)) | {0x2E, 0x30, 0x32, 0x33, 0x34, 0x36, 0x37,
                                                    0x38, 0x3A, 0x3B, 0x3C, 0x3D})

    def rate_hz(self) -> float | None:
        code = self.regs[CTRL_REG1_A] >> 4
        return ACC_RATES_BY_CODE[code] if code < len(ACC_RATES_BY_CODE) else None

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        super().on_write(reg, value, old, now)  # the FIFO's registers
        if reg == CTRL_REG1_A and (value ^ old) & 0xF0:
            if value >> 4:
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        ctrl4 = self.regs[CTRL_REG4_A]
        # 12-bit (HR) or 10-bit (normal) value, left-justified in 16 bits
        bits = 12 if ctrl4 & HR else 10
        lsb = ACC_MG_PER_LSB[(ctrl4 >> 4) & 0b11] * 1e-3 * STANDARD_GRAVITY * (4096 >> bits)
        lo, hi = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        big = bool(ctrl4 & BLE)
        status = self.regs[STATUS_REG_A]
        over = 0xF0 if skipped else (status & 0x0F) << 4
        self.regs[STATUS_REG_A] = (status & 0xF0) | over | 0x0F
        for i, a in enumerate(phys["acc"]):
            c = to_counts(a, lsb, lo, hi) << (16 - bits)
            self.regs[OUT_X_L_A + 2 * i: OUT_X_L_A + 2 * i + 2] = bytes(i16_bytes(c, big))
        self._fifo_push(phys.get("truth"))

    def on_read(self, regs: list[int], now: float) -> None:
        status = self.regs[STATUS_REG_A]
        if not status:
            return
        high_first = bool(self.regs[CTRL_REG4_A] & BLE)
        for axis in range(3):
            if OUT_X_L_A + 2 * axis + (0 if high_first else 1) in regs:
                status &= ~((1 << axis) | (0x10 << axis)) & 0xFF
        if not status & 0x07:
            status &= ~ZYXDA & 0xFF
        if not status & 0x70:
            status &= ~ZYXOR & 0xFF
        self.regs[STATUS_REG_A] = status


class SimulatedLSM303DLHCMag(SimulatedHoneywellStyleMagnetometer):
    """Simulated LSM303DLHC magnetometer: separate X/Y and Z gains, saturates at ±2047.

    Pointer: plain auto-increment. DRDY behaves as modelled for the HMC5883L (set by new
    data, not cleared by reads). Power-on mode is sleep.
    """

    PART = "LSM303DLHC magnetometer"
    DEFAULT_ADDRESS = 0x1E
    GAINS_XY = (1100.0, 1100.0, 855.0, 670.0, 450.0, 400.0, 330.0, 230.0)
    GAINS_Z = (980.0, 980.0, 760.0, 600.0, 400.0, 355.0, 295.0, 205.0)
    RATES = (0.75, 1.5, 3.0, 7.5, 15.0, 30.0, 75.0, 220.0)
    POWER_ON = {0x00: 0x10, 0x01: 0x20, 0x02: 0x03, 0x0A: 0x48, 0x0B: 0x34, 0x0C: 0x33}
    OVERFLOW_CODE = None
