"""The simulated MPU-9250: registers, byte FIFO and the I2C bypass to its AK8963, see
:mod:`ahrs_service.drivers.parts.mpu9250`.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY
from ahrs_service.drivers.parts.mpu9250 import (
    ACC_LSB_PER_G,
    ACCEL_CONFIG,
    ACCEL_XOUT_H,
    BYPASS_EN,
    CLKSEL_PLL,
    CONFIG,
    FIFO_BYTES,
    FIFO_COUNTH,
    FIFO_EN_REG,
    FIFO_MODE,
    FIFO_OFLOW,
    FIFO_R_W,
    GYRO_CONFIG,
    GYRO_LSB_PER_DPS,
    H_RESET,
    I2C_MST_EN,
    INT_ANYRD_2CLEAR,
    INT_PIN_CFG,
    INT_STATUS,
    PWR_MGMT_1,
    PWR_MGMT_2,
    RAW_DATA_RDY,
    SLEEP,
    SMPLRT_DIV,
    TEMP_LSB_PER_C,
    TEMP_OFFSET_C,
    TEMP_OUT_H,
    USER_CTRL,
    USER_FIFO_EN,
    USER_FIFO_RST,
    WHO_AM_I,
)
from ahrs_service.drivers.sim.register_device import (
    SimulatedRegisterDevice,
    counts_array,
    i16_bytes,
    to_counts,
)


class SimulatedMPU9250(SimulatedRegisterDevice):
    """Simulated MPU-9250: latches physics "gyr", "acc" and "temperature_c" at the sample rate.

    ``bypass_enabled()`` tells the bus whether the attached AK8963 is reachable.
    """

    CLOCK_ERROR = +0.0070  # this simulated unit runs 0.7 % fast
    PART = "MPU-9250"
    DEFAULT_ADDRESS = 0x68
    POWER_ON = {PWR_MGMT_1: CLKSEL_PLL, WHO_AM_I: 0x71}
    WRITABLE = frozenset(set(range(0x00, 0x3A)) | {USER_CTRL, PWR_MGMT_1, PWR_MGMT_2}
                         | set(range(0x63, 0x6A)) | {0x74} | set(range(0x77, 0x7F)))

    def __init__(self, source: Any = None, address: int | None = None, who_am_i: int = 0x71) -> None:
        self.who_am_i = who_am_i
        super().__init__(source, address)

    def reset_state(self, now: float) -> None:
        self.regs[WHO_AM_I] = self.who_am_i
        self.fifo = bytearray()
        self.fifo_overflowed = 0  # samples that did not fit, since power-on (for tests)
        self.fifo_discarded = 0  # samples a FIFO_RST emptied unread, since power-on (for tests)
        # (sample time s, physics "truth") of each sample in the FIFO, oldest first: what a
        # test or the simulated board compares the driver's rows with (not a register)
        self.fifo_samples: deque[tuple[float, Any]] = deque()
        if not self.regs[PWR_MGMT_1] & SLEEP:
            self.restart_measurement(now)  # the MPU-9250 samples from power-on

    def bypass_enabled(self) -> bool:
        return bool(self.regs[INT_PIN_CFG] & BYPASS_EN) and not self.regs[USER_CTRL] & I2C_MST_EN

    def rate_hz(self) -> float | None:
        if self.regs[PWR_MGMT_1] & SLEEP:
            return None
        dlpf = self.regs[CONFIG] & 0x07
        internal = 1000.0 if 1 <= dlpf <= 6 and not self.regs[GYRO_CONFIG] & 0x03 else 8000.0
        return internal / (1 + self.regs[SMPLRT_DIV])

    # ---------------------------------------------------------------- FIFO
    def fifo_enabled(self) -> bool:
        return bool(self.regs[USER_CTRL] & USER_FIFO_EN) and bool(self.regs[FIFO_EN_REG])

    def frame_bytes(self) -> int:
        """Bytes one sample writes: 6 for the accelerometer, 2 for TEMP, 2 per gyro axis."""
        en = self.regs[FIFO_EN_REG]
        return 2 * bin(en & 0x70).count("1") + (6 if en & 0x08 else 0) + (2 if en & 0x80 else 0)

    @property
    def fifo_frames(self) -> int:
        """Whole samples in the FIFO now (for tests)."""
        return len(self.fifo) // max(1, self.frame_bytes())

    def fifo_room(self) -> int | None:
        if not self.fifo_enabled():
            return None
        return (FIFO_BYTES - len(self.fifo)) // self.frame_bytes()

    def fifo_keeps_oldest(self) -> bool:
        return bool(self.regs[CONFIG] & FIFO_MODE)

    def fifo_dropped(self, n: int) -> None:
        self.fifo_overflowed += n
        self.regs[INT_STATUS] |= FIFO_OFLOW

    def _fifo_push(self) -> None:
        """One sample into the FIFO, from the data registers, in register order (§4.7)."""
        en = self.regs[FIFO_EN_REG]
        frame = bytearray()
        if en & 0x08:
            frame += self.regs[ACCEL_XOUT_H:ACCEL_XOUT_H + 6]
        if en & 0x80:
            frame += self.regs[TEMP_OUT_H:TEMP_OUT_H + 2]
        for bit, reg in ((0x40, 0x43), (0x20, 0x45), (0x10, 0x47)):
            if en & bit:
                frame += self.regs[reg:reg + 2]
        if len(self.fifo) + len(frame) > FIFO_BYTES:
            self.fifo_dropped(1)
            if self.fifo_keeps_oldest():
                return
            del self.fifo[:len(frame)]  # FIFO_MODE 0: the oldest sample makes room
            if self.fifo_samples:
                self.fifo_samples.popleft()
        self.fifo += frame
        self.fifo_samples.append((self.latched_t, (self.latched or {}).get("truth")))

    def latch_run(self, t: np.ndarray, period: float) -> None:
        """The samples of a run (due at the times ``t``, s, ascending) latched at once from
        the source's ``physics_block``: the data registers end with the last sample, as
        after :meth:`latch` of each, and with the FIFO on each sample's frame goes in, in
        order, the same bytes as :meth:`_fifo_push` writes, with the same room and overflow
        rules. Sources without ``physics_block``, and runs of one sample (a bus transfer
        shortly after the last: cheaper per sample than an array call), are latched sample
        by sample."""
        if self._physics_block is None or len(t) == 1:
            super().latch_run(t, period)
            return
        block = self._physics_block(t, period)
        n = len(t)
        a_lsb = STANDARD_GRAVITY / ACC_LSB_PER_G[(self.regs[ACCEL_CONFIG] >> 3) & 3]
        g_lsb = DEG2RAD / GYRO_LSB_PER_DPS[(self.regs[GYRO_CONFIG] >> 3) & 3]
        # the 14 data registers of each sample, 0x3B…0x48: ACCEL X Y Z, TEMP, GYRO X Y Z
        counts = np.empty((n, 7), np.int64)
        counts[:, 0:3] = counts_array(block.acc, a_lsb, -32768, 32767)
        counts[:, 3] = counts_array(block.temperature_c - TEMP_OFFSET_C, 1 / TEMP_LSB_PER_C, -32768, 32767)
        counts[:, 4:7] = counts_array(block.gyr, g_lsb, -32768, 32767)
        data = counts.astype(">i2").view(np.uint8).reshape(n, 14)
        self.regs[ACCEL_XOUT_H:ACCEL_XOUT_H + 14] = data[-1].tobytes()
        self.latched, self.latched_t = block.reading(n - 1), float(t[-1])
        self.samples_latched += n
        self.regs[INT_STATUS] |= RAW_DATA_RDY
        if self.fifo_enabled():
            self._fifo_push_run(data, t, block.truth)

    def _fifo_push_run(self, data: np.ndarray, t: np.ndarray, truths: list[Any]) -> None:
        """The frames of a run's samples into the FIFO, oldest first, as :meth:`_fifo_push`
        of each would put them: the data registers (``data``, (n, 14) bytes) in the FIFO_EN
        order (§4.7); a frame that does not fit is dropped (FIFO_MODE 1) or makes room by
        dropping the oldest (FIFO_MODE 0), each counted by :meth:`fifo_dropped`."""
        en = self.regs[FIFO_EN_REG]
        cols: list[int] = []
        if en & 0x08:
            cols += range(0, 6)  # ACCEL_XOUT_H … ACCEL_ZOUT_L
        if en & 0x80:
            cols += (6, 7)  # TEMP_OUT
        for bit, first in ((0x40, 8), (0x20, 10), (0x10, 12)):  # GYRO X, Y, Z
            if en & bit:
                cols += (first, first + 1)
        frame = len(cols)
        n = len(t)
        if frame == 0:  # FIFO_EN without a data bit: empty frames, one truth each
            self.fifo_samples.extend(zip(t.tolist(), truths))
            return
        fit = max(0, (FIFO_BYTES - len(self.fifo)) // frame)
        if n > fit and self.fifo_keeps_oldest():
            for _ in range(n - fit):
                self.fifo_dropped(1)
            n = fit
        self.fifo += data[:n, cols].tobytes()
        self.fifo_samples.extend(zip(t[:n].tolist(), truths[:n]))
        over = len(self.fifo) - FIFO_BYTES
        if over > 0:  # FIFO_MODE 0: the oldest samples make room, one frame each
            drop = -(-over // frame)
            for _ in range(drop):
                self.fifo_dropped(1)
            del self.fifo[:drop * frame]
            for _ in range(min(drop, len(self.fifo_samples))):
                self.fifo_samples.popleft()

    def pop_truth(self, n: int) -> list[tuple[float, Any]]:
        """(time s, truth) of the ``n`` oldest samples the host has read from the FIFO."""
        return [self.fifo_samples.popleft() for _ in range(min(n, len(self.fifo_samples)))]

    def read_register(self, reg: int) -> int:
        if reg == FIFO_R_W:
            if not self.fifo:
                return 0xFF  # reading an empty FIFO returns the last byte; 0xFF here
            v = self.fifo[0]
            del self.fifo[0]
            return v
        if reg == FIFO_COUNTH:
            return (len(self.fifo) >> 8) & 0x1F
        if reg == FIFO_COUNTH + 1:
            return len(self.fifo) & 0xFF
        return self.regs[reg]

    def next_pointer(self, reg: int) -> int:
        # a burst at FIFO_R_W keeps popping the FIFO (§4.31)
        return reg if reg == FIFO_R_W else (reg + 1) & 0xFF

    def bus_read(self, sub: int, n: int, now: float) -> list[int]:
        """A burst at FIFO_R_W pops ``n`` bytes at once (0xFF for each byte beyond the
        FIFO's end, as :meth:`read_register` returns one by one); others as every twin."""
        if sub != FIFO_R_W:
            return super().bus_read(sub, n, now)
        self.update(now)
        take = min(n, len(self.fifo))
        out = list(self.fifo[:take])
        del self.fifo[:take]
        out += [0xFF] * (n - take)
        self.on_read([FIFO_R_W] * n, now)
        return out

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == USER_CTRL and value & USER_FIFO_RST:
            self.fifo_discarded += self.fifo_frames
            self.fifo.clear()
            self.fifo_samples.clear()
            self.regs[USER_CTRL] = value & ~USER_FIFO_RST  # self-clearing
            self.regs[INT_STATUS] &= ~FIFO_OFLOW
            return
        if reg == PWR_MGMT_1 and value & H_RESET:
            self.power_on_reset(now)
        elif reg in (PWR_MGMT_1, CONFIG, SMPLRT_DIV, GYRO_CONFIG) and value != old:
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    def latch(self, phys: dict, t: float, skipped: int) -> None:
        a_lsb = STANDARD_GRAVITY / ACC_LSB_PER_G[(self.regs[ACCEL_CONFIG] >> 3) & 3]
        g_lsb = DEG2RAD / GYRO_LSB_PER_DPS[(self.regs[GYRO_CONFIG] >> 3) & 3]
        out = []
        for a in phys["acc"]:
            out.extend(i16_bytes(to_counts(a, a_lsb, -32768, 32767), True))
        temp = phys.get("temperature_c", TEMP_OFFSET_C)
        out.extend(i16_bytes(to_counts(temp - TEMP_OFFSET_C, 1 / TEMP_LSB_PER_C, -32768, 32767), True))
        for w in phys["gyr"]:
            out.extend(i16_bytes(to_counts(w, g_lsb, -32768, 32767), True))
        self.regs[ACCEL_XOUT_H:ACCEL_XOUT_H + 14] = bytes(out)
        self.regs[INT_STATUS] |= RAW_DATA_RDY
        if self.fifo_enabled():
            self._fifo_push()

    def on_read(self, regs: list[int], now: float) -> None:
        if INT_STATUS in regs or self.regs[INT_PIN_CFG] & INT_ANYRD_2CLEAR:
            # FIFO_OFLOW_INT clears on the INT_STATUS read too (§4.19); the FIFO stays as is
            self.regs[INT_STATUS] = 0
