"""Parameter presets: named parameter sets for an estimator, read from a preset file.

A preset file is JSON written by ``ahrs-service tune`` (``ahrs_service.evaluation.tuning``):
``{"estimator": NAME, "params": {FIELD: VALUE, ...}, "command": ..., scores ...}``.
``estimators.create(name, preset=PATH)`` and ``estimators.run(..., preset=PATH)`` start from
its ``params``; explicit keyword parameters override it. An estimator other than the one
asked for, or a parameter the estimator does not have, is a ValueError naming it.

:class:`SearchRange` is the search-space declaration a ``Params`` field carries in its
metadata (``dataclasses.field(default=..., metadata={"search": SearchRange(...)})``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class SearchRange:
    """Where ``tune`` looks for a parameter: ``low`` .. ``high`` (the field's unit), ``log`` scale."""

    low: float
    high: float
    log: bool = False


def load_preset(name: str, preset: str | os.PathLike) -> dict[str, Any]:
    """The ``params`` of preset file ``preset`` for estimator ``name`` (ValueError on mismatch)."""
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
