"""The data-ready (FIFO watermark) interrupt line: libgpiod 2, or simulated.

The service loop waits on this line instead of a timer when ``source.drdy_gpio`` names one
(``"gpiochip0:17"``: chip, line offset). :meth:`DataReadyLine.wait` returns True when a
rising edge came within the timeout (the part's FIFO reached its watermark), False on a
timeout — the loop then polls as on a timer, so a missed or unwired interrupt costs
latency, never samples.

* :class:`GpiodLine` — ``gpiod.request_lines`` with rising-edge detection;
  ``wait_edge_events(timeout)`` then ``read_edge_events()``. Event times are the kernel's
  CLOCK_MONOTONIC stamps of the edge (``last_edge_ns``). Install with
  ``pip install 'ahrs-service[hardware]'`` (the libgpiod 2 bindings, ``gpiod>=2``).
* :class:`SimulatedDataReadyLine` — wired to a simulated part's INT1 output: the part
  raises it at its watermark; waiting advances the simulation to that moment.
"""

from __future__ import annotations

import abc
import time
from typing import Any


def parse_line_spec(spec: str) -> tuple[str, int]:
    """``"gpiochip0:17"`` → (``"/dev/gpiochip0"``, 17); ValueError naming the key otherwise."""
    chip, sep, offset = spec.rpartition(":")
    if not sep or not chip or not offset.isdigit():
        raise ValueError(f"source.drdy_gpio: {spec!r} is not '<chip>:<line>', e.g. 'gpiochip0:17'")
    path = chip if chip.startswith("/") else f"/dev/{chip}"
    return path, int(offset)


class DataReadyLine(abc.ABC):
    """A rising-edge interrupt input. ``edges`` counts edges, ``timeouts`` waits without one."""

    name = "drdy"

    def __init__(self) -> None:
        self.edges = 0
        self.timeouts = 0
        self.last_edge_ns: int | None = None

    @abc.abstractmethod
    def wait(self, timeout_s: float) -> bool:
        """Blocks until a rising edge (True) or ``timeout_s`` seconds pass (False)."""

    def close(self) -> None:
        """Releases the line."""


class GpiodLine(DataReadyLine):
    """One line of a GPIO chip through the libgpiod 2 Python bindings."""

    def __init__(self, spec: str, consumer: str = "ahrs-service") -> None:
        super().__init__()
        import gpiod  # the hardware module only where a line is configured
        from gpiod.line import Direction, Edge

        self.chip_path, self.offset = parse_line_spec(spec)
        self.name = f"{self.chip_path}:{self.offset}"
        try:
            self._request = gpiod.request_lines(
                self.chip_path, consumer=consumer,
                config={self.offset: gpiod.LineSettings(direction=Direction.INPUT,
                                                        edge_detection=Edge.RISING)})
        except FileNotFoundError as exc:
            raise FileNotFoundError(
                f"source.drdy_gpio: GPIO chip {self.chip_path} does not exist (`gpiodetect` lists "
                f"the chips)") from exc
        except PermissionError as exc:
            raise PermissionError(
                f"source.drdy_gpio: no permission to open {self.chip_path}: add the service user "
                f"to the 'gpio' group (`sudo usermod -aG gpio $USER`)") from exc
        except OSError as exc:
            raise OSError(exc.errno, f"source.drdy_gpio: cannot request line {self.name}: "
                                     f"{exc.strerror or exc} (in use by another program? `gpioinfo`)") from exc

    def wait(self, timeout_s: float) -> bool:
        if not self._request.wait_edge_events(timeout_s):
            self.timeouts += 1
            return False
        events = self._request.read_edge_events()
        if events:
            self.edges += len(events)
            self.last_edge_ns = int(events[-1].timestamp_ns)
        return True

    def close(self) -> None:
        self._request.release()


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
