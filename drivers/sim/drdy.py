"""A data-ready line wired to a simulated part's INT1 output (see
:mod:`ahrs_service.drivers.buses.drdy`).
"""

from __future__ import annotations

import time
from typing import Any

from ahrs_service.drivers.buses.drdy import DataReadyLine


class SimulatedDataReadyLine(DataReadyLine):
    """The INT1 line of a simulated part (one with ``int1`` and ``next_watermark_time()``).

    clock: the simulation clock; ``wait`` sleeps on it — ``clock.advance`` on a
    ``ManualClock`` (tests), ``time.sleep`` on a real-time clock.
    """

    def __init__(self, device: Any, clock: Any, name: str = "sim-gpio:0") -> None:
        super().__init__()
        self.device, self.clock, self.name = device, clock, name
        self._pending = 0
        device.int1 = self._raise

    def _raise(self, t: float) -> None:
        self._pending += 1
        to_ns = getattr(self.clock, "to_ns", None)
        self.last_edge_ns = to_ns(t) if to_ns else int(t * 1e9)

    def _sleep(self, dt: float) -> None:
        if dt <= 0:
            return
        advance = getattr(self.clock, "advance", None)
        if advance is not None:
            advance(dt)
        else:
            time.sleep(dt)

    def wait(self, timeout_s: float) -> bool:
        now = self.clock.now()
        self.device.update(now)
        if not self._pending:
            t_wm = self.device.next_watermark_time()
            if t_wm is not None and t_wm <= now:
                return True  # above the watermark already (the edge was taken): data waiting
            if t_wm is None or t_wm - now > timeout_s:
                self._sleep(timeout_s)
                self.device.update(self.clock.now())
            else:
                self._sleep(t_wm - now)
                self.device.update(max(self.clock.now(), t_wm))
        if self._pending:
            self.edges += self._pending
            self._pending = 0
            return True
        self.timeouts += 1
        return False
