"""A data set's folder of HDF5 files, one per recording: what the BROAD and DIDO loaders
(``broad.py``, ``dido.py``) share before they read their own datasets.

Where the folder is (an environment variable, else ``../shared/data/<name>`` relative to the
working directory), why it cannot be read (one line naming the folder), the recordings in it,
and opening one with its datasets checked. ``h5py`` comes from the extra ``recordings``.
"""

from __future__ import annotations

import fnmatch
import os
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator


@dataclass(frozen=True)
class RecordingFolder:
    """dataset: the data set's name in messages ("BROAD"); env_var: the variable naming its
    folder; shared_name: the folder's name under ``../shared/data``; item: what one file
    holds, in messages ("recording", "flight")."""

    dataset: str
    env_var: str
    shared_name: str
    item: str

    def default_dir(self) -> Path:
        """``$<env_var>`` when set, else ``../shared/data/<shared_name>``."""
        env = os.environ.get(self.env_var)
        return Path(env) if env else Path("..") / "shared" / "data" / self.shared_name

    def problem(self, data_dir: str | os.PathLike) -> str | None:
        """Why the folder holds nothing to read (None when it does), in one line."""
        path = Path(data_dir)
        if not path.is_dir():
            return f"{self.dataset} data folder {str(path)!r} does not exist; pass --data DIR or set {self.env_var}"
        if not any(path.glob("*.hdf5")):
            return f"{self.dataset} data folder {str(path)!r} holds no *.hdf5 {self.item}s"
        return None

    def check_dir(self, data_dir: str | os.PathLike) -> Path:
        """The folder as a Path; FileNotFoundError (:meth:`problem`) when it holds nothing."""
        problem = self.problem(data_dir)
        if problem is not None:
            raise FileNotFoundError(problem)
        return Path(data_dir)

    def names(self, data_dir: str | os.PathLike, pattern: str | None = None) -> list[str]:
        """Stems of the ``*.hdf5`` files, sorted; ``pattern`` (a substring or shell glob such
        as ``magnet_?cm``) may match anywhere in the name."""
        names = sorted(p.stem for p in self.check_dir(data_dir).glob("*.hdf5"))
        if pattern:
            names = [n for n in names if fnmatch.fnmatchcase(n, f"*{pattern}*")]
        return names

    @contextmanager
    def open(self, data_dir: str | os.PathLike, name: str, datasets: tuple[str, ...]) -> Iterator[Any]:
        """The open ``h5py.File`` of recording ``name``: FileNotFoundError when there is none,
        ValueError naming the file when one of ``datasets`` is missing."""
        import h5py

        path = self.check_dir(data_dir)
        file = path / f"{name}.hdf5"
        if not file.is_file():
            raise FileNotFoundError(f"no {self.item} {name!r} in {str(path)!r}")
        with h5py.File(file, "r") as f:
            missing = [k for k in datasets if k not in f]
            if missing:
                raise ValueError(f"{file}: missing dataset(s) {', '.join(missing)}")
            yield f
