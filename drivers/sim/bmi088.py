"""The simulated BMI088: its accelerometer and gyroscope dies, each on its own chip select,
with their FIFOs: see :mod:`ahrs_service.drivers.parts.bmi088`.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY
from ahrs_service.drivers.parts.bmi088 import (
    ACC_CHIP_ID,
    ACC_CHIP_ID_VALUE,
    ACC_CONF,
    ACC_EMPTY,
    ACC_FIFO_BYTES,
    ACC_FIFO_CONFIG_0,
    ACC_FIFO_CONFIG_1,
    ACC_FIFO_DATA,
    ACC_FIFO_FLUSH_CMD,
    ACC_FRAME,
    ACC_FRAME_HEADER,
    ACC_ODR_HZ,
    ACC_PWR_CONF,
    ACC_PWR_CTRL,
    ACC_RANGE,
    ACC_SOFTRESET,
    FIFO_LENGTH_0,
    FIFO_STATUS,
    FIFO_WM_ENABLE,
    FIFO_WTM_0,
    FIFO_WTM_1,
    GYRO_BANDWIDTH,
    GYRO_CHIP_ID,
    GYRO_CHIP_ID_VALUE,
    GYRO_FIFO_CONFIG_0,
    GYRO_FIFO_CONFIG_1,
    GYRO_FIFO_DATA,
    GYRO_FIFO_FRAMES,
    GYRO_FRAME,
    GYRO_INT_CTRL,
    GYRO_LPM1,
    GYRO_ODR_HZ,
    GYRO_RANGE,
    GYRO_SOFTRESET,
    INT1_IO_CTRL,
    INT3_INT4_IO_CONF,
    INT3_INT4_IO_MAP,
    INT_MAP_DATA,
    OVERRUN,
    SOFTRESET_CMD,
    acc_lsb_per_g,
    gyro_lsb_per_dps,
)
from ahrs_service.drivers.sim.fifo import SimulatedFifo, SimulatedFifoDevice
from ahrs_service.drivers.sim.register_device import to_counts


class _BMI088Die(SimulatedFifoDevice):
    """What both dies' twins share: FIFO port reads, soft reset, the truth side channel."""

    FIFO_PORT = 0x00
    SOFTRESET_REG = 0x00

    def __init__(self, source: Any = None, clock_error: float | None = None) -> None:
        self.int1 = None
        super().__init__(source, 0x10, clock_error)

    def reset_state(self, now: float) -> None:
        self.truth: deque = deque()
        self.popped_truth: list = []
        self._above_wm = False

    def take_popped_truth(self) -> list:
        out, self.popped_truth = self.popped_truth, []
        return out

    def bus_read(self, sub: int, n: int, now: float) -> list[int]:
        self.update(now)
        if sub == self.FIFO_PORT:
            return self.pop_fifo(n)
        return [self.read_register((sub + i) & 0x7F) for i in range(n)]

    def bus_write(self, sub: int, data: list[int], now: float) -> None:
        self.update(now)
        if sub == self.SOFTRESET_REG and data and data[0] == SOFTRESET_CMD:
            self.power_on_reset(now)
            return
        if sub == self.SOFTRESET_REG and data and data[0] == self.FIFO_FLUSH_CMD:
            self.flush_fifo()
            return
        super().bus_write(sub, data, now)

    FIFO_FLUSH_CMD: int | None = None  # a command to SOFTRESET_REG that empties the FIFO

    def flush_fifo(self) -> None:
        self.fifo.clear()
        self.truth.clear()
        self._above_wm = False

    def _truth_q(self, phys: dict):
        truth = phys.get("truth")
        if truth is None:
            return None
        return np.asarray(truth["q"] if isinstance(truth, dict) else truth.q, dtype=float)

    def _edge(self, t: float, level_frames: int, wm_frames: int, routed: bool) -> None:
        if wm_frames and level_frames >= wm_frames:
            if not self._above_wm:
                self._above_wm = True
                if self.int1 is not None and routed:
                    self.int1(t)
        else:
            self._above_wm = False


