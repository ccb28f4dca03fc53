"""What every sensor input gives the service: timestamped samples in SI units, and counters.

A source (an I2C IMU, a DroneCAN IMU, the simulator, a recorded log) is one class behind
:class:`ImuSource`. Two ways to take its samples:

* :meth:`ImuSource.read` — the newest *new* sample or ``None``; it never hands the same
  reading out twice (one :class:`ImuSample` object per sample);
* :meth:`ImuSource.read_block` — every new sample at once as a :class:`SampleBlock` (arrays,
  one row per sample, oldest first), with the samples lost before its first row counted by
  cause (:class:`LossCounts`). A part with a FIFO drains it here in bursts; every other
  source gets a block built from ``read`` (the base implementation).

A source is read through one of them, not both interleaved: a FIFO board's ``read`` hands
out the rows of its last drained burst one by one.

Units and axes of an :class:`ImuSample`: gyroscope rad/s, specific force m/s², magnetic
field µT; ``gyr``/``acc``/``mag`` are calibrated and in the **body frame (FRD)** once
:mod:`ahrs_service.core.calibration` has been applied, in the sensor's own axes before.
"""

from __future__ import annotations

import abc
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ahrs_service.core.layout import Layout, Slot

#: one sample as the estimators take it: a row of a float64 array (``SampleBlock.rows``)
SAMPLE_ROW = Layout(
    "sample row",
    [
        Slot("gyr", 3, "gyroscope, rad/s, sensor axes"),
        Slot("acc", 3, "specific force, m/s², sensor axes"),
        Slot("mag", 3, "magnetic field, µT, sensor axes (NaN: no new field)"),
        Slot("dt", 1, "time since the previous sample, s"),
    ],
)

# validity flags of one sample (bit mask)
GYR_VALID = 1 << 0
ACC_VALID = 1 << 1
MAG_VALID = 1 << 2
GYR_SATURATED = 1 << 3
ACC_SATURATED = 1 << 4
MAG_SATURATED = 1 << 5
MAG_NEW = 1 << 6  # the magnetometer value is a fresh reading (magnetometers run slower)

#: largest reading per axis a source takes from another device's floats (the autopilot's
#: MAVLink IMU, a DroneCAN node), rad/s, m/s², µT: twice the widest range of the IMUs flight
#: controllers and CAN IMU nodes carry (gyroscopes ±4000 °/s — ICM-45686 —, accelerometers
#: ±32 g, magnetometers ±4900 µT — AK09916 —). A finite value beyond it (3e38 in a float32
#: field, 65504 in a float16 one, 1e6 rad/s) is no motion but a corrupt or hostile message: the
#: source marks the reading saturated (``diagnostics.saturated``) and the estimator skips it.
#: Our own parts' drivers know their full scale and flag saturation from the counts instead.
MAX_READING = {"gyr": 2 * 4000.0 * math.pi / 180.0, "acc": 2 * 32 * 9.80665, "mag": 2 * 4900.0}


def beyond_range(values, part: str) -> bool:
    """Whether a finite reading of ``part`` ("gyr", "acc", "mag") has an axis beyond
    :data:`MAX_READING`."""
    limit = MAX_READING[part]
    return any(abs(float(v)) > limit for v in values)


@dataclass(slots=True)
class ImuSample:
    """One IMU reading.

    t_ns: timestamp in nanoseconds on the monotonic clock of the host (``time.monotonic_ns``),
        or the sensor's own clock mapped onto it (CAN).
    gyr, acc: (3,) float64, rad/s and m/s² (specific force).
    mag: (3,) float64 in µT, or None when the source has no magnetometer value for this sample.
    flags: validity bits (``GYR_VALID`` …). A reading that is saturated or not finite has its
        ``*_VALID`` bit cleared and is not fed to the estimator as valid.
    raw: the uncalibrated readings where the driver has them, e.g. {"gyr": [counts…], …}.
    truth_q: ground-truth q_earth←body [w, x, y, z] when the source knows it (simulator, BROAD).
    """

    t_ns: int
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray | None = None
    flags: int = GYR_VALID | ACC_VALID
    raw: dict[str, Any] | None = None
    truth_q: np.ndarray | None = None
    temperature_c: float | None = None


