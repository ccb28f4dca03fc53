"""The BROAD recordings: one HDF5 file per trial plus ``trials.json`` with the trial groups.

Source: D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD — A Benchmark for Robust Inertial
Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072 (CC BY 4.0).

The IMU data stay in the sensor's own axes (its z axis points up at rest, so a resting
accelerometer reads about +9.81 m/s² on z — still specific force). The reference
``opt_quat`` maps sensor-frame vectors into an ENU earth frame whose north is magnetic north.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ahrs_service.evaluation.hdf5_folder import RecordingFolder

#: The citation every document, plot or table made from the data must carry.
CITATION = (
    'D. Laidig, M. Caruso, A. Cereatti, T. Seel, "BROAD — A Benchmark for Robust Inertial '
    'Orientation Estimation", Data 6(7), 2021, doi:10.3390/data6070072. Licence: CC BY 4.0.'
)

#: Environment variable that points at the recordings folder.
ENV_VAR = "AHRS_BROAD_DIR"

#: The recordings folder: where it is, the files in it, opening one (shared with DIDO's loader).
FOLDER = RecordingFolder("BROAD", ENV_VAR, "broad", "recording")


@dataclass
class Trial:
    """One BROAD recording.

    gyr rad/s, acc m/s² (specific force), mag µT: (N, 3) in the sensor's axes.
    ref: (N, 4) q_enu←sensor [w, x, y, z], NaN where the cameras lost the marker.
    movement: (N,) bool, the samples on which errors are scored. rate_hz: sampling rate.
    """

    name: str
    gyr: np.ndarray
    acc: np.ndarray
    mag: np.ndarray
    ref: np.ndarray
    movement: np.ndarray
    rate_hz: float
    groups: list[str] = field(default_factory=list)
    description: str = ""

    def __len__(self) -> int:
        return self.gyr.shape[0]

    @property
    def duration_s(self) -> float:
        return len(self) / self.rate_hz


def default_dir() -> Path:
    """``$AHRS_BROAD_DIR`` when set, else ``../shared/data/broad`` relative to the working directory."""
    return FOLDER.default_dir()


def check_dir(data_dir: str | os.PathLike) -> Path:
    """The folder as a Path; FileNotFoundError with a clear message when it holds no recordings."""
    return FOLDER.check_dir(data_dir)


def load_index(data_dir: str | os.PathLike) -> dict:
    """``trials.json`` of the folder: {"groups": [...], "trials": {name: {...}}}.

    Without the file, every recording found is listed in the single group "all_trials".
    """
    path = check_dir(data_dir)
    index_file = path / "trials.json"
    if index_file.is_file():
        with open(index_file, encoding="utf-8") as fh:
            return json.load(fh)
    trials = {p.stem: {"description": "", "groups": ["all_trials"]} for p in sorted(path.glob("*.hdf5"))}
    return {"groups": [{"name": "all_trials", "level": 0, "category": ""}], "trials": trials}


def list_trials(data_dir: str | os.PathLike, pattern: str | None = None) -> list[str]:
    """Names of the recordings present in the folder, sorted.

    ``pattern`` (a substring, or a shell glob such as ``magnet_?cm``) may match anywhere in the name.
    """
    return FOLDER.names(data_dir, pattern)


def list_groups(data_dir: str | os.PathLike, trials: list[str] | None = None) -> dict[str, list[str]]:
    """Group name → the trials (among ``trials``, default all present) in it, in trials.json order.

    Groups without any of the trials are left out.
    """
    index = load_index(data_dir)
    present = list_trials(data_dir) if trials is None else list(trials)
    out: dict[str, list[str]] = {}
    for group in index.get("groups", []):
        gname = group["name"]
        members = [t for t in present if gname in index["trials"].get(t, {}).get("groups", [])]
        if members:
            out[gname] = members
    return out


def load_trial(data_dir: str | os.PathLike, name: str) -> Trial:
    """Reads one recording (all of it into memory)."""
    info = load_index(data_dir)["trials"].get(name, {})
    with FOLDER.open(data_dir, name, ("imu_gyr", "imu_acc", "imu_mag", "opt_quat", "movement")) as f:
        if "sampling_rate" not in f.attrs:
            raise ValueError(f"{f.filename}: missing attribute 'sampling_rate'")
        return Trial(
            name=name,
            gyr=np.asarray(f["imu_gyr"][:], dtype=np.float64),
            acc=np.asarray(f["imu_acc"][:], dtype=np.float64),
            mag=np.asarray(f["imu_mag"][:], dtype=np.float64),
            ref=np.asarray(f["opt_quat"][:], dtype=np.float64),
            movement=np.asarray(f["movement"][:], dtype=bool),
            rate_hz=float(f.attrs["sampling_rate"]),
            groups=list(info.get("groups", [])),
            description=str(info.get("description", "")),
        )