class SimulatedBMI088Accel(_BMI088Die):
    """Accelerometer die twin: SPI mode after the first CSB1 edge, one dummy byte per read,
    the 1 KB FIFO of 7-byte frames in FIFO (stop-when-full) mode, a 0x80 header when empty."""

    PART = "BMI088 accelerometer"
    SPI_DUMMY_BYTES = 1
    CLOCK_ERROR = -0.0061
    FIFO_PORT, SOFTRESET_REG, FIFO_FLUSH_CMD = ACC_FIFO_DATA, ACC_SOFTRESET, ACC_FIFO_FLUSH_CMD
    POWER_ON = {ACC_CHIP_ID: ACC_CHIP_ID_VALUE, ACC_CONF: 0xA8, ACC_RANGE: 0x01, ACC_PWR_CONF: 0x03,
                ACC_PWR_CTRL: 0x00, ACC_FIFO_CONFIG_0: 0x02, ACC_FIFO_CONFIG_1: 0x10, FIFO_WTM_0: 0x00,
                FIFO_WTM_1: 0x02, INT_MAP_DATA: 0x00}
    WRITABLE = frozenset({ACC_CONF, ACC_RANGE, FIFO_WTM_0, FIFO_WTM_1, ACC_FIFO_CONFIG_0, ACC_FIFO_CONFIG_1,
                          INT1_IO_CTRL, INT_MAP_DATA, ACC_PWR_CONF, ACC_PWR_CTRL})

    def reset_state(self, now: float) -> None:
        super().reset_state(now)
        self.fifo = SimulatedFifo(ACC_FIFO_BYTES, stop_on_full=True, frame=ACC_FRAME)
        self.spi_mode = False
        self.restart_measurement(now)

    def spi_select(self, now: float) -> bool:
        """Chip select asserted: the first edge after power-on switches the die to SPI."""
        if not self.spi_mode:
            self.spi_mode = True
            return False
        return True

    def nominal_rate_hz(self) -> float | None:
        if self.regs[ACC_PWR_CTRL] != 0x04 or self.regs[ACC_PWR_CONF] != 0x00:
            return None
        return ACC_ODR_HZ.get(self.regs[ACC_CONF] & 0x0F)

    def backlog_limit(self) -> int:
        return ACC_FIFO_BYTES // ACC_FRAME + 1

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        # no FIFO clearing on FIFO_CONFIG writes: no source gives that rule (the 0xB0
        # command to ACC_SOFTRESET flushes, see _BMI088Die.bus_write)
        if reg in (ACC_PWR_CTRL, ACC_PWR_CONF, ACC_CONF) and value != old:
            self.restart_measurement(now)

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        lsb = STANDARD_GRAVITY / acc_lsb_per_g(self.regs[ACC_RANGE] & 3)
        frame = bytearray((ACC_FRAME_HEADER,))
        for a in phys["acc"]:
            frame += (to_counts(a, lsb, -32768, 32767) & 0xFFFF).to_bytes(2, "little")
        if self.regs[ACC_FIFO_CONFIG_1] & 0x40 and self.fifo.push(bytes(frame)):
            self.truth.append(self._truth_q(phys))
        wm = (self.regs[FIFO_WTM_0] | (self.regs[FIFO_WTM_1] & 0x1F) << 8) // ACC_FRAME
        self._edge(t, self.fifo.level // ACC_FRAME, wm, bool(self.regs[INT_MAP_DATA] & 0x02))

    def skipped_unseen(self, n: int) -> None:
        self.fifo.overflowed = True
        self.fifo.dropped += n

    def read_register(self, reg: int) -> int:
        if reg == FIFO_LENGTH_0:
            return self.fifo.level & 0xFF
        if reg == FIFO_LENGTH_0 + 1:
            return self.fifo.level >> 8
        return self.regs[reg]

    def pop_fifo(self, n: int) -> list[int]:
        before = self.fifo.level // ACC_FRAME
        got = self.fifo.pop(n)
        for _ in range(before - -(-self.fifo.level // ACC_FRAME)):
            self.popped_truth.append(self.truth.popleft())
        self._above_wm = False
        return list(got) + [ACC_EMPTY] * (n - len(got))


class SimulatedBMI088Gyro(_BMI088Die):
    """Gyroscope die twin: the 100-frame FIFO in FIFO mode, FIFO_STATUS overrun, INT3."""

    PART = "BMI088 gyroscope"
    CLOCK_ERROR = +0.0073
    FIFO_PORT, SOFTRESET_REG = GYRO_FIFO_DATA, GYRO_SOFTRESET
    POWER_ON = {GYRO_CHIP_ID: GYRO_CHIP_ID_VALUE, GYRO_BANDWIDTH: 0x80, GYRO_RANGE: 0x00,
                FIFO_WM_ENABLE: 0x08, GYRO_FIFO_CONFIG_1: 0x00}
    WRITABLE = frozenset({GYRO_RANGE, GYRO_BANDWIDTH, GYRO_LPM1, GYRO_INT_CTRL, INT3_INT4_IO_CONF,
                          INT3_INT4_IO_MAP, FIFO_WM_ENABLE, GYRO_FIFO_CONFIG_0, GYRO_FIFO_CONFIG_1})

    def reset_state(self, now: float) -> None:
        super().reset_state(now)
        self.fifo = SimulatedFifo(GYRO_FIFO_FRAMES * GYRO_FRAME, stop_on_full=True, frame=GYRO_FRAME)
        self.restart_measurement(now)

    def nominal_rate_hz(self) -> float | None:
        if self.regs[GYRO_LPM1] != 0x00:
            return None
        return GYRO_ODR_HZ[self.regs[GYRO_BANDWIDTH] & 0x07]

    def backlog_limit(self) -> int:
        return GYRO_FIFO_FRAMES + 1

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == GYRO_BANDWIDTH:
            self.regs[GYRO_BANDWIDTH] = 0x80 | value  # bit 7 reads 1
            if (value & 0x07) != (old & 0x07):
                self.restart_measurement(now)
        elif reg == GYRO_FIFO_CONFIG_0:  # "clears the FIFO buffer", not the overrun flag
            overrun = self.fifo.overflowed
            self.flush_fifo()
            self.fifo.overflowed = overrun
        elif reg == GYRO_FIFO_CONFIG_1:  # the only way to clear the overrun flag
            self.fifo.overflowed = False
        elif reg == GYRO_LPM1 and value != old:
            self.restart_measurement(now)

    def fifo_on(self) -> bool:
        return (self.regs[GYRO_FIFO_CONFIG_1] & 0xC0) != 0

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        lsb = DEG2RAD / gyro_lsb_per_dps(self.regs[GYRO_RANGE] & 7)
        frame = bytearray()
        for w in phys["gyr"]:
            frame += (to_counts(w, lsb, -32768, 32767) & 0xFFFF).to_bytes(2, "little")
        if self.fifo_on() and self.fifo.push(bytes(frame)):
            self.truth.append(self._truth_q(phys))
        routed = bool(self.regs[INT3_INT4_IO_MAP] & 0x04) and self.regs[FIFO_WM_ENABLE] == 0x88
        self._edge(t, self.fifo.level // GYRO_FRAME, self.regs[GYRO_FIFO_CONFIG_0] & 0x7F, routed)

    def skipped_unseen(self, n: int) -> None:
        self.fifo.overflowed = True
        self.fifo.dropped += n

    def read_register(self, reg: int) -> int:
        if reg == FIFO_STATUS:
            return (OVERRUN if self.fifo.overflowed else 0) | (self.fifo.level // GYRO_FRAME)
        return self.regs[reg]

    def pop_fifo(self, n: int) -> list[int]:
        before = self.fifo.level // GYRO_FRAME
        got = self.fifo.pop(n)
        for _ in range(before - -(-self.fifo.level // GYRO_FRAME)):
            self.popped_truth.append(self.truth.popleft())
        self._above_wm = False
        return list(got) + [0] * (n - len(got))

    def next_watermark_time(self) -> float | None:
        rate, wm = self.rate_hz(), self.regs[GYRO_FIFO_CONFIG_0] & 0x7F
        if not rate or self._t0 is None or not wm:
            return None
        missing = max(0, wm - self.fifo.level // GYRO_FRAME)
        if missing == 0:
            return self.latched_t if self.latched_t is not None else self._t0
        return self._t0 + (self._k + missing) / rate
