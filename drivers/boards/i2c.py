"""I2C IMU boards as :class:`~ahrs_service.core.samples.ImuSource`: GY-80, MinIMU-9 v2, MPU-9250.

A board is its parts (gyro, accelerometer, magnetometer drivers) on one :class:`I2CBus`.
``read()`` returns one :class:`ImuSample` per new gyro sample (the gyro's data-ready bit
drives the sample rate; the same reading is never returned twice), with:

* ``gyr`` rad/s, ``acc`` m/s² (specific force), ``mag`` µT — in the board's axes (the
  sensors' own axes; mounting rotation and calibration are applied elsewhere);
* ``mag`` only when the magnetometer has a new reading (``MAG_NEW``), else None;
* ``t_ns``: ``time.monotonic_ns()`` right after the gyro read, or the simulation clock in
  ns on a :class:`SimulatedI2CBus`, where ``truth_q`` is the true attitude of the gyro sample;
* ``raw``: the counts as read ({"gyr", "acc", "mag", "temp"});
* flags: a saturated or non-finite reading gets ``*_SATURATED`` / loses ``*_VALID``.

Faults: transient ``OSError`` is retried and counted (``diagnostics.bus_errors``,
``retries``) and never raised from ``read()``. A part that keeps failing is marked lost
(``diagnostics.device_lost``, ``last_error``); the board retries its configuration at most
every ``reinit_period_s`` (bus clock) and counts ``reinitialisations`` when it is back. A lost
magnetometer leaves gyro/accelerometer samples flowing; a lost gyro or accelerometer stops
them until it returns.

Factories: :func:`make_board` (hardware, ``/dev/i2c-N``) and :func:`make_simulated_board`
(a simulator behind simulated register devices on a :class:`SimulatedI2CBus`).
"""

from __future__ import annotations

import inspect
from collections import deque
from typing import Any

import numpy as np

from ahrs_service.core.samples import (
    ACC_SATURATED,
    ACC_VALID,
    GYR_SATURATED,
    GYR_VALID,
    MAG_NEW,
    MAG_SATURATED,
    MAG_VALID,
    ImuSample,
    ImuSource,
    LossCounts,
    SampleBlock,
    bus_simulation_cpu_s,
)
from ahrs_service.drivers.buses.i2c import I2CBus, SMBusI2C
from ahrs_service.drivers.device import DeviceIdentityError, I2CDevice, I2CDeviceError, watermark_frames
from ahrs_service.drivers.fifo import FifoTimeline, burst_flags, hold_pairing, latch_bounds
from ahrs_service.drivers.parts.adxl345 import ADXL345
from ahrs_service.drivers.parts.adxl345 import RATES_HZ as ADXL345_RATES_HZ
from ahrs_service.drivers.parts.ak8963 import AK8963
from ahrs_service.drivers.parts.hmc5883l import HMC5883L
from ahrs_service.drivers.parts.l3g4200d import L3G4200D
from ahrs_service.drivers.parts.l3gd20 import L3GD20
from ahrs_service.drivers.parts.lsm303dlhc import ACC_RATES_HZ as LSM303_ACC_RATES_HZ
from ahrs_service.drivers.parts.lsm303dlhc import LSM303DLHCAcc, LSM303DLHCMag
from ahrs_service.drivers.parts.mpu9250 import FIFO_LAYOUT as MPU9250_FIFO
from ahrs_service.drivers.parts.mpu9250 import MPU9250
from ahrs_service.drivers.parts.st_fifo import FIFO_FRAMES as ST_FIFO_FRAMES
from ahrs_service.drivers.sim.adxl345 import SimulatedADXL345
from ahrs_service.drivers.sim.ak8963 import SimulatedAK8963
from ahrs_service.drivers.sim.bus import SimulatedI2CBus
from ahrs_service.drivers.sim.hmc5883l import SimulatedHMC5883L
from ahrs_service.drivers.sim.l3g4200d import SimulatedL3G4200D
from ahrs_service.drivers.sim.l3gd20 import SimulatedL3GD20
from ahrs_service.drivers.sim.lsm303dlhc import SimulatedLSM303DLHCAcc, SimulatedLSM303DLHCMag
from ahrs_service.drivers.sim.mpu9250 import SimulatedMPU9250

#: what :meth:`I2CBoard._read_inertial` gives: (t_ns, gyr, acc, flags, raw, temperature_c)
_Inertial = tuple[int, np.ndarray, np.ndarray, int, dict[str, Any], float | None]

