"""The simulated ICM-42688-P: its registers and hi-res FIFO packets, behind the driver of
:mod:`ahrs_service.drivers.parts.icm42688p`.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY
from ahrs_service.drivers.parts.icm42688p import (
    ACC_REG_LSB,
    ACCEL_CONFIG0,
    DATA_RDY_INT,
    DEVICE_CONFIG,
    FIFO_ACCEL_EN,
    FIFO_BYTES,
    FIFO_CONFIG,
    FIFO_CONFIG1,
    FIFO_CONFIG2,
    FIFO_CONFIG3,
    FIFO_COUNTH,
    FIFO_COUNTL,
    FIFO_DATA,
    FIFO_FLUSH,
    FIFO_FULL_INT,
    FIFO_GYRO_EN,
    FIFO_MODE_MASK,
    FIFO_THS_INT,
    FIFO_THS_INT1_EN,
    GYRO_CONFIG0,
    GYRO_REG_LSB,
    HEADER_EMPTY,
    HIRES_ACC_LSB_PER_G,
    HIRES_GYRO_LSB_PER_DPS,
    HIRES_HEADER,
    INT_ASYNC_RESET,
    INT_CONFIG,
    INT_CONFIG1,
    INT_SOURCE0,
    INT_STATUS,
    INTF_CONFIG0,
    ODR_HZ,
    PACKET,
    PWR_MGMT0,
    REG_BANK_SEL,
    RESET_DONE_INT,
    SIGNAL_PATH_RESET,
    SOFT_RESET,
    TEMP_DATA1,
    TEMP_LSB_PER_C,
    TEMP_OFFSET_C,
    TMST_CONFIG,
    WHO_AM_I,
    WHO_AM_I_VALUE,
)
from ahrs_service.drivers.sim.fifo import SimulatedFifo, SimulatedFifoDevice
from ahrs_service.drivers.sim.register_device import i16_bytes, to_counts


class SimulatedICM42688P(SimulatedFifoDevice):
    """ICM-42688-P twin: bank-0 registers above, the 2 KB FIFO with hi-res packets, the
    watermark and stop-on-full overflow, a 16-bit µs timestamp on the part's clock, INT1.

    ``int1``: a callable ``(t)`` the simulated data-ready line attaches; called when the FIFO
    level rises to the watermark (or the FIFO fills) with FIFO_THS/FULL routed to INT1 and
    INT_CONFIG1.INT_ASYNC_RESET cleared (the datasheet only says the pin does not operate
    properly with it set; the twin models that as no edges, so a driver that forgets it
    is caught).
    """

    PART = "ICM-42688-P"
    DEFAULT_ADDRESS = 0x68
    CLOCK_ERROR = +0.0042  # this unit's RC oscillator runs 0.42 % fast
    POWER_ON = {WHO_AM_I: WHO_AM_I_VALUE, INTF_CONFIG0: 0x30, GYRO_CONFIG0: 0x06,
                ACCEL_CONFIG0: 0x06, INT_SOURCE0: 0x10, FIFO_CONFIG1: 0x00, TMST_CONFIG: 0x23,
                INT_CONFIG: 0x00, INT_CONFIG1: INT_ASYNC_RESET, INT_STATUS: RESET_DONE_INT}
    WRITABLE = frozenset({DEVICE_CONFIG, INT_CONFIG, FIFO_CONFIG, SIGNAL_PATH_RESET, INTF_CONFIG0,
                          PWR_MGMT0, GYRO_CONFIG0, ACCEL_CONFIG0, TMST_CONFIG, FIFO_CONFIG1,
                          FIFO_CONFIG2, FIFO_CONFIG3, INT_CONFIG1, INT_SOURCE0, REG_BANK_SEL})

    def __init__(self, source: Any = None, address: int | None = None, clock_error: float | None = None) -> None:
        self.int1 = None
        super().__init__(source, address, clock_error)

    def reset_state(self, now: float) -> None:
        self.fifo = SimulatedFifo(FIFO_BYTES, stop_on_full=True, frame=PACKET)
        self.truth: deque = deque()  # the true attitude of each packet in the FIFO (simulation only)
        self.popped_truth: list = []  # … of the packets read out since take_popped_truth()
        self._above_wm = False
        self._data_due = False  # a sample latched since the data registers were filled

    # ---------------------------------------------------------------- configuration
    def nominal_rate_hz(self) -> float | None:
        if (self.regs[PWR_MGMT0] & 0x0C) != 0x0C:  # gyro not in low-noise mode
            return None
        return ODR_HZ.get(self.regs[GYRO_CONFIG0] & 0x0F)

    def fifo_enabled(self) -> bool:
        return (self.regs[FIFO_CONFIG] & FIFO_MODE_MASK) != 0 and \
            (self.regs[FIFO_CONFIG1] & (FIFO_GYRO_EN | FIFO_ACCEL_EN)) != 0

    def watermark_bytes(self) -> int:
        return self.regs[FIFO_CONFIG2] | (self.regs[FIFO_CONFIG3] & 0x0F) << 8

    def backlog_limit(self) -> int:
        return FIFO_BYTES // PACKET + 1 if self.fifo_enabled() else 1

    def on_write(self, reg: int, value: int, old: int, now: float) -> None:
        if reg == DEVICE_CONFIG and value & SOFT_RESET:
            self.power_on_reset(now)
        elif reg == SIGNAL_PATH_RESET and value & FIFO_FLUSH:
            self.fifo.clear()
            self.truth.clear()
            self._above_wm = False
            self.regs[SIGNAL_PATH_RESET] = 0
        elif reg in (PWR_MGMT0, GYRO_CONFIG0) and value != old:
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()

    # ---------------------------------------------------------------- samples
    def latch(self, phys: dict, t: float, skipped: int) -> None:
        # the data registers show the newest sample (``latched``) when they are read: filled
        # then (_fill_data_registers), not for every sample — most are only read through the
        # FIFO, and filling them was about half of latching a sample (29 → 22 µs a sample
        # for the whole twin at 8 kHz, benchmarks/README.md)
        self._data_due = True
        self.regs[INT_STATUS] |= DATA_RDY_INT
        if self.fifo_enabled():
            self._push(phys, t, phys.get("temperature_c", TEMP_OFFSET_C))

    def _fill_data_registers(self) -> None:
        """TEMP_DATA1 … GYRO_DATA_Z0 (16-bit, big-endian, configured FS) from the newest sample."""
        self._data_due = False
        phys = self.latched
        if phys is None:
            return
        g_lsb = DEG2RAD / (GYRO_REG_LSB[(self.regs[GYRO_CONFIG0] >> 5) & 3])
        a_lsb = STANDARD_GRAVITY / (ACC_REG_LSB[(self.regs[ACCEL_CONFIG0] >> 5) & 3])
        temp_c = phys.get("temperature_c", TEMP_OFFSET_C)
        regs = self.regs
        out = list(i16_bytes(to_counts(temp_c - TEMP_OFFSET_C, 1 / TEMP_LSB_PER_C, -32768, 32767), True))
        for a in phys["acc"]:
            out.extend(i16_bytes(to_counts(a, a_lsb, -32768, 32767), True))
        for w in phys["gyr"]:
            out.extend(i16_bytes(to_counts(w, g_lsb, -32768, 32767), True))
        regs[TEMP_DATA1:TEMP_DATA1 + 14] = bytes(out)

    def _push(self, phys: dict, t: float, temp_c: float) -> None:
        # 18-bit accel / 19-bit gyro counts at the hi-res sensitivities, left-aligned in 20 bits
        acc = [to_counts(a, STANDARD_GRAVITY / HIRES_ACC_LSB_PER_G, -(1 << 17), (1 << 17) - 1) << 2
               for a in phys["acc"]]
        gyr = [to_counts(w, DEG2RAD / HIRES_GYRO_LSB_PER_DPS, -(1 << 18), (1 << 18) - 1) << 1
               for w in phys["gyr"]]
        temp = to_counts(temp_c - TEMP_OFFSET_C, 1 / TEMP_LSB_PER_C, -32768, 32767) & 0xFFFF
        # the timestamp counts µs of the part's own clock: k samples of 1/ODR nominal each
        tmst = int(round(self._k_latched() * 1e6 / self.nominal_rate_hz())) & 0xFFFF
        pkt = bytearray(PACKET)
        pkt[0] = HIRES_HEADER
        for i in range(3):
            a, g = acc[i] & 0xFFFFF, gyr[i] & 0xFFFFF
            pkt[1 + 2 * i], pkt[2 + 2 * i] = a >> 12, (a >> 4) & 0xFF
            pkt[7 + 2 * i], pkt[8 + 2 * i] = g >> 12, (g >> 4) & 0xFF
            pkt[17 + i] = (a & 0x0F) << 4 | (g & 0x0F)
        pkt[13], pkt[14] = temp >> 8, temp & 0xFF
        pkt[15], pkt[16] = tmst >> 8, tmst & 0xFF
        self._push_packet(bytes(pkt), t, phys)

    def _k_latched(self) -> int:
        # update() sets latched_t before calling latch: recover the sample number from it
        return int(round((self.latched_t - self._t0) * self.rate_hz()))

    def _push_packet(self, pkt: bytes, t: float, phys: dict) -> None:
        fifo = self.fifo
        if not fifo.push(pkt):
            self.regs[INT_STATUS] |= FIFO_FULL_INT
        else:
            self.truth.append(_truth_q(phys))
        if fifo.level >= self.watermark_bytes() > 0:
            self.regs[INT_STATUS] |= FIFO_THS_INT
            if not self._above_wm:
                self._above_wm = True
                if self.int1 is not None and self.regs[INT_SOURCE0] & FIFO_THS_INT1_EN \
                        and not self.regs[INT_CONFIG1] & INT_ASYNC_RESET:
                    self.int1(t)

    def take_popped_truth(self) -> list:
        """The true attitudes of the packets read since the last call, oldest first."""
        out, self.popped_truth = self.popped_truth, []
        return out

    def skipped_unseen(self, n: int) -> None:
        self.fifo.overflowed = True
        self.fifo.dropped += n
        self.regs[INT_STATUS] |= FIFO_FULL_INT

    def next_watermark_time(self) -> float | None:
        """When the FIFO reaches its watermark (simulation time), None if never."""
        rate, wm = self.rate_hz(), self.watermark_bytes()
        if not rate or self._t0 is None or not self.fifo_enabled() or wm == 0:
            return None
        missing = max(0, math.ceil((wm - self.fifo.level) / PACKET))
        if missing == 0:
            return self.latched_t if self.latched_t is not None else self._t0
        return self._t0 + (self._k + missing) / rate

    # ---------------------------------------------------------------- bus side
    def bus_read(self, sub: int, n: int, now: float) -> list[int]:
        self.update(now)
        if self._data_due and sub < TEMP_DATA1 + 14 and sub + n > TEMP_DATA1:
            self._fill_data_registers()
        out: list[int] = []
        reg = sub
        while len(out) < n:
            if reg == FIFO_DATA:  # the FIFO port: pops, never increments
                out.extend(self._pop_fifo(n - len(out)))
                break
            if reg == INT_STATUS:
                out.append(self.regs[INT_STATUS])
                self.regs[INT_STATUS] = 0  # clear on read
            elif reg == FIFO_COUNTH:
                level = self.fifo.level
                self._count_latch = level
                out.append(level >> 8)
            elif reg == FIFO_COUNTL:
                out.append(getattr(self, "_count_latch", self.fifo.level) & 0xFF)
            else:
                out.append(self.regs[reg])
            reg = (reg + 1) & 0x7F
        return out

    def _pop_fifo(self, n: int) -> list[int]:
        before = self.fifo.level // PACKET
        got = self.fifo.pop(n)
        for _ in range(before - -(-self.fifo.level // PACKET)):
            self.popped_truth.append(self.truth.popleft())
        if self.fifo.level < self.watermark_bytes():
            self._above_wm = False
        if not self.fifo.level:
            self.fifo.overflowed = False
        # reading past the data: an empty-FIFO header then 0x00 (§6.1: header bit 7)
        return list(got) + ([HEADER_EMPTY] + [0] * (n - len(got) - 1) if len(got) < n else [])


def _truth_q(phys: dict) -> np.ndarray | None:
    truth = phys.get("truth")
    if truth is None:
        return None
    return np.asarray(truth["q"] if isinstance(truth, dict) else truth.q, dtype=float)