@dataclass(slots=True)
class LossCounts:
    """Samples that never reached the host, by cause (whole sample periods of the part).

    fifo_overflow: the part's FIFO filled and overwrote (or refused) samples; where the part
        only flags the overrun, the count is estimated from the sensor clock (elapsed time ×
        output rate − what the FIFO held).
    bus_error: samples the part produced while a read failed or the part was lost.
    gap: periods missing in a source without FIFO or sample counter (clock recovery, CAN,
        recordings).
    host_stall: samples a part without FIFO overwrote in its data registers before the
        host came to read them (the host was late: an overrun of the loop).
    """

    fifo_overflow: int = 0
    bus_error: int = 0
    gap: int = 0
    host_stall: int = 0

    @property
    def total(self) -> int:
        return self.fifo_overflow + self.bus_error + self.gap + self.host_stall

    def add(self, other: "LossCounts") -> None:
        """Adds ``other``'s counts to these (in place)."""
        self.fifo_overflow += other.fifo_overflow
        self.bus_error += other.bus_error
        self.gap += other.gap
        self.host_stall += other.host_stall

    def since(self, earlier: "LossCounts") -> "LossCounts":
        """The counts added since ``earlier`` (a :meth:`copy` taken then)."""
        return LossCounts(self.fifo_overflow - earlier.fifo_overflow, self.bus_error - earlier.bus_error,
                          self.gap - earlier.gap, self.host_stall - earlier.host_stall)

    def copy(self) -> "LossCounts":
        return LossCounts(self.fifo_overflow, self.bus_error, self.gap, self.host_stall)

    def as_dict(self) -> dict[str, int]:
        return {"fifo_overflow": self.fifo_overflow, "bus_error": self.bus_error, "gap": self.gap,
                "host_stall": self.host_stall, "total": self.total}

    def summary(self) -> str:
        """The total and its non-zero causes: "0" or "12 (fifo_overflow 9, bus_error 3)"."""
        causes = [f"{k} {v}" for k, v in self.as_dict().items() if k != "total" and v]
        return f"{self.total} ({', '.join(causes)})" if causes else str(self.total)


def _floats(x: Any) -> list[float]:
    """A reading as a list of Python floats (an array's ``tolist``, the cheap common case)."""
    return x.tolist() if type(x) is np.ndarray else [float(v) for v in x]


