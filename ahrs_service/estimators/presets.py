"""Parameter presets: named parameter sets for an estimator, read from a preset file.

A preset file is JSON written by ``ahrs-service tune`` (``ahrs_service.evaluation.tuning``):
``{"estimator": NAME, "params": {FIELD: VALUE, ...}, "command": ..., scores ...}``.
``estimators.create(name, preset=PATH)`` and ``estimators.run(..., preset=PATH)`` start from
its ``params``; explicit keyword parameters override it. An estimator other than the one
asked for, a parameter the estimator does not have, or a value outside the field's bounds is
a ValueError naming it.

The estimators' defaults are the presets tuned on BROAD and DIDO together that ship in
``ahrs_service/estimators/tuned/NAME.json`` (``Params`` defaults equal their ``params``; a
test keeps them so). ``preset="paper"`` gives the source papers' values instead, declared
beside each field (:func:`tunable`). Details: docs/tuning.md.

:class:`SearchRange` is the search-space declaration a ``Params`` field carries in its
metadata (``dataclasses.field(default=..., metadata={"search": SearchRange(...)})``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ahrs_service.estimators.registry import get


@dataclass(frozen=True)
class SearchRange:
    """Where ``tune`` looks for a parameter: ``low`` .. ``high`` (the field's unit), ``log`` scale."""

    low: float
    high: float
    log: bool = False


def tunable(default: float, *, paper: float, search: SearchRange | None = None) -> Any:
    """A ``Params`` field: its tuned ``default``, the source paper's value and its search range.

    ``paper`` is what ``preset="paper"`` gives the field (see :func:`paper_params`); ``search``
    is where ``ahrs-service tune`` looks (None: the field is not tuned, e.g. a site constant).
    """
    meta: dict[str, Any] = {"paper": paper}
    if search is not None:
        meta["search"] = search
    return field(default=default, metadata=meta)


#: The preset name that selects the source papers' values instead of the tuned defaults.
PAPER = "paper"

#: Folder of the shipped tuned presets, one ``NAME.json`` per estimator (their params are the
#: ``Params`` defaults; the file records the command, date, budget and scores behind them).
TUNED_DIR = Path(__file__).with_name("tuned")


def _paper_values(params_cls: type) -> dict[str, Any]:
    import dataclasses

    return {f.name: f.metadata["paper"] for f in dataclasses.fields(params_cls) if "paper" in f.metadata}


def has_paper_preset(params_cls: type) -> bool:
    """Whether ``params_cls`` declares paper values (else ``preset="paper"`` is a ValueError)."""
    return bool(_paper_values(params_cls))


def paper_params(name: str, params_cls: type) -> dict[str, Any]:
    """The source paper's value of every field of ``params_cls`` that declares one."""
    out = _paper_values(params_cls)
    if not out:
        raise ValueError(f"estimator {name!r} has no preset {PAPER!r} (its parameters declare no paper values)")
    return out


def tuned_preset_path(name: str) -> Path:
    """The shipped tuned preset file of estimator ``name`` (it may not exist: robust, triad …)."""
    return TUNED_DIR / f"{name}.json"


def load_preset(name: str, preset: str | os.PathLike) -> dict[str, Any]:
    """The ``params`` of preset ``preset`` for estimator ``name`` (ValueError on mismatch).

    ``preset`` is ``"paper"`` (the source paper's values, :func:`paper_params`) or a preset file.
    """
    if str(preset) == PAPER:
        return paper_params(name, get(name).Params)
    path = Path(preset)
    if not path.is_file():
        raise ValueError(f"preset {str(preset)!r} of estimator {name!r}: no such file")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"preset {str(path)!r}: not a preset file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("params"), dict):
        raise ValueError(f"preset {str(path)!r}: no 'params' table")
    if data.get("estimator") not in (None, name):
        raise ValueError(f"preset {str(path)!r} is for estimator {data['estimator']!r}, not {name!r}")
    return dict(data["params"])