class I2CBoard(ImuSource):
    """Base of the boards: parts ``gyro``, ``acc``, ``mag`` (drivers), configured in that order.

    bus: the I2C bus. own_bus: close the bus with the board. retries: transfer retries per
    part. reinit_period_s: minimum time between two attempts to bring a lost part back.
    """

    NAME = ""
    #: part → part it needs (reconfigured first, lost with it)
    DEPENDS: dict[str, str] = {}
    #: polled once per tick, the newest sample of each part's data registers
    skipped_ticks_lose_samples = True

    def __init__(self, bus: I2CBus, *, retries: int = 2, reinit_period_s: float = 0.05,
                 own_bus: bool = False, i2c_speed_hz: float = 400_000) -> None:
        super().__init__()
        self.bus = bus
        #: the bus clock (``source.i2c_speed_hz``): what the FIFO traffic is checked against
        self.i2c_speed_hz = float(i2c_speed_hz)
        self.own_bus = own_bus
        self.retries = retries
        self.reinit_period_ns = int(reinit_period_s * 1e9)
        self.parts: dict[str, I2CDevice] = {}
        self.lost: set[str] = set()
        self._last_attempt_ns = 0
        self._opened = False

    @property
    def simulation_cpu_s(self) -> float | None:
        return bus_simulation_cpu_s(self.bus)

    def _kw(self) -> dict[str, Any]:
        return {"diagnostics": self.diagnostics, "retries": self.retries}

    # ------------------------------------------------------------------ life cycle
    def open(self) -> None:
        """Identifies and configures every part; raises naming bus, address and register."""
        for part in self.parts.values():
            part.configure()
        self.lost.clear()
        self.diagnostics.device_lost = False
        self._opened = True

    def close(self) -> None:
        """Releases the bus if the board owns it."""
        self._opened = False
        if self.own_bus:
            self.bus.close()

    # ------------------------------------------------------------------ faults
    def _mark_lost(self, role: str, err: Exception) -> None:
        roles = {role} | {r for r, dep in self.DEPENDS.items() if dep == role}
        if not roles <= self.lost:
            self.lost |= roles
            self._last_attempt_ns = self.bus.now_ns()
        self.diagnostics.device_lost = True
        self.diagnostics.last_error = f"{role} lost: {err}"

    def _recover(self) -> None:
        now = self.bus.now_ns()
        if now - self._last_attempt_ns < self.reinit_period_ns:
            return
        self._last_attempt_ns = now
        for role, part in self.parts.items():  # dependency order = configuration order
            if role not in self.lost or self.DEPENDS.get(role) in self.lost:
                continue
            try:
                part.configure()
            except (OSError, DeviceIdentityError) as exc:
                self.diagnostics.last_error = f"{role} still lost: {exc}"
                continue
            self.lost.discard(role)
            self.diagnostics.reinitialisations += 1
        self.diagnostics.device_lost = bool(self.lost)

    # ------------------------------------------------------------------ samples
    def _truth_q(self, role: str = "gyro") -> np.ndarray | None:
        try:
            phys = self.bus.device(self.parts[role].address).latched  # type: ignore[attr-defined]
        except KeyError:
            return None
        truth = phys.get("truth") if phys else None
        if truth is None:
            return None
        q = truth["q"] if isinstance(truth, dict) else getattr(truth, "q", None)
        return None if q is None else np.array(q, dtype=float)

    def _check(self, values: np.ndarray, saturated: bool, valid: int, sat_flag: int) -> int:
        d = self.diagnostics
        if saturated:
            d.saturated += 1
            return sat_flag
        # integer counts times a float scale: a corrupted scale (NaN/inf) is what this catches
        if not np.isfinite(values).all():
            d.non_finite += 1
            return 0
        return valid

    def _read_mag(self, t_ns: int) -> tuple[Any, np.ndarray | None, int]:
        mag = self.parts.get("mag")
        if mag is None or "mag" in self.lost:
            return None, None, 0
        try:
            m = mag.read_if_new(t_ns)  # type: ignore[attr-defined]
        except I2CDeviceError as exc:
            self._mark_lost("mag", exc)
            return None, None, 0
        if m is None:
            return None, None, 0
        si = mag.to_si(m)
        return m, si, MAG_NEW | self._check(si, mag.is_saturated(m), MAG_VALID, MAG_SATURATED)

    def read(self) -> ImuSample | None:
        """The newest new sample, or None (nothing new, or a part lost: see diagnostics)."""
        if not self._opened:
            raise RuntimeError(f"{self.NAME} on {self.bus.name}: read() before open()")
        if self.lost:
            self._recover()
            if "gyro" in self.lost or "acc" in self.lost:
                return None
        got = self._read_inertial()
        if got is None:
            return None
        t_ns, gyr, acc, flags, raw, temperature_c = got
        m, mag, mflags = self._read_mag(t_ns)
        if m is not None:
            raw["mag"] = m
        self.diagnostics.samples += 1
        return ImuSample(t_ns, gyr, acc, mag, flags | mflags, raw,
                         self._truth_q() if self.bus.simulated else None, temperature_c)

    def _read_inertial(self) -> _Inertial | None:
        """A new gyro sample with the accelerometer read after it: (t_ns, gyr, acc, flags, raw,
        temperature_c), or None (nothing new, or a part lost)."""
        gyro, acc = self.parts["gyro"], self.parts["acc"]
        try:
            g = gyro.read_if_new()  # type: ignore[attr-defined]
        except I2CDeviceError as exc:
            self._mark_lost("gyro", exc)
            return None
        if g is None:
            return None
        t_ns = self.bus.now_ns()
        try:
            a = acc.read_counts()  # type: ignore[attr-defined]
        except I2CDeviceError as exc:
            self._mark_lost("acc", exc)
            return None
        gyr, accel = gyro.to_si(g), acc.to_si(a)
        flags = self._check(gyr, gyro.is_saturated(g), GYR_VALID, GYR_SATURATED) \
            | self._check(accel, acc.is_saturated(a), ACC_VALID, ACC_SATURATED)
        return t_ns, gyr, accel, flags, {"gyr": g, "acc": a}, None

    # ------------------------------------------------------------------ simulation
    @classmethod
    def attach_simulated(cls, bus: SimulatedI2CBus, source: Any, **options: Any) -> None:
        """Attaches this board's simulated parts to ``bus`` at the addresses in ``options``."""
        raise NotImplementedError


