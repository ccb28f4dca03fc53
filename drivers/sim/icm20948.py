"""The simulated ICM-20948: register banks, FIFO packets and the auxiliary I2C master that
reads its AK09916: see :mod:`ahrs_service.drivers.parts.icm20948`.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np

from ahrs_service.drivers.device import DEG2RAD, STANDARD_GRAVITY
from ahrs_service.drivers.parts import ak09916
from ahrs_service.drivers.parts.icm20948 import (
    ACC_LSB,
    ACCEL_CONFIG,
    ACCEL_SMPLRT_DIV_1,
    ACCEL_SMPLRT_DIV_2,
    ACCEL_XOUT_H,
    BASE_RATE_HZ,
    CLKSEL_AUTO,
    DEVICE_RESET,
    EXT_SLV_SENS_DATA_00,
    FIFO_BYTES,
    FIFO_COUNTH,
    FIFO_EN_1,
    FIFO_EN_2,
    FIFO_EN_BIT,
    FIFO_MODE,
    FIFO_R_W,
    FIFO_RST,
    GYRO_CONFIG_1,
    GYRO_LSB,
    GYRO_SMPLRT_DIV,
    I2C_MST_CTRL,
    I2C_MST_EN,
    I2C_MST_STATUS,
    I2C_SLV0_ADDR,
    I2C_SLV0_CTRL,
    I2C_SLV0_REG,
    I2C_SLV4_ADDR,
    I2C_SLV4_CTRL,
    I2C_SLV4_DI,
    I2C_SLV4_DO,
    I2C_SLV4_REG,
    INT_STATUS_2,
    PACKET,
    PWR_MGMT_1,
    PWR_MGMT_2,
    READ,
    REG_BANK_SEL,
    SLEEP,
    SLV4_DONE,
    SLV_EN,
    USER_CTRL,
    WHO_AM_I,
    WHO_AM_I_VALUE,
)
from ahrs_service.drivers.sim.ak09916 import SimulatedAK09916
from ahrs_service.drivers.sim.bus import SimulatedI2CBus
from ahrs_service.drivers.sim.fifo import SimulatedFifo, SimulatedFifoDevice
from ahrs_service.drivers.sim.register_device import i16_bytes, to_counts


class SimulatedICM20948(SimulatedFifoDevice):
    """ICM-20948 twin: four user banks, the FIFO (snapshot mode, overflow flag), and an
    auxiliary I2C master on its own simulated bus carrying a :class:`SimulatedAK09916`."""

    PART = "ICM-20948"
    DEFAULT_ADDRESS = 0x68
    CLOCK_ERROR = -0.0088

    WRITABLE_BANK = {
        0: frozenset({USER_CTRL, PWR_MGMT_1, PWR_MGMT_2, FIFO_EN_1, FIFO_EN_2, FIFO_RST, FIFO_MODE, 0x0F, 0x10, 0x11}),
        2: frozenset({GYRO_SMPLRT_DIV, GYRO_CONFIG_1, ACCEL_SMPLRT_DIV_1, ACCEL_SMPLRT_DIV_2, ACCEL_CONFIG}),
        3: frozenset({I2C_MST_CTRL, I2C_SLV0_ADDR, I2C_SLV0_REG, I2C_SLV0_CTRL, 0x06,
                      I2C_SLV4_ADDR, I2C_SLV4_REG, I2C_SLV4_CTRL, I2C_SLV4_DO}),
    }

    def __init__(self, source: Any = None, address: int | None = None, clock_error: float | None = None,
                 clock: Any = None) -> None:
        self._clock = clock
        self.aux = None
        super().__init__(source, address, clock_error)
        self.aux = SimulatedI2CBus(clock if clock is not None else _Zero(), name="icm20948-aux")
        self.mag = self.aux.attach(SimulatedAK09916(source))

    def reset_state(self, now: float) -> None:
        self.banks = [bytearray(128) for _ in range(4)]
        self.banks[0][WHO_AM_I] = WHO_AM_I_VALUE
        self.banks[0][PWR_MGMT_1] = SLEEP | CLKSEL_AUTO
        self.banks[2][GYRO_CONFIG_1] = 0x01
        self.banks[2][ACCEL_CONFIG] = 0x01
        self.fifo = SimulatedFifo(FIFO_BYTES, stop_on_full=True, frame=PACKET)
        self.truth: deque = deque()
        self.popped_truth: list = []
        if self.aux is not None:
            self.aux.device(ak09916.ADDRESS).power_on_reset(now)

    def take_popped_truth(self) -> list:
        out, self.popped_truth = self.popped_truth, []
        return out

    @property
    def bank(self) -> int:
        return (self.banks[0][REG_BANK_SEL] >> 4) & 3

    def nominal_rate_hz(self) -> float | None:
        if self.banks[0][PWR_MGMT_1] & SLEEP:
            return None
        return BASE_RATE_HZ / (1 + self.banks[2][GYRO_SMPLRT_DIV])

    def backlog_limit(self) -> int:
        return FIFO_BYTES // PACKET + 1

    def fifo_on(self) -> bool:
        return bool(self.banks[0][USER_CTRL] & FIFO_EN_BIT) and bool(self.banks[0][FIFO_EN_2] & 0x1E)

    # ---------------------------------------------------------------- bus side
    def bus_read(self, sub: int, n: int, now: float) -> list[int]:
        self.update(now)
        bank = self.bank
        if bank == 0 and sub == FIFO_R_W:
            before = self.fifo.level // PACKET
            got = self.fifo.pop(n)
            for _ in range(before - -(-self.fifo.level // PACKET)):
                self.popped_truth.append(self.truth.popleft())
            return list(got) + [0xFF] * (n - len(got))
        out = []
        for i in range(n):
            reg = (sub + i) & 0x7F
            if reg == REG_BANK_SEL:
                out.append(self.banks[0][REG_BANK_SEL])
            elif bank == 0 and reg == FIFO_COUNTH:
                out.append(self.fifo.level >> 8)
            elif bank == 0 and reg == FIFO_COUNTH + 1:
                out.append(self.fifo.level & 0xFF)
            elif bank == 0 and reg == INT_STATUS_2:
                out.append(0x1F if self.fifo.overflowed else 0)
                self.fifo.overflowed = False  # cleared on read
            elif bank == 0 and reg == I2C_MST_STATUS:
                out.append(self.banks[0][reg])
                self.banks[0][reg] = 0
            else:
                out.append(self.banks[bank][reg])
        return out

    def bus_write(self, sub: int, data: list[int], now: float) -> None:
        self.update(now)
        for i, value in enumerate(data):
            reg = (sub + i) & 0x7F
            if reg == REG_BANK_SEL:
                self.banks[0][REG_BANK_SEL] = value & 0x30
                continue
            bank = self.bank
            if reg not in self.WRITABLE_BANK.get(bank, ()):
                continue
            old = self.banks[bank][reg]
            self.banks[bank][reg] = value
            self._on_write(bank, reg, value, old, now)

    def _on_write(self, bank: int, reg: int, value: int, old: int, now: float) -> None:
        if bank == 0 and reg == PWR_MGMT_1 and value & DEVICE_RESET:
            self.power_on_reset(now)
        elif bank == 0 and reg == FIFO_RST and value & 0x1F:
            self.fifo.clear()
            self.truth.clear()
        elif (bank, reg) in ((0, PWR_MGMT_1), (2, GYRO_SMPLRT_DIV)) and value != old:
            if self.rate_hz():
                self.restart_measurement(now)
            else:
                self.stop_measurement()
        elif bank == 3 and reg == I2C_SLV4_CTRL and value & SLV_EN:
            self._slave4(now)

    def _slave4(self, now: float) -> None:
        """One aux-bus transfer of slave 4 (the part's I2C master runs it, then sets DONE)."""
        b3 = self.banks[3]
        addr, reg = b3[I2C_SLV4_ADDR] & 0x7F, b3[I2C_SLV4_REG]
        self.aux.clock = _At(now)
        try:
            if b3[I2C_SLV4_ADDR] & READ:
                b3[I2C_SLV4_DI] = self.aux.read_byte_data(addr, reg)
            else:
                self.aux.write_byte_data(addr, reg, b3[I2C_SLV4_DO])
        except OSError:
            pass  # a NACK: DONE still set, as on the part (it would also set I2C_SLV4_NACK)
        b3[I2C_SLV4_CTRL] &= ~SLV_EN
        self.banks[0][I2C_MST_STATUS] |= SLV4_DONE

    # ---------------------------------------------------------------- samples
    def latch(self, phys: dict, t: float, skipped: int) -> None:
        b0, b2, b3 = self.banks[0], self.banks[2], self.banks[3]
        a_lsb = STANDARD_GRAVITY / ACC_LSB[(b2[ACCEL_CONFIG] >> 1) & 3]
        g_lsb = DEG2RAD / GYRO_LSB[(b2[GYRO_CONFIG_1] >> 1) & 3]
        out = []
        for a in phys["acc"]:
            out.extend(i16_bytes(to_counts(a, a_lsb, -32768, 32767), True))
        for w in phys["gyr"]:
            out.extend(i16_bytes(to_counts(w, g_lsb, -32768, 32767), True))
        b0[ACCEL_XOUT_H:ACCEL_XOUT_H + 12] = bytes(out)
        ext = b""
        if b0[USER_CTRL] & I2C_MST_EN and b3[I2C_SLV0_CTRL] & SLV_EN and b3[I2C_SLV0_ADDR] & READ:
            self.aux.clock = _At(t)
            n = b3[I2C_SLV0_CTRL] & 0x0F
            try:
                ext = bytes(self.aux.read_i2c_block_data(b3[I2C_SLV0_ADDR] & 0x7F, b3[I2C_SLV0_REG], n))
            except OSError:
                ext = bytes(n)
            b0[EXT_SLV_SENS_DATA_00:EXT_SLV_SENS_DATA_00 + n] = ext
        if self.fifo_on():
            pkt = bytes(out) + (ext if b0[FIFO_EN_1] & 0x01 else b"")
            if self.fifo.push(pkt):
                truth = phys.get("truth")
                self.truth.append(None if truth is None else np.asarray(
                    truth["q"] if isinstance(truth, dict) else truth.q, dtype=float))

    def skipped_unseen(self, n: int) -> None:
        self.fifo.overflowed = True
        self.fifo.dropped += n


class _At:
    """A clock stopped at ``t``: the aux bus runs on the part's sample instants."""

    def __init__(self, t: float) -> None:
        self.t = t

    def now(self) -> float:
        return self.t


class _Zero(_At):
    def __init__(self) -> None:
        super().__init__(0.0)
