"""The DIDO quadrotor flights: one HDF5 file per flight, IMU at ~400 Hz with attitude truth.

Source: K. Zhang, C. Jiang, J. Li, S. Yang, T. Ma, C. Xu, F. Gao, "DIDO: Deep Inertial
Quadrotor Dynamical Odometry", IEEE Robotics and Automation Letters 7(4), 2022
(arXiv:2203.03149); data from the authors' repository zhangkunyi/DIDO, which carries no
licence: the files are read for evaluation and tests only, never copied into the project.

Each file holds ``ts`` (s, epoch; the host's stamps, which jitter), ``gyr`` (rad/s) and ``acc``
(m/s², specific force, about +9.8 on the axis pointing up at rest) in the IMU frame, and
``gt_q`` [w, x, y, z] rotating IMU-frame vectors into a gravity-aligned world frame with z up
and arbitrary heading. There is no magnetometer: flights are scored on inclination only (the
angle between the estimated and the true gravity direction in the IMU frame), over each
flight after its first 10 % (convergence). ``gt_*``, ``meas_rpm`` and ``dynamic_params`` are
never read: nothing but the IMU reaches an estimator.

A ``Flight`` has the fields the evaluation reads from a BROAD ``Trial`` (gyr, acc, mag, ref,
movement, rate_hz, groups), plus the recorded ``timestamps``. ``ref`` is ``gt_q``: its world
frame shares the vertical with ENU, and the inclination error does not depend on heading.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ahrs_service.evaluation.hdf5_folder import RecordingFolder

#: The citation every document, plot or table made from the data must carry.
CITATION = (
    'K. Zhang, C. Jiang, J. Li, S. Yang, T. Ma, C. Xu, F. Gao, "DIDO: Deep Inertial Quadrotor '
    'Dynamical Odometry", IEEE Robotics and Automation Letters 7(4), 2022, arXiv:2203.03149 '
    "(data: github.com/zhangkunyi/DIDO, evaluation use only)."
)

#: Environment variable that points at the flights folder.
ENV_VAR = "AHRS_DIDO_DIR"

#: Fraction of each flight skipped before scoring (the estimators' convergence).
SKIP_FRACTION = 0.10

#: The single group every flight belongs to (the report's per-group tables).
GROUP = "all_flights"

_KEYS = ("ts", "gyr", "acc", "gt_q")

#: The flights folder: where it is, the files in it, opening one (shared with BROAD's loader).
FOLDER = RecordingFolder("DIDO", ENV_VAR, "dido", "flight")


@dataclass
class Flight:
    """One DIDO flight.

    gyr rad/s, acc m/s² (specific force): (N, 3) in the IMU frame; mag (N, 3) all NaN (none
    recorded). ref: (N, 4) gt_q [w, x, y, z], q_world←imu with world z up. timestamps: (N,)
    the recorded host stamps, s. movement: (N,) bool, the scored samples (after the first
    10 %). rate_hz: the rate of a straight-line fit of time against sample index (the sensor's
    own rate; the stamps' median step is 2–4 % short of it).
    """

    name: str
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    ref: np.ndarray
    timestamps: np.ndarray
    movement: np.ndarray
    rate_hz: float
    groups: list[str] = field(default_factory=lambda: [GROUP])
    description: str = ""

    def __len__(self) -> int:
        return self.gyr.shape[0]

    @property
    def duration_s(self) -> float:
        return float(self.timestamps[-1] - self.timestamps[0]) if len(self) else 0.0


def default_dir() -> Path:
    """``$AHRS_DIDO_DIR`` when set, else ``../shared/data/dido`` relative to the working directory."""
    return FOLDER.default_dir()


def missing_reason(data_dir: str | os.PathLike) -> str | None:
    """Why the flights cannot be read from ``data_dir`` (None when they can): for test skips."""
    problem = FOLDER.problem(data_dir)
    if problem is not None:
        return problem
    try:
        import h5py  # noqa: F401
    except ImportError:
        return "reading DIDO needs h5py: install the extra 'recordings' (pip install 'ahrs-service[recordings]')"
    return None


def check_dir(data_dir: str | os.PathLike) -> Path:
    """The folder as a Path; FileNotFoundError with a clear message when it holds no flights."""
    return FOLDER.check_dir(data_dir)


def list_trials(data_dir: str | os.PathLike, pattern: str | None = None) -> list[str]:
    """Names of the flights present, sorted; ``pattern`` a substring or shell glob."""
    return FOLDER.names(data_dir, pattern)


def list_groups(data_dir: str | os.PathLike, trials: list[str] | None = None) -> dict[str, list[str]]:
    """One group holding every flight (DIDO has no trial groups)."""
    present = list_trials(data_dir) if trials is None else list(trials)
    return {GROUP: present} if present else {}


def fitted_rate_hz(t: np.ndarray) -> float:
    """Rate (Hz) of the least-squares line of time against sample index."""
    n = np.arange(t.size, dtype=np.float64)
    slope = np.polyfit(n, t - t[0], 1)[0]
    return float(1.0 / slope)


def load_trial(data_dir: str | os.PathLike, name: str) -> Flight:
    """Reads one flight (all of it into memory)."""
    with FOLDER.open(data_dir, name, _KEYS) as f:
        file = f.filename
        t = np.asarray(f["ts"][:], dtype=np.float64)
        gyr = np.asarray(f["gyr"][:], dtype=np.float64)
        acc = np.asarray(f["acc"][:], dtype=np.float64)
        ref = np.asarray(f["gt_q"][:], dtype=np.float64)
    n = t.size
    if gyr.shape != (n, 3) or acc.shape != (n, 3) or ref.shape != (n, 4):
        raise ValueError(f"{file}: ts, gyr, acc, gt_q have inconsistent shapes {t.shape}, {gyr.shape}, {acc.shape}, {ref.shape}")
    movement = np.arange(n) >= int(np.ceil(SKIP_FRACTION * n))
    return Flight(
        name=name, gyr=gyr, acc=acc, mag=np.full((n, 3), np.nan), ref=ref, timestamps=t,
        movement=movement, rate_hz=fitted_rate_hz(t),
    )