#: bus bits one I2C read of n data bytes costs: start, address + W, register, restart,
#: address + R, the data, stop — 9 clocks a byte
def _i2c_read_bits(n: int) -> int:
    return 9 * (n + 3) + 2


def check_i2c_fifo_load(key: str, rate_hz: float, load_bits_per_s: float, parts: str,
                        speed_hz: float, bus_name: str, margin: float = 0.75) -> None:
    """Refuses an output rate whose FIFO traffic needs more than ``margin`` of the I2C bus
    (one line naming the key, the need and the bus)."""
    if load_bits_per_s > margin * speed_hz:
        raise ValueError(
            f"source.board_options.{key} = {rate_hz:g} Hz: the {parts} FIFO traffic on "
            f"{bus_name} needs {load_bits_per_s / 1000:.0f} kbit/s, more than {margin:.0%} of "
            f"the I2C bus's {speed_hz / 1000:g} kHz clock; lower {key} (or raise source.i2c_speed_hz)")


class I2CFifoBoard(I2CBoard):
    """Base of the boards read through their parts' FIFOs (on by default; ``fifo = false``
    polls one sample per tick through :meth:`I2CBoard.read`).

    The FIFOs are drained every ``1 / fifo_read_hz`` s of the bus clock — the wake-up rate:
    these boards wire no watermark line, so it is the host's schedule, and it must stay
    above the part's rate / FIFO depth to lose nothing. Between drains ``read_block`` makes
    no bus transfer. ``read`` hands out the rows of the last drained block one by one.
    Subclasses implement :meth:`_drain` (one drain → a block), :meth:`_new_timelines` (the
    parts' FIFOs were just reset by ``configure``) and name their FIFO parts in ``FIFO_ROLES``.
    """

    #: the roles whose FIFO gives the rows (a loss of one of them is a loss of rows)
    FIFO_ROLES: frozenset[str] = frozenset({"gyro"})

    def __init__(self, bus: I2CBus, *, fifo: bool = True, fifo_read_hz: float = 100.0,
                 **kw: Any) -> None:
        super().__init__(bus, **kw)
        if not (isinstance(fifo_read_hz, (int, float)) and fifo_read_hz > 0):
            raise ValueError(f"{self.NAME} fifo_read_hz must be > 0 Hz, got {fifo_read_hz!r}")
        self.fifo = bool(fifo)
        self.may_have_backlog = self.fifo
        self.skipped_ticks_lose_samples = not self.fifo  # a FIFO keeps them (or counts them)
        self.times_on_sensor_clock = self.fifo  # FIFO rows timed on the part's own clock
        self.fifo_read_hz = float(fifo_read_hz)
        #: bursts per second (the service's loop may wake at this rate), None when polled
        self.wakeup_rate_hz = self.fifo_read_hz if self.fifo else None
        self.fifo_read_period_ns = int(round(1e9 / fifo_read_hz))
        self._next_drain_ns = 0
        self._queue: deque[ImuSample] = deque()  # rows of drained blocks for read()
        self._sim_dropped_base = 0

    @property
    def late_tolerance_s(self) -> float | None:  # type: ignore[override]
        """The shortest time a FIFO part's depth holds at its rate, less one drain period, s;
        None when polled without the FIFOs (each skipped tick is then counted lost)."""
        if not self.fifo:
            return None
        spans = [part.fifo_layout.depth_frames / part.rate_hz  # type: ignore[attr-defined]
                 for role, part in self.parts.items() if hasattr(part, "fifo_layout")]
        return max(0.0, min(spans) - 1.0 / self.fifo_read_hz) if spans else None

    def open(self) -> None:
        super().open()
        if self.fifo:
            self._restart_fifo_schedule()
            self._sim_dropped_base = self._sim_dropped()

    def _restart_fifo_schedule(self) -> None:
        """configure() has just reset the FIFOs: new timelines (the parts restarted their
        sample grids), the first drain one read period on."""
        self._next_drain_ns = self.bus.now_ns() + self.fifo_read_period_ns
        self._new_timelines()
        self._queue.clear()

    def _new_timelines(self) -> None:
        raise NotImplementedError

    def _timelines(self) -> list[FifoTimeline]:
        raise NotImplementedError

    @property
    def pending(self) -> int:
        """Rows drained from the FIFO that ``read`` has not handed out yet."""
        return len(self._queue)

    def read(self) -> ImuSample | None:
        """Polling (``fifo = false``): as every board. FIFO: the next row of the last drained
        block (a block is drained when the queue is empty)."""
        if not self.fifo:
            return super().read()
        if not self._queue:
            self._queue.extend(self.read_block().samples())
        return self._queue.popleft() if self._queue else None

    def read_block(self, max_samples: int = 64) -> SampleBlock:
        """Polling: the base's block of ``read``. FIFO: every whole sample in the FIFOs, once
        per ``1 / fifo_read_hz`` (an empty block in between); at most a FIFO's depth,
        whatever ``max_samples`` says. A part lost on the bus stops the rows; when it is
        back, what the row part produced meanwhile is counted in ``lost.bus_error``."""
        if not self.fifo:
            return super().read_block(max_samples)
        if not self._opened:
            raise RuntimeError(f"{self.NAME} on {self.bus.name}: read_block() before open()")
        if self.lost:
            was_lost = bool(self.lost & self.FIFO_ROLES)
            self._recover()
            if self.lost & self.FIFO_ROLES:
                return SampleBlock.empty()
            if was_lost:  # back: its FIFO was reset; count what the row part produced meanwhile
                self._back()
                return SampleBlock.empty()
        now = self.bus.now_ns()
        if now < self._next_drain_ns:
            return SampleBlock.empty()
        self._next_drain_ns = max(self._next_drain_ns + self.fifo_read_period_ns, now)
        block = self._drain()
        if self.bus.simulated:
            # the twin's own count of the samples it dropped or had emptied unread since the
            # first read, beside the driver's estimate (what the stall tests compare)
            self.diagnostics.extra["sim_fifo_dropped"] = self._sim_dropped() - self._sim_dropped_base
        return block

    def _back(self) -> None:
        """A FIFO part is configured again: the rows' part counts its outage, then every
        FIFO starts afresh (a part that was not lost is reset too)."""
        old = self._timelines()[0]
        for role in self.FIFO_ROLES:
            self.parts[role].fifo_reset()  # type: ignore[attr-defined]
        old.missed(self.bus.now_ns())
        self._restart_fifo_schedule()
        self._timelines()[0].carry_loss(old)

    def _drain(self) -> SampleBlock:
        raise NotImplementedError

    # ------------------------------------------------------------------ helpers
    def _sim_dropped(self) -> int:
        """The twins' count of the row part's dropped samples (0 on hardware)."""
        if not self.bus.simulated:
            return 0
        twin = self.bus.device(self.parts["gyro"].address)
        return twin.fifo_overflowed + twin.fifo_discarded  # type: ignore[attr-defined]

    @staticmethod
    def _truth_rows(truths: list[Any], n: int) -> np.ndarray | None:
        """(n, 4) true attitudes from the twin's per-sample truths, None when any is missing."""
        qs = []
        for truth in truths:
            q = None if truth is None else (truth["q"] if isinstance(truth, dict) else getattr(truth, "q", None))
            if q is None:
                return None
            qs.append(q)
        return np.array(qs, dtype=float) if len(qs) == n and n else None

    def _attach_mag(self, t_ns: np.ndarray, mag: np.ndarray, flags: np.ndarray,
                    raw: dict[str, np.ndarray]) -> None:
        """One magnetometer read per drain (magnetometers have no FIFO): its reading goes
        with the newest row."""
        n = len(t_ns)
        if not n:
            return
        m, m_si, mflags = self._read_mag(int(t_ns[-1]))
        if m is not None:
            mag[-1] = m_si
            flags[-1] |= mflags
            mag_raw = np.zeros((n, 3), np.int64)
            mag_raw[-1] = m
            raw["mag"] = mag_raw


