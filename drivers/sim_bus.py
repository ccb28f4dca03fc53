"""What the simulated buses share (:class:`~ahrs_service.drivers.i2c.bus.SimulatedI2CBus`,
:class:`~ahrs_service.drivers.spi.bus.SimulatedSPIBus`): simulated register devices in slots
(an I2C address, an SPI chip select), the simulation clock, and fault injection — transfer
errors and a device that vanishes and comes back power-cycled.
"""

from __future__ import annotations

import errno
import functools
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # pragma: no cover
    from ahrs_service.drivers.i2c.device import SimulatedRegisterDevice


class SimulatedSlot:
    """A device on a simulated bus, with its fault-injection state."""

    __slots__ = ("device", "present", "visible_if", "pending_errors", "error_errno")

    def __init__(self, device: "SimulatedRegisterDevice",
                 visible_if: Callable[[], bool] | None = None) -> None:
        self.device = device
        self.present = True
        self.visible_if = visible_if
        self.pending_errors = 0
        self.error_errno = errno.EIO

    def injected_error(self, where: str) -> OSError | None:
        """The error of the next transfer when one was injected (counted down), else None."""
        if self.pending_errors <= 0:
            return None
        self.pending_errors -= 1
        return OSError(self.error_errno, f"{where}: injected transfer error")


def simulating(method: Callable[..., Any]) -> Callable[..., Any]:
    """Marks a simulated bus's method whose work is the simulated hardware's (a transfer, the
    catch-up of the parts' due samples): its thread CPU time is added to the bus's
    ``simulation_cpu_ns`` — what a real bus's parts would have done for nothing. Counted at
    the outermost such call only (one may call another)."""

    @functools.wraps(method)
    def counted(self: "SimulatedBusBase", *args: Any, **kwargs: Any) -> Any:
        if self._inside_simulation:
            return method(self, *args, **kwargs)
        self._inside_simulation = True
        start = time.thread_time_ns()
        try:
            return method(self, *args, **kwargs)
        finally:
            self.simulation_cpu_ns += time.thread_time_ns() - start
            self._inside_simulation = False

    return counted


class SimulatedBusBase:
    """The slots, clock and fault injection of a simulated bus (``clock.now()`` in s).

    ``simulation_cpu_ns``: thread CPU time (ns) spent inside the bus's transfers and in its
    parts' making of samples (:func:`simulating`): the simulated hardware's share of the
    process's CPU, which benchmarks take off to state the service's own work (/loop
    ``simulation_cpu_s``).
    """

    clock: Any
    name: str
    _slots: dict[int, SimulatedSlot]
    simulation_cpu_ns: int = 0
    _inside_simulation: bool = False

    def _init_clock(self, clock: Any, bus_kind: str) -> None:
        if not callable(getattr(clock, "now", None)):
            raise TypeError(f"{bus_kind} needs a clock with now() -> seconds, got {clock!r}")
        self.clock = clock
        self._slots = {}

    def inject_errors(self, key: int, count: int = 1, err: int = errno.EIO) -> None:
        """The next ``count`` transfers to the device at ``key`` (address or chip select)
        raise ``OSError(err)`` (a glitch on the wires)."""
        slot = self._slots[key]
        slot.pending_errors += int(count)
        slot.error_errno = err

    def set_present(self, key: int, present: bool, power_cycle: bool = True) -> None:
        """Makes the device at ``key`` vanish or come back; coming back with ``power_cycle``
        resets its registers to power-on values (it lost power): the driver must configure
        it again."""
        slot = self._slots[key]
        if present and not slot.present and power_cycle:
            slot.device.power_on_reset(self.clock.now())
        slot.present = bool(present)

    #: passes of :meth:`catch_up` at most: each makes the samples that came due during the last
    CATCH_UP_PASSES = 4

    def catch_up(self, device: "SimulatedRegisterDevice") -> None:
        """Lets ``device`` make the samples due by now before a transfer reaches it, then
        those that came due while it did (until a pass makes at most one, at most
        :attr:`CATCH_UP_PASSES` passes). Making a FIFO's worth of samples costs the simulation
        tens of ms on a busy host; a real part's samples cost the host nothing. Done inside
        the transfer, that cost fell between the FIFO level the transfer latched and the
        data read that follows it — where a real part leaves microseconds — and the FIFO
        overflowed in between (issue 15). Done first, it falls before the transfer, as a
        host delayed before its read would: the level then counts every sample made.
        Buses call it at each transfer and when the host reads their clock (it times a
        transfer next): the transfer's own time is then its own, as on a real bus, and the
        sensor clock's bounds stay tight (a transfer that took the simulation's 30 ms
        allowed its latch anywhere in them)."""
        for _ in range(self.CATCH_UP_PASSES):
            before = device.samples_due
            device.update(self.clock.now())
            if device.samples_due - before <= 1:
                return

    def now_ns(self) -> int:
        """The simulation clock's now, mapped to ns (``clock.to_ns`` when the clock has it)."""
        t = self.clock.now()
        to_ns = getattr(self.clock, "to_ns", None)
        return to_ns(t) if to_ns is not None else int(round(t * 1e9))

    def sleep(self, seconds: float) -> None:
        # simulated parts settle at once; tests move the clock themselves
        return None