@dataclass(slots=True)
class SampleBlock:
    """Consecutive samples of one source as arrays, one row per sample, oldest first.

    t_ns: (n,) int64, each sample's time on the monotonic clock (ns): the sensor clock's
        sample instant mapped onto the host's clock where the source knows it (FIFO position
        × output period), else the host's read time.
    gyr, acc: (n, 3) float64, rad/s and m/s² (specific force), sensor or body axes as for
        :class:`ImuSample`.
    mag: (n, 3) float64 µT; NaN rows where the magnetometer has no new reading for the
        sample (then ``MAG_NEW`` is clear in ``flags``).
    flags: (n,) int64 validity bits, as :attr:`ImuSample.flags`.
    temperature_c: (n,) float64 °C, NaN where unknown.
    raw: counts as read, {"gyr": (n, 3) int64, "acc": …, "mag": …, "temp": (n,)} where the
        driver has them.
    truth_q: (n, 4) q_earth←body [w, x, y, z] where the source knows the truth, else None.
    lost: samples lost **immediately before row 0** (a source ends a block at a loss, so the
        gap shows as one long dt between the previous block's last row and this one's first —
        lost samples are never filled in).
    """

    t_ns: np.ndarray
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    flags: np.ndarray
    temperature_c: np.ndarray
    raw: dict[str, np.ndarray] | None = None
    truth_q: np.ndarray | None = None
    lost: LossCounts = field(default_factory=LossCounts)

    def __len__(self) -> int:
        return len(self.t_ns)

    @classmethod
    def empty(cls, lost: LossCounts | None = None) -> "SampleBlock":
        """A block without samples (it may still carry a loss)."""
        return cls(np.empty(0, np.int64), np.empty((0, 3)), np.empty((0, 3)), np.empty((0, 3)),
                   np.empty(0, np.int64), np.empty(0), lost=lost or LossCounts())

    @classmethod
    def from_samples(cls, samples: list[ImuSample], lost: LossCounts | None = None) -> "SampleBlock":
        """The block of ``samples`` (oldest first); ``raw`` and ``truth_q`` are kept only when
        every sample has them."""
        n = len(samples)
        if n == 0:
            return cls.empty(lost)
        # one list of plain floats per field, then one array each: the polling path builds a
        # block per sample, and per-element NumPy work there costs tens of microseconds
        nan3 = [math.nan, math.nan, math.nan]
        if n == 1:  # the polling path: one sample a tick, one array for its three readings
            s = samples[0]
            vec = np.array([_floats(s.gyr), _floats(s.acc), nan3 if s.mag is None else _floats(s.mag)], dtype=float)
            return cls(
                np.array([s.t_ns], dtype=np.int64), vec[0:1], vec[1:2], vec[2:3], np.array([s.flags], dtype=np.int64),
                np.array([math.nan if s.temperature_c is None else s.temperature_c]),
                None if s.raw is None else {k: np.array([s.raw[k]], dtype=np.int64) for k in sorted(s.raw)},
                None if s.truth_q is None else np.array([_floats(s.truth_q)]), lost or LossCounts())
        raw = None
        if all(s.raw is not None for s in samples):
            first = samples[0].raw
            keys = set(first)  # type: ignore[arg-type]
            if any(set(s.raw) != keys for s in samples):  # type: ignore[arg-type]
                keys = set.intersection(*(set(s.raw) for s in samples))  # type: ignore[arg-type]
            # (n, 3) per vector reading, (n,) per scalar one (a temperature count)
            same_shape = [k for k in keys if len({np.ndim(s.raw[k]) for s in samples}) == 1]  # type: ignore[index]
            raw = {k: np.array([s.raw[k] for s in samples], dtype=np.int64)  # type: ignore[index]
                   for k in sorted(same_shape)}
        truth = (np.array([_floats(s.truth_q) for s in samples], dtype=float)
                 if all(s.truth_q is not None for s in samples) else None)
        return cls(
            np.array([s.t_ns for s in samples], dtype=np.int64),
            np.array([_floats(s.gyr) for s in samples], dtype=float).reshape(n, 3),
            np.array([_floats(s.acc) for s in samples], dtype=float).reshape(n, 3),
            np.array([nan3 if s.mag is None else _floats(s.mag) for s in samples], dtype=float).reshape(n, 3),
            np.array([s.flags for s in samples], dtype=np.int64),
            np.array([math.nan if s.temperature_c is None else s.temperature_c for s in samples], dtype=float),
            raw, truth, lost or LossCounts())

    def sample(self, i: int) -> ImuSample:
        """Row ``i`` as an :class:`ImuSample` (``mag`` None where the row has no reading)."""
        mag = self.mag[i]
        temp = float(self.temperature_c[i])
        return ImuSample(
            int(self.t_ns[i]), self.gyr[i].copy(), self.acc[i].copy(),
            None if np.isnan(mag).all() else mag.copy(), int(self.flags[i]),
            None if self.raw is None else {k: v[i].tolist() for k, v in self.raw.items()},
            None if self.truth_q is None else self.truth_q[i].copy(),
            None if math.isnan(temp) else temp,
        )

    @classmethod
    def concat(cls, blocks: list["SampleBlock"]) -> "SampleBlock":
        """Consecutive blocks of one source as one (the first's ``lost``; the others must
        carry none: a block ends at a loss). ``raw`` keeps the keys all have, ``truth_q`` is
        kept when all have it."""
        if len(blocks) == 1:
            return blocks[0]
        if any(b.lost.total for b in blocks[1:]):
            raise ValueError("SampleBlock.concat: only the first block may carry a loss")
        raw = None
        if all(b.raw is not None for b in blocks):
            keys = set.intersection(*(set(b.raw) for b in blocks))  # type: ignore[arg-type]
            raw = {k: np.concatenate([b.raw[k] for b in blocks]) for k in sorted(keys)}  # type: ignore[index]
        truth = (np.concatenate([b.truth_q for b in blocks])  # type: ignore[misc]
                 if all(b.truth_q is not None for b in blocks) else None)
        return cls(np.concatenate([b.t_ns for b in blocks]), np.concatenate([b.gyr for b in blocks]),
                   np.concatenate([b.acc for b in blocks]), np.concatenate([b.mag for b in blocks]),
                   np.concatenate([b.flags for b in blocks]),
                   np.concatenate([b.temperature_c for b in blocks]), raw, truth, blocks[0].lost)

    def split(self, n: int) -> tuple["SampleBlock", "SampleBlock"]:
        """(the first ``n`` rows, the rest): the first keeps ``lost`` (it is before row 0),
        the rest has none (its row 0 follows the first part's last row without a gap)."""
        def cut(sl: slice, lost: LossCounts) -> "SampleBlock":
            return SampleBlock(
                self.t_ns[sl], self.gyr[sl], self.acc[sl], self.mag[sl], self.flags[sl],
                self.temperature_c[sl],
                None if self.raw is None else {k: v[sl] for k, v in self.raw.items()},
                None if self.truth_q is None else self.truth_q[sl], lost)
        return cut(slice(0, n), self.lost), cut(slice(n, None), LossCounts())

    def samples(self) -> Iterator[ImuSample]:
        """The rows as :class:`ImuSample` objects, oldest first (for per-sample consumers)."""
        for i in range(len(self.t_ns)):
            yield self.sample(i)


