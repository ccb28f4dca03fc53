"""The 32-level FIFO of ST's L3G4200D, L3GD20 and LSM303DLHC accelerometer: driver and twin side.

The three parts share the FIFO block and its registers (L3G4200D datasheet Doc ID 17116
§5.2 "FIFO" and §7.6, 7.16, 7.17; L3GD20 Doc ID 022116 §4.2 and the same registers;
LSM303DLHC Doc ID 018771 §3.3 "FIFO" and CTRL_REG5_A, FIFO_CTRL_REG_A, FIFO_SRC_REG_A):

=====  =============  ====================================================================
0x24   CTRL_REG5      bit 6 FIFO_EN: the FIFO is on (off: the output registers hold the
                      newest sample, as in polling)
0x2E   FIFO_CTRL_REG  FM2:0 in bits 7:5 on the gyroscopes, FM1:0 in bits 7:6 (bit 5 TR)
                      on the LSM303DLHC, the same numbers: 0 bypass (FIFO empty and
                      off), 1 FIFO (stops when full), 2 stream (a full FIFO overwrites its
                      oldest sample); WTM4:0 / FTH4:0 in bits 4:0, the watermark level
0x2F   FIFO_SRC_REG   bit 7 WTM (level ≥ watermark), bit 6 OVRN (the FIFO is completely
                      filled: 32 samples), bit 5 EMPTY, FSS4:0 the stored level (31 with
                      OVRN set: the driver takes OVRN as 32 samples, whichever the part
                      reports)
0x28…  OUT_X_L…       each sample is X, Y, Z (6 bytes); with the FIFO on they read the
0x2D   OUT_Z_H        oldest stored sample, and an auto-increment read that passes OUT_Z_H
                      rolls back to OUT_X_L with the next sample: one transfer reads as many
                      whole samples as it has bytes for (5 in a 32-byte SMBus block)
=====  =============  ====================================================================

The driver runs the FIFO in stream mode: a host that stops longer than 32 samples finds the
newest 32, the oldest ones overwritten; the overrun is flagged only as "filled", so the loss
is estimated from the sensor clock (:class:`~ahrs_service.drivers.fifo.FifoTimeline`).
The FIFO is emptied by switching to bypass mode and back (§5.2.1: bypass resets it).

The ADXL345's 32-entry FIFO (:mod:`.adxl345`) numbers its modes alike and holds the same
X, Y, Z frames: it shares the mode-only parts, :class:`FrameFifoDriver` (reset, burst
decode) and :class:`SimulatedFrameFifoTwin` (the twin's FIFO hooks), not the ST registers.
"""

from __future__ import annotations

import numpy as np

from ahrs_service.drivers.buses.i2c import SMBUS_BLOCK_MAX
from ahrs_service.drivers.device import FifoLayout, FifoStatus

CTRL_REG5, FIFO_CTRL_REG, FIFO_SRC_REG, OUT_X_L = 0x24, 0x2E, 0x2F, 0x28
OUT_Z_H = OUT_X_L + 5
FIFO_EN = 0x40
FM_BYPASS, FM_FIFO, FM_STREAM = 0b000, 0b001, 0b010
WTM_MASK = 0x1F
SRC_WTM, SRC_OVRN, SRC_EMPTY = 0x80, 0x40, 0x20
FIFO_FRAMES = 32
FRAME_BYTES = 6
#: how a driver reads the FIFO: auto-increment bursts from OUT_X_L, 5 whole samples a block
FIFO_LAYOUT = FifoLayout(depth_frames=FIFO_FRAMES, frame_bytes=FRAME_BYTES,
                         data_register=0x80 | OUT_X_L,
                         frames_per_transfer=SMBUS_BLOCK_MAX // FRAME_BYTES)


class FrameFifoDriver:
    """Driver side of a 32-sample FIFO of X, Y, Z frames (little-endian counts) whose control
    register holds the mode at ``FM_SHIFT`` (0 bypass, 2 stream) above a 5-bit watermark: the
    ST parts' FIFO_CTRL_REG and the ADXL345's FIFO_CTL. Mixed into the parts' drivers (their
    :class:`~ahrs_service.drivers.device.RegisterDevice` base provides ``write_u8`` and
    ``read_fifo_frames``; they set ``fifo_watermark``)."""

    #: the FIFO's control register and where its mode sits in it
    FIFO_CTRL = FIFO_CTRL_REG
    FM_SHIFT = 5
    fifo_layout = FIFO_LAYOUT

    def fifo_reset(self) -> None:
        """Empties the FIFO: bypass mode, then stream mode again with the watermark."""
        self.write_u8(self.FIFO_CTRL, FM_BYPASS << self.FM_SHIFT)  # type: ignore[attr-defined]
        self.write_u8(self.FIFO_CTRL, FM_STREAM << self.FM_SHIFT | self.fifo_watermark)  # type: ignore[attr-defined]

    def read_fifo(self, frames: int) -> np.ndarray:
        """``frames`` samples, oldest first: (frames, 3) int64 counts, little-endian."""
        data = self.read_fifo_frames(self.fifo_layout, frames)  # type: ignore[attr-defined]
        return np.frombuffer(data, dtype="<i2").reshape(frames, 3).astype(np.int64)


class STFifoDriver(FrameFifoDriver):
    """Driver side, mixed into the ST parts' drivers (their
    :class:`~ahrs_service.drivers.device.RegisterDevice` base provides ``write_u8``,
    ``read_u8``, ``read_fifo_frames`` and ``transport``); :meth:`fifo_reset`
    (§5.2.1: bypass resets it) and :meth:`read_fifo` (BLE 0) are :class:`FrameFifoDriver`'s.
    FM sits in FIFO_CTRL_REG at bits 7:5 on the gyroscopes, 7:6 on the LSM303DLHC."""

    def configure_fifo(self, watermark: int) -> None:
        """FIFO on in stream mode with the watermark (1 … 31 samples), emptied."""
        if not 1 <= watermark < FIFO_FRAMES:
            raise ValueError(f"{self.PART}: FIFO watermark must be 1…{FIFO_FRAMES - 1}, got {watermark}")  # type: ignore[attr-defined]
        self.fifo_watermark = int(watermark)
        self.write_u8(CTRL_REG5, FIFO_EN)  # type: ignore[attr-defined]
        self.fifo_reset()

    def fifo_status(self) -> FifoStatus:
        """Stored samples and whether the FIFO had filled (FIFO_SRC_REG, one byte)."""
        t = self.transport.now_ns()  # type: ignore[attr-defined]
        src = self.read_u8(FIFO_SRC_REG)  # type: ignore[attr-defined]
        if src & SRC_OVRN:
            return FifoStatus(FIFO_FRAMES, True, t)
        return FifoStatus(0 if src & SRC_EMPTY else src & 0x1F, False, t)