class _PairedFifoBoard(I2CFifoBoard):
    """A gyroscope and an accelerometer on separate clocks, each with a 32-level stream FIFO
    (GY-80, MinIMU-9 v2), and a magnetometer without.

    A drain reads the accelerometer's FIFO, then the gyroscope's (the rows, on its clock);
    each part's samples are timed on its own sensor clock
    (:class:`~ahrs_service.drivers.fifo.FifoTimeline`), and each row takes the accelerometer
    sample the pairing rule picks (:func:`~ahrs_service.drivers.fifo.hold_pairing`: the newest
    at or before the row's time). Loss: a FIFO found filled (OVRN / Overrun) holds the newest
    32 samples; what the part produced before them since the last read is counted in
    ``lost.fifo_overflow`` (gyroscope) from the sensor clock, the gap shows as one long dt.
    A drain that took longer than the FIFO had room for (the host stopped inside it) cannot
    tell which samples it read: the FIFO is reset and everything since the last read is
    counted. The accelerometer's overflows cost no rows (the held value bridges them) and are
    counted in ``diagnostics.extra["acc_fifo_overflows"]``.

    ``fifo_read_hz`` defaults to 200 Hz (4 samples a drain at 800 Hz): the magnetometer has
    no FIFO and is read once a drain, so the drain rate bounds how many of its readings
    arrive (75 Hz HMC5883L, 220 Hz LSM303DLHC).
    """

    FIFO_ROLES = frozenset({"gyro", "acc"})

    @staticmethod
    def _rates(odr_hz: float | None, gyro_rate_hz: float, acc_rate_hz: float | None,
               gyro_rates, acc_rates) -> tuple[float, float]:
        """(gyro, accelerometer) rates: ``odr_hz`` is the rows' (gyroscope's) output rate and
        wins over ``gyro_rate_hz``; the accelerometer runs at ``acc_rate_hz`` or, not given,
        at its slowest supported rate at or above the rows' (the pairing rule holds it)."""
        gyro = float(gyro_rate_hz if odr_hz is None else odr_hz)
        if gyro not in gyro_rates:
            key = "gyro_rate_hz" if odr_hz is None else "odr_hz"
            raise ValueError(f"source.board_options.{key} = {gyro:g} Hz: the gyroscope runs at "
                             f"{', '.join(f'{r:g}' for r in sorted(gyro_rates))} Hz")
        if acc_rate_hz is None:
            acc_rate_hz = min((r for r in acc_rates if r >= gyro), default=max(acc_rates))
        return gyro, float(acc_rate_hz)

    def _check_load(self) -> None:
        """The two FIFOs' traffic at the drain rate against the bus clock."""
        if not self.fifo:
            return
        gyro, acc = self.parts["gyro"], self.parts["acc"]
        bits = 0.0
        for part in (gyro, acc):
            lay = part.fifo_layout
            per_drain = part.rate_hz / self.fifo_read_hz
            per = lay.frames_per_transfer or max(1, 32 // lay.frame_bytes)
            transfers = max(1.0, per_drain / per)
            bits += part.rate_hz * 9 * lay.frame_bytes + self.fifo_read_hz * (
                transfers * _i2c_read_bits(0) + 2 * _i2c_read_bits(1))  # data, status reads
        bits += self.fifo_read_hz * _i2c_read_bits(6)  # the magnetometer, once a drain
        key, rate = (("acc_rate_hz", acc.rate_hz) if acc.rate_hz * (1 + 3 / acc.fifo_layout.frames_per_transfer)
                     > gyro.rate_hz * 1.6 else ("odr_hz", gyro.rate_hz))
        check_i2c_fifo_load(key, rate, bits, f"{type(gyro).PART} and {type(acc).PART}",
                            self.i2c_speed_hz, getattr(self.bus, "name", "the I2C bus"))

    def _fifo_kw(self, fifo: bool, rate_hz: float, fifo_read_hz: float) -> dict[str, Any]:
        """A part's FIFO options: the watermark for draining at ``fifo_read_hz``."""
        return {"fifo": fifo, "watermark": watermark_frames(rate_hz, fifo_read_hz, ST_FIFO_FRAMES)}

    def _new_timelines(self) -> None:
        gyro, acc = self.parts["gyro"], self.parts["acc"]
        latch = latch_bounds("i2c", self.i2c_speed_hz, level_bytes=1)  # FIFO_SRC_REG, FIFO_STATUS
        self.timeline = FifoTimeline(gyro.rate_hz, self.diagnostics, **latch)  # type: ignore[attr-defined]
        self.acc_timeline = FifoTimeline(acc.rate_hz, self.diagnostics, **latch,  # type: ignore[attr-defined]
                                         events_key="acc_fifo_overflows", rows=False)
        self._acc_t = np.empty(0, np.int64)  # the accelerometer samples a row may still take
        self._acc_c = np.empty((0, 3), np.int64)
        self._paired = False  # a row has had an accelerometer sample since the start

    def _timelines(self) -> list[FifoTimeline]:
        return [self.timeline, self.acc_timeline]

    def _drain_part(self, role: str, timeline: FifoTimeline
                    ) -> tuple[np.ndarray, np.ndarray, list[Any]] | None:
        """One part's FIFO: (counts (n, 3), times (n,), truths) or None when the part failed."""
        part = self.parts[role]
        depth = part.fifo_layout.depth_frames  # type: ignore[attr-defined]
        rate = part.rate_hz  # type: ignore[attr-defined]
        try:
            t_start = self.bus.now_ns()
            status = part.fifo_status()  # type: ignore[attr-defined]
            t_read, t_level_done = status.level_read_ns, self.bus.now_ns()
            n = status.level
            counts = part.read_fifo(n) if n else np.empty((0, 3), np.int64)  # type: ignore[attr-defined]
            t_done = self.bus.now_ns()
            truths = self._popped_truth(role)
            # the FIFO had room for depth − n more samples from the status read on: a host
            # stopped longer than that inside the drain read samples it cannot place
            stopped = not status.overflow and (t_done - t_start) * 1e-9 * rate >= depth - n
            if stopped:
                t_reset_started = self.bus.now_ns()
                part.fifo_reset()  # type: ignore[attr-defined]
                t_reset = self.bus.now_ns()
        except I2CDeviceError as exc:
            self._mark_lost(role, exc)
            return None
        if not timeline.started and (status.overflow or stopped):
            # filled before the first read after open(): stale samples nobody asked for yet
            if stopped:
                return np.empty((0, 3), np.int64), np.empty(0, np.int64), []
            return counts, timeline.stamp(t_read, n), truths
        if stopped:
            timeline.overflowed(t_reset_started, t_reset, flagged=False)
            return np.empty((0, 3), np.int64), np.empty(0, np.int64), []
        if status.overflow:
            # stream mode: the newest samples, the oldest overwritten: the gap comes first
            timeline.overran(t_read, n)
        return counts, (timeline.stamp(t_read, n, read_end_ns=t_level_done) if n else np.empty(0, np.int64)), truths

    def _popped_truth(self, role: str) -> list[Any]:
        if not self.bus.simulated:
            return []
        return self.bus.device(self.parts[role].address).take_popped_truth()  # type: ignore[attr-defined]

    def _drain(self) -> SampleBlock:
        # the accelerometer first: should it fail, the gyroscope's FIFO is left as it is and
        # what it holds is counted when the accelerometer is back (no row without its value)
        got_acc = self._drain_part("acc", self.acc_timeline)
        if got_acc is None:
            return SampleBlock.empty()
        a, ta, _ = got_acc
        if len(ta):
            # the last accelerometer samples stay (a FIFO's worth): the next drain's first rows
            # may take one of them (the two parts' times are estimates, each off by tens of µs)
            self._acc_t = np.concatenate([self._acc_t[-ST_FIFO_FRAMES:], ta])
            self._acc_c = np.concatenate([self._acc_c[-ST_FIFO_FRAMES:], a])
        got = self._drain_part("gyro", self.timeline)
        if got is None:
            return SampleBlock.empty()
        g, t, truths = got
        idx = hold_pairing(t, self._acc_t)
        if self._paired:  # after the start a row older than the kept history takes its oldest
            idx = np.maximum(idx, 0)
        ok = idx >= 0  # rows before the accelerometer's first sample after start: not handed out
        self._paired |= bool(ok.any())
        g, t, idx = g[ok], t[ok], idx[ok]
        truth = self._truth_rows([q for q, keep in zip(truths, ok) if keep], len(t))
        lost = self.timeline.take_loss()
        gyro, acc = self.parts["gyro"], self.parts["acc"]
        a = self._acc_c[idx]
        n = len(t)
        flags = burst_flags(g, a, gyro.full_scale, acc.full_scale, self.diagnostics)
        self.diagnostics.samples += n
        mag, raw = np.full((n, 3), np.nan), {"gyr": g, "acc": a}
        self._attach_mag(t, mag, flags, raw)
        return SampleBlock(t.astype(np.int64), g * gyro.scale, a * acc.scale, mag, flags,
                           np.full(n, np.nan), raw, truth, lost)


class GY80(_PairedFifoBoard):
    """GY-80: L3G4200D gyro (0x69), ADXL345 accelerometer (0x53), HMC5883L compass (0x1E).

    (Its BMP085 barometer at 0x77 is not used.) Ranges/rates: see each driver. FIFO: both
    inertial parts' 32-level FIFOs in stream mode (40 ms at the default 800 Hz), drained at
    ``fifo_read_hz``; rows on the gyroscope's clock (:class:`_PairedFifoBoard`).
    """

    NAME = "gy80"

    def __init__(self, bus: I2CBus, *, gyro_address: int = 0x69, acc_address: int = 0x53,
                 mag_address: int = 0x1E, gyro_range_dps: int = 2000, gyro_rate_hz: float = 800,
                 acc_range_g: int = 8, acc_rate_hz: float | None = None, mag_range_ga: float = 1.3,
                 mag_rate_hz: float = 75, mag_averaging: int = 8, fifo: bool = True,
                 fifo_read_hz: float = 200.0, odr_hz: float | None = None, **kw: Any) -> None:
        super().__init__(bus, fifo=fifo, fifo_read_hz=fifo_read_hz, **kw)
        gyro_rate_hz, acc_rate_hz = self._rates(odr_hz, gyro_rate_hz, acc_rate_hz,
                                                L3G4200D.RATES_HZ, ADXL345_RATES_HZ)
        self.parts = {
            "gyro": L3G4200D(bus, gyro_address, range_dps=gyro_range_dps, rate_hz=gyro_rate_hz,
                             **self._fifo_kw(fifo, gyro_rate_hz, fifo_read_hz), **self._kw()),
            "acc": ADXL345(bus, acc_address, range_g=acc_range_g, rate_hz=acc_rate_hz,
                           **self._fifo_kw(fifo, acc_rate_hz, fifo_read_hz), **self._kw()),
            "mag": HMC5883L(bus, mag_address, range_ga=mag_range_ga, rate_hz=mag_rate_hz,
                            averaging=mag_averaging, **self._kw()),
        }
        self._check_load()

    @classmethod
    def attach_simulated(cls, bus: SimulatedI2CBus, source: Any, *, gyro_address: int = 0x69,
                         acc_address: int = 0x53, mag_address: int = 0x1E, **_: Any) -> None:
        bus.attach(SimulatedL3G4200D(source, gyro_address))
        bus.attach(SimulatedADXL345(source, acc_address))
        bus.attach(SimulatedHMC5883L(source, mag_address))


class MinIMU9v2(_PairedFifoBoard):
    """Pololu MinIMU-9 v2: L3GD20 gyro (0x6B), LSM303DLHC accelerometer (0x19) and
    magnetometer (0x1E). FIFO: the gyroscope's and the accelerometer's 32-level FIFOs in
    stream mode (42 ms at 760 Hz), drained at ``fifo_read_hz``; rows on the gyroscope's clock
    (:class:`_PairedFifoBoard`)."""

    NAME = "minimu9v2"

    def __init__(self, bus: I2CBus, *, gyro_address: int = 0x6B, acc_address: int = 0x19,
                 mag_address: int = 0x1E, gyro_range_dps: int = 2000, gyro_rate_hz: float = 760,
                 acc_range_g: int = 8, acc_rate_hz: float | None = None, mag_range_ga: float = 1.3,
                 mag_rate_hz: float = 220, fifo: bool = True, fifo_read_hz: float = 200.0,
                 odr_hz: float | None = None, **kw: Any) -> None:
        super().__init__(bus, fifo=fifo, fifo_read_hz=fifo_read_hz, **kw)
        gyro_rate_hz, acc_rate_hz = self._rates(odr_hz, gyro_rate_hz, acc_rate_hz,
                                                L3GD20.RATES_HZ, LSM303_ACC_RATES_HZ)
        self.parts = {
            "gyro": L3GD20(bus, gyro_address, range_dps=gyro_range_dps, rate_hz=gyro_rate_hz,
                           **self._fifo_kw(fifo, gyro_rate_hz, fifo_read_hz), **self._kw()),
            "acc": LSM303DLHCAcc(bus, acc_address, range_g=acc_range_g, rate_hz=acc_rate_hz,
                                 **self._fifo_kw(fifo, acc_rate_hz, fifo_read_hz), **self._kw()),
            "mag": LSM303DLHCMag(bus, mag_address, range_ga=mag_range_ga, rate_hz=mag_rate_hz,
                                 **self._kw()),
        }
        self._check_load()

    @classmethod
    def attach_simulated(cls, bus: SimulatedI2CBus, source: Any, *, gyro_address: int = 0x6B,
                         acc_address: int = 0x19, mag_address: int = 0x1E, **_: Any) -> None:
        bus.attach(SimulatedL3GD20(source, gyro_address))
        bus.attach(SimulatedLSM303DLHCAcc(source, acc_address))
        bus.attach(SimulatedLSM303DLHCMag(source, mag_address))


class MPU9250Board(I2CFifoBoard):
    """MPU-9250 (0x68) with its AK8963 magnetometer (0x0C, reached in I2C bypass mode).

    The magnetometer is reported in the MPU-9250's accelerometer/gyro axes. ``temperature_c``
    is the MPU-9250 die temperature. The AK8963 depends on the MPU-9250: it is lost with it
    and reconfigured after it (the MPU's reset turns bypass off). FIFO: 512 bytes, 42
    samples (42 ms at 1 kHz), drained at ``fifo_read_hz`` (default 100: 10 samples a drain).
    """

    NAME = "mpu9250"
    DEPENDS = {"mag": "gyro"}

    def __init__(self, bus: I2CBus, *, address: int = 0x68, mag_address: int = 0x0C,
                 gyro_range_dps: int = 2000, acc_range_g: int = 8, rate_hz: float = 1000,
                 mag_rate_hz: float = 100, fifo: bool = True, fifo_read_hz: float = 100.0,
                 odr_hz: float | None = None, **kw: Any) -> None:
        super().__init__(bus, fifo=fifo, fifo_read_hz=fifo_read_hz, **kw)
        if odr_hz is not None:  # odr_hz, the key every board has; rate_hz its older name
            rate_hz = odr_hz
        try:
            self.mpu = MPU9250(bus, address, gyro_range_dps=gyro_range_dps, acc_range_g=acc_range_g,
                               rate_hz=rate_hz, fifo=fifo, **self._kw())
        except ValueError as exc:
            if odr_hz is None or "rate_hz" not in str(exc):
                raise
            raise ValueError(f"source.board_options.odr_hz = {odr_hz:g} Hz: {exc}".replace(
                "MPU-9250 rate_hz must be", "the MPU-9250 runs at")) from None
        self.parts = {"gyro": self.mpu,
                      "mag": AK8963(bus, mag_address, rate_hz=mag_rate_hz, **self._kw())}
        self.timeline: FifoTimeline | None = None  # the FIFO's samples on the part's clock

    def _new_timelines(self) -> None:
        self.timeline = FifoTimeline(self.mpu.rate_hz, self.diagnostics,
                                     **latch_bounds("i2c", self.i2c_speed_hz, level_bytes=2))  # FIFO_COUNTH/L

    def _timelines(self) -> list[FifoTimeline]:
        return [self.timeline]

    def _back(self) -> None:
        # configure() (H_RESET) has reset the FIFO and restarted the part's sample grid
        old = self.timeline
        old.missed(self.bus.now_ns())
        self._restart_fifo_schedule()
        self.timeline.carry_loss(old)

    def _drain(self) -> SampleBlock:
        """INT_STATUS, FIFO_COUNT, the samples, TEMP_OUT, and a FIFO reset when it overflowed —
        flagged, or full at the count read (a stop between the status and the count read
        fills it before the flag is read), or when the drain took longer than the FIFO had
        room for (the host stopped inside it).

        Times come from the sensor clock (:class:`~ahrs_service.drivers.fifo.FifoTimeline`):
        the samples' indices on the part's own clock, tracked against the host time of the
        count read. The samples a full FIFO kept (FIFO_MODE 1: the oldest, contiguous with the
        last ones read) are timed from the clock's fit; the rest are counted in
        ``lost.fifo_overflow`` as what the clock says the part produced by the reset minus
        what was read. A FIFO that overflowed before the first read after ``open`` is emptied
        without counting: those samples predate the consumer.
        """
        mpu = self.mpu
        depth = MPU9250_FIFO.depth_frames
        try:
            t_start = self.bus.now_ns()
            status = mpu.fifo_status()
            t_read, t_level_done = status.level_read_ns, self.bus.now_ns()
            n = status.level
            acc_c, gyr_c = mpu.read_fifo(n) if n else (np.empty((0, 3), np.int64),) * 2
            t_done = self.bus.now_ns()
            truth = self._fifo_truth(n) if self.bus.simulated else None  # before any reset
            temp = mpu.read_temperature_counts()
            # the FIFO had room for depth − n more samples from the count read to the end of
            # the burst: a host that stopped longer than that anywhere in the drain (even
            # before it took t_read) left it full, and a FIFO that refills as it is read
            # after a gap is no longer contiguous: reset it and count by the clock
            filled = (t_done - t_start) * 1e-9 * mpu.rate_hz >= depth - n
            overflow = status.overflow or n >= depth or filled
            if overflow:
                t_reset_started = self.bus.now_ns()
                mpu.fifo_reset()
                t_reset = self.bus.now_ns()
        except I2CDeviceError as exc:
            self._mark_lost("gyro", exc)
            return SampleBlock.empty()
        timeline = self.timeline
        if overflow and not timeline.started:
            # the FIFO filled between open() and the first read (the service sets up its log
            # and links in between): stale samples nobody asked for yet, not a loss
            self._restart_fifo_schedule()
            self._sim_dropped_base = self._sim_dropped()
            return SampleBlock.empty()
        t_ns = timeline.stamp(t_read, n, full=overflow, read_end_ns=t_level_done) if n else np.empty(0, np.int64)
        lost = timeline.take_loss()  # after stamping: a gap before these rows is counted by it
        if overflow:  # counted when found; the next block carries it before its first row
            timeline.overflowed(t_reset_started, t_reset, flagged=status.overflow)
        return self._fifo_block(t_ns, acc_c, gyr_c, temp, truth, lost)

    def _fifo_block(self, t_ns: np.ndarray, acc_c: np.ndarray, gyr_c: np.ndarray, temp: int,
                    truth: np.ndarray | None, lost: LossCounts) -> SampleBlock:
        mpu = self.mpu
        n = len(t_ns)
        flags = burst_flags(gyr_c, acc_c, mpu.gyro_full_scale, mpu.acc_full_scale, self.diagnostics)
        self.diagnostics.samples += n
        mag = np.full((n, 3), np.nan)
        raw = {"gyr": gyr_c, "acc": acc_c, "temp": np.full(n, temp, np.int64)}
        self._attach_mag(t_ns, mag, flags, raw)
        return SampleBlock(t_ns.astype(np.int64), gyr_c * mpu.gyro_scale, acc_c * mpu.acc_scale, mag,
                           flags, np.full(n, mpu.temperature_c(temp)), raw, truth, lost)

    def _fifo_truth(self, n: int) -> np.ndarray | None:
        """True attitudes of the ``n`` samples just read (simulated bus only: the twin keeps
        each FIFO sample's truth beside it)."""
        frames = self.bus.device(self.mpu.address).pop_truth(n)  # type: ignore[attr-defined]
        return self._truth_rows([truth for _, truth in frames], n)


    def _read_inertial(self) -> _Inertial | None:
        """Gyro, accelerometer and temperature come in one burst from the MPU-9250."""
        mpu = self.mpu
        try:
            frame = mpu.read_if_new()
        except I2CDeviceError as exc:
            self._mark_lost("gyro", exc)
            return None
        if frame is None:
            return None
        t_ns = self.bus.now_ns()
        a, temp, g = frame
        gyr, acc = mpu.gyr_si(g), mpu.acc_si(a)
        flags = self._check(gyr, mpu.gyr_saturated(g), GYR_VALID, GYR_SATURATED) \
            | self._check(acc, mpu.acc_saturated(a), ACC_VALID, ACC_SATURATED)
        return t_ns, gyr, acc, flags, {"gyr": g, "acc": a, "temp": temp}, mpu.temperature_c(temp)

    @classmethod
    def attach_simulated(cls, bus: SimulatedI2CBus, source: Any, *, address: int = 0x68,
                         mag_address: int = 0x0C, **_: Any) -> None:
        mpu = bus.attach(SimulatedMPU9250(source, address))
        bus.attach(SimulatedAK8963(source, mag_address), visible_if=mpu.bypass_enabled)
