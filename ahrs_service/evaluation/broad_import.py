"""Turning a BROAD recording (HDF5) into a flight log (MCAP) with ground truth.

BROAD: D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD — A Benchmark for Robust Inertial
Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072 (CC BY 4.0). Every log
made here carries that citation in its MCAP metadata ("broad").

The IMU data stay in the sensor's axes (the rows are what an estimator is fed; BROAD's
sensor z points up at rest). The reference ``opt_quat`` (q_enu←sensor) is turned into our
NED convention, q_ned = conj(Q_NED_TO_ENU) ⊗ q_enu, and written to /attitude/truth with the
``movement`` flag; samples whose reference is NaN get no truth message. Sample i has
t_ns = round(i · 10⁹ / rate) counted from the start of the trial, and dt = 1 / rate.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from ahrs_service.core.quaternion import Q_NED_TO_ENU, quat_conj_array, quat_mul_array
from ahrs_service.core.samples import ACC_VALID, GYR_VALID, MAG_NEW, MAG_VALID
from ahrs_service.estimators import SAMPLE_ROW
from ahrs_service.evaluation.broad import CITATION
from ahrs_service.logs.mcap_file import McapLogFile
from ahrs_service.logs.schemas import raw_message, truth_message

_R = SAMPLE_ROW.slices


@dataclass
class BroadSlice:
    """Part of one BROAD trial, ready to record or play.

    rows (N, 10) sample rows (sensor axes; rad/s, m/s², µT, dt s); t_ns (N,) int64;
    index (N,) sample numbers in the trial; truth (N, 4) q_ned←sensor [w, x, y, z] (NaN where
    the cameras lost the marker); movement (N,) bool; rate_hz; name of the trial.
    """

    name: str
    rate_hz: float
    rows: np.ndarray
    t_ns: np.ndarray
    index: np.ndarray
    truth: np.ndarray
    movement: np.ndarray


def enu_to_ned(q_enu: np.ndarray) -> np.ndarray:
    """q_ned←body of (N, 4) q_enu←body: conj(Q_NED_TO_ENU) ⊗ q_enu (NaN rows stay NaN)."""
    return quat_mul_array(quat_conj_array(Q_NED_TO_ENU), q_enu)


def load_broad(path: str | os.PathLike, start_s: float | None = None, duration_s: float | None = None) -> BroadSlice:
    """Reads samples [start_s, start_s + duration_s) of a BROAD trial (whole trial by default)."""
    path = Path(path)
    with h5py.File(path, "r") as h5:
        rate = float(h5.attrs["sampling_rate"])
        n_all = h5["imu_gyr"].shape[0]
        a = 0 if start_s is None else max(0, int(round(start_s * rate)))
        b = n_all if duration_s is None else min(n_all, a + int(round(duration_s * rate)))
        if b <= a:
            raise ValueError(f"{path.name}: empty slice (start {start_s} s, duration {duration_s} s, {n_all / rate:.1f} s long)")
        gyr = np.asarray(h5["imu_gyr"][a:b], dtype=np.float64)
        acc = np.asarray(h5["imu_acc"][a:b], dtype=np.float64)
        mag = np.asarray(h5["imu_mag"][a:b], dtype=np.float64)
        ref = np.asarray(h5["opt_quat"][a:b], dtype=np.float64)
        movement = np.asarray(h5["movement"][a:b], dtype=bool)
    n = b - a
    rows = np.empty((n, SAMPLE_ROW.end))
    rows[:, _R.gyr], rows[:, _R.acc], rows[:, _R.mag] = gyr, acc, mag
    rows[:, SAMPLE_ROW.index.dt] = 1.0 / rate
    index = np.arange(a, b, dtype=np.int64)
    t_ns = np.round(index * (1e9 / rate)).astype(np.int64)
    return BroadSlice(path.stem, rate, rows, t_ns, index, enu_to_ned(ref), movement)


def sample_flags(rows: np.ndarray) -> np.ndarray:
    """(N,) int64 validity bits of (N, 10) recorded rows: a reading is valid when all its values are finite."""
    ok = np.isfinite(np.asarray(rows)[..., : _R.mag.stop])
    gyr, acc, mag = ok[..., _R.gyr].all(axis=-1), ok[..., _R.acc].all(axis=-1), ok[..., _R.mag].all(axis=-1)
    return np.where(gyr, GYR_VALID, 0) | np.where(acc, ACC_VALID, 0) | np.where(mag, MAG_VALID | MAG_NEW, 0)


def import_broad(
    path: str | os.PathLike,
    out_path: str | os.PathLike,
    start_s: float | None = None,
    duration_s: float | None = None,
) -> dict[str, int | float | str]:
    """Writes a BROAD trial (or a slice of it) as an MCAP flight log; returns a short summary."""
    s = load_broad(path, start_s, duration_s)
    truth_ok = np.all(np.isfinite(s.truth), axis=1)
    flags = sample_flags(s.rows).tolist()
    t0 = int(s.t_ns[0])
    config = {
        "source": {"kind": "broad", "trial": s.name, "rate_hz": s.rate_hz, "first_sample": int(s.index[0])},
        "frames": {"imu": "BROAD sensor axes (z up at rest)", "truth": "q_ned<-sensor"},
    }
    meta = {"trial": s.name, "citation": CITATION, "licence": "CC BY 4.0", "sampling_rate": repr(s.rate_hz)}
    with McapLogFile(out_path, metadata={"source": "BROAD"}) as f:
        f.add_metadata("broad", meta)
        f.write("/config", t0, {"t_ns": t0, "reason": "import", "config": config})
        for i in range(len(s.t_ns)):
            t = int(s.t_ns[i])
            row = s.rows[i].tolist()
            f.write("/imu/raw", t, raw_message(t, row, flags[i], index=int(s.index[i])))
            if truth_ok[i]:
                f.write("/attitude/truth", t, truth_message(t, s.truth[i].tolist(), bool(s.movement[i]), "BROAD opt_quat"))
    return {
        "trial": s.name,
        "samples": int(len(s.t_ns)),
        "truth_samples": int(truth_ok.sum()),
        "duration_s": len(s.t_ns) / s.rate_hz,
        "output": str(out_path),
    }
