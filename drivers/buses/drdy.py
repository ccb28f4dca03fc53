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
* :class:`~ahrs_service.drivers.sim.drdy.SimulatedDataReadyLine` — wired to a simulated part's INT1 output: the part
  raises it at its watermark; waiting advances the simulation to that moment.
"""

from __future__ import annotations

import abc


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