@dataclass
class SourceDiagnostics:
    """Fault counters of one source; the service publishes them (SYS_STATUS, STATUSTEXT, MCAP).

    Every fault a source survives increments one of these; ``last_error`` keeps the latest
    message for humans.
    """

    samples: int = 0
    bus_errors: int = 0  # I2C OSError/NACK, CAN interface errors
    retries: int = 0
    reinitialisations: int = 0
    device_lost: bool = False
    saturated: int = 0
    non_finite: int = 0
    dropped_frames: int = 0  # malformed / foreign / out-of-order CAN frames
    incomplete_transfers: int = 0
    last_error: str = ""
    #: samples lost since the start, by cause (blocks carry theirs, this is the sum)
    lost: LossCounts = field(default_factory=LossCounts)
    extra: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        d = {k: getattr(self, k) for k in self.__dataclass_fields__ if k not in ("extra", "lost")}
        d["lost"] = self.lost.as_dict()
        d.update(self.extra)
        return d


def bus_simulation_cpu_s(bus: Any) -> float | None:
    """``simulation_cpu_s`` of a source on ``bus``: the simulated bus's count, None on a real one."""
    return bus.simulation_cpu_ns / 1e9 if getattr(bus, "simulated", False) else None


class ImuSource(abc.ABC):
    """Base of every sensor input. Subclasses implement ``open``, ``read`` and ``close``."""

    #: whether this source can deliver magnetometer readings at all
    has_mag: bool = True
    #: whether several samples can be due at once (a FIFO, a replayed log): the service then
    #: reads until ``read`` returns None, a bounded number per tick, so a late tick loses nothing
    may_have_backlog: bool = False
    #: whether ``t_ns`` is already each sample's instant on the sensor's clock (a FIFO timed
    #: by its position in the burst, a flight log's recorded times); otherwise it is the
    #: host's read time and the service recovers the sample times (ahrs_service.core.sample_clock)
    times_on_sensor_clock: bool = False
    #: bursts per second a source that reads blocks (a FIFO) is drained at: the service's
    #: loop wakes at this rate (Hz); None: one sample per tick at the estimation rate
    wakeup_rate_hz: float | None = None
    #: whether each tick the loop skips loses a sample: a part without FIFO polled once per
    #: tick keeps only its newest sample in its data registers, so the samples of a host
    #: stall are overwritten unread; the service counts the skipped ticks in
    #: ``diagnostics.lost.host_stall`` (loop periods: the estimation rate the part is read at)
    skipped_ticks_lose_samples: bool = False
    #: how late (s) the loop may come to this source without a sample being lost: what its
    #: FIFO holds beyond one drain's worth. None: no bound the loop can approach (a socket's
    #: buffer, a recording) or none to warn of (a part that loses a sample per skipped tick
    #: counts it lost at once). The service warns of samples at risk when a tick is late by
    #: half of it (ahrs_service/health.py)
    late_tolerance_s: float | None = None

    def __init__(self) -> None:
        self.diagnostics = SourceDiagnostics()

    @property
    def simulation_cpu_s(self) -> float | None:
        """CPU time (s) this process has spent being the simulated hardware behind this source
        (a simulated bus's transfers and its parts' making of samples), which real hardware
        does for nothing; None when the hardware is real or not simulated behind a bus. The
        service logs it on /loop (``simulation_cpu_s``) so benchmarks can state its own work."""
        return None

    @abc.abstractmethod
    def open(self) -> None:
        """Connects and configures the device; raises a clear error naming bus/address on failure."""

    @abc.abstractmethod
    def read(self) -> ImuSample | None:
        """The newest new sample, or None when nothing new arrived since the last call.

        Must not raise on transient faults: count them in ``diagnostics`` and return None.
        """

    def read_block(self, max_samples: int = 64) -> SampleBlock:
        """Every new sample, at most ``max_samples``, as one block (possibly empty).

        The base implementation calls :meth:`read` (once for a source without backlog, until
        it returns None otherwise) and packs the samples; sources that read bursts (a FIFO)
        override it. Must not raise on transient faults, like ``read``.
        """
        samples = []
        for _ in range(max_samples if self.may_have_backlog else 1):
            sample = self.read()
            if sample is None:
                break
            samples.append(sample)
        return SampleBlock.from_samples(samples)

    def close(self) -> None:
        """Releases the bus."""

    def __enter__(self) -> "ImuSource":
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
