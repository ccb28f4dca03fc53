"""A recorded flight (MCAP log) or BROAD recording (HDF5) played back as a sensor source.

The samples are handed out as recorded (for a log: the calibrated body-frame values the
service fed its estimator; for BROAD: the sensor axes), with the recorded ground truth when
there is one. ``realtime=True`` paces them on ``time.monotonic`` as they were recorded;
``realtime=False`` gives one sample per ``read`` call, as fast as the caller asks.
``finished`` turns True after the last sample. A flight log without a single sample is a
ValueError at ``open`` (naming the damage, if any): there is nothing to play.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ahrs_service.core.samples import ImuSample, ImuSource
from ahrs_service.estimators import SAMPLE_ROW

_R = SAMPLE_ROW.slices


class RecordedSource(ImuSource):
    """Plays ``path`` (``.mcap`` flight log or ``.hdf5`` BROAD trial).

    realtime: pace on the monotonic clock (True) or as fast as possible (False).
    rebase_time: give t_ns on the host's monotonic clock (recorded offsets added to the time
        of the first read) instead of the recorded t_ns; default: the same as ``realtime``.
    start_s, duration_s: a slice (HDF5 only).
    catch_up: in real time, a late caller gets the missed samples one by one, in order (True:
        a replay loses nothing; ``may_have_backlog`` tells the service to read until None);
        False gives the newest due sample and counts the skipped ones as ``dropped_frames``,
        like a live sensor without a FIFO.

    ``calibrated`` tells the service whether the samples are already calibrated body-frame
    values (True for a flight log: it recorded what the estimator was fed) or raw sensor-axis
    readings (False for BROAD), i.e. whether calibration/mounting must still be applied.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        realtime: bool = True,
        rebase_time: bool | None = None,
        start_s: float | None = None,
        duration_s: float | None = None,
        catch_up: bool = True,
    ) -> None:
        super().__init__()
        self.catch_up = catch_up
        self.path = Path(path)
        self.realtime = realtime
        self.rebase_time = realtime if rebase_time is None else rebase_time
        self.start_s, self.duration_s = start_s, duration_s
        self.finished = False
        self.calibrated = False
        self.damage = None
        self._i = 0
        self._t0_host: int | None = None

    @property
    def may_have_backlog(self) -> bool:  # type: ignore[override]
        return self.catch_up

    def open(self) -> None:
        if self.path.suffix.lower() in (".hdf5", ".h5"):
            from ahrs_service.evaluation.broad_import import load_broad, sample_flags

            s = load_broad(self.path, self.start_s, self.duration_s)
            self.rows, self.t_ns, self.truth = s.rows, s.t_ns, s.truth
            self.flags = sample_flags(s.rows)
            self.calibrated = False
        else:
            from ahrs_service.logs.reader import read_log

            log = read_log(self.path)
            if len(log.t_ns) == 0:
                # a run that plays nothing would start, stop at once and exit 0 ("samples 0")
                damage = f" ({log.damage})" if log.damage else ""
                raise ValueError(f"recorded log {self.path}: no samples to play{damage}")
            self.rows, self.t_ns, self.truth, self.flags = log.rows, log.t_ns, log.truth, log.flags
            self.damage = log.damage
            self.calibrated = True
        # a flight log's t_ns are the recovered sample times its dt came from: never recovered
        # again; a BROAD recording's are its device's stamps
        self.times_on_sensor_clock = self.calibrated
        self.has_mag = bool(np.isfinite(self.rows[:, _R.mag]).any())
        self._precompute()
        self._i = 0
        self._t0_host = None
        self.finished = len(self.t_ns) == 0

    def _precompute(self) -> None:
        """What read() needs per sample, for the whole recording at once (vectorised).

        read() runs at the sample rate; NumPy reductions and scalar arithmetic on a 3-element
        slice cost microseconds each, the same answers looked up in a Python list ~50 ns.
        """
        t = self.t_ns
        # t_ns is int64 (reader, BROAD import): Python ints give the same values exactly
        self._t_list = t.tolist()
        self._offsets = (t - t[0]).tolist() if len(t) else []
        self._flags_list = self.flags.tolist()
        self._mag_ok = np.isfinite(self.rows[:, _R.mag]).all(axis=1).tolist()
        self._truth_ok = None if self.truth is None else np.isfinite(self.truth).all(axis=1).tolist()

    def __len__(self) -> int:
        return len(self.t_ns)

    def read(self) -> ImuSample | None:
        if self.finished:
            return None
        now = time.monotonic_ns()
        if self._t0_host is None:
            self._t0_host = now
        i = self._i
        offsets = self._offsets
        if self.realtime:
            elapsed = now - self._t0_host
            if elapsed < offsets[i]:
                return None  # not due yet
            if not self.catch_up:
                # the newest due sample, like a live sensor: skip the missed ones
                n = len(offsets)
                while i + 1 < n and offsets[i + 1] <= elapsed:
                    i += 1
                    self.diagnostics.dropped_frames += 1
        self._i = i + 1
        self.finished = self._i >= len(offsets)
        row = self.rows[i].copy()  # one copy; the sample's vectors are views of it
        truth_ok = self._truth_ok is not None and self._truth_ok[i]
        self.diagnostics.samples += 1
        return ImuSample(
            t_ns=self._t0_host + offsets[i] if self.rebase_time else self._t_list[i],
            gyr=row[_R.gyr],
            acc=row[_R.acc],
            mag=row[_R.mag] if self._mag_ok[i] else None,
            flags=self._flags_list[i],
            truth_q=self.truth[i].copy() if truth_ok else None,
        )

    @property
    def last_dt(self) -> float:
        """The dt (s) recorded with the sample read last: feed it for a bit-exact re-run."""
        return float(self.rows[max(self._i - 1, 0), SAMPLE_ROW.index.dt])
