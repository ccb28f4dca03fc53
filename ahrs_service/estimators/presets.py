"""Parameter presets: named parameter sets for an estimator, read from a preset file.

A preset file is JSON written by ``ahrs-service tune`` (``ahrs_service.evaluation.tuning``):
``{"estimator": NAME, "params": {FIELD: VALUE, ...}, "command": ..., scores ...}``.
``estimators.create(name, preset=PATH)`` and ``estimators.run(..., preset=PATH)`` start from
its ``params``; explicit keyword parameters override it. An estimator other than the one
asked for, a parameter the estimator does not have, or a value outside the field's bounds is
a ValueError naming it. The bounds are those of the configuration file's ``estimator.params``
(:func:`range_violation`: within :data:`CONFIG_RANGE_FACTOR` of the field's default or paper
value, never of the preset's own value), and a preset file is read only when it is a small,
shallow JSON document (:data:`MAX_PRESET_BYTES`, :data:`MAX_PRESET_DEPTH`).

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


#: how far the configuration file's ``estimator.params`` (and a preset file's values) may move
#: a value from its reference: wider than over the air, short of values no filter survives
#: (``beta = 1e300``)
CONFIG_RANGE_FACTOR = 1e6
#: a preset file is a few hundred bytes (``ahrs-service tune`` writes parameters, the command
#: and scores); anything far larger is not one
MAX_PRESET_BYTES = 1 << 20
#: nesting a preset file may have: ``tune`` writes three levels; JSON nested deeper than
#: Python's recursion limit would end its parser in a RecursionError
MAX_PRESET_DEPTH = 32


def param_bounds(default: float, factor: float) -> tuple[float, float]:
    """[minimum, maximum] of an estimator parameter: from 0 to ``factor`` times its default
    on the default's side (a gain, a time constant, a noise level); ±factor around a default
    of 0."""
    if default > 0:
        return 0.0, default * factor
    if default < 0:
        return default * factor, 0.0
    return -factor, factor


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def range_violation(name: str, value: Any, references: list[dict[str, Any]]) -> str | None:
    """What is wrong with parameter ``name`` = ``value`` against its ``references`` (dicts of
    reference values: its default, its paper value), or None when it is within
    :data:`CONFIG_RANGE_FACTOR` of the largest of them (a paper's 1e9 for "gate off"). A finite
    1e300 passes an estimator's own checks and overflows inside it."""
    refs = [r[name] for r in references if _is_number(r.get(name))]
    if not _is_number(value) or not refs:
        return None
    reference = max(refs, key=abs)
    lo, hi = param_bounds(float(reference), CONFIG_RANGE_FACTOR)
    if lo <= value <= hi:
        return None
    return f"{value!r}: must be within {lo:g} … {hi:g} ({CONFIG_RANGE_FACTOR:g} × its default {reference:g})"


def reference_params(name: str) -> list[dict[str, Any]]:
    """The values the ranges of estimator ``name``'s parameters are taken from: its defaults
    (the ``Params`` fields') and, where declared, its paper values."""
    params_cls = get(name).Params
    references = [get(name)().get_params()]
    if has_paper_preset(params_cls):
        references.append(paper_params(name, params_cls))
    return references


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
    A file's values are checked against the estimator's own ranges (:func:`range_violation`);
    a value outside them is a ValueError naming the file and the key.
    """
    if str(preset) == PAPER:
        return paper_params(name, get(name).Params)
    path = Path(preset)
    if not path.is_file():
        raise ValueError(f"preset {str(preset)!r} of estimator {name!r}: no such file")
    if path.stat().st_size > MAX_PRESET_BYTES:
        raise ValueError(f"preset {str(path)!r}: not a preset file ({path.stat().st_size} bytes, "
                         f"more than {MAX_PRESET_BYTES} a preset may have)")
    try:
        text = path.read_text(encoding="utf-8")
        depth = json_depth(text)
        if depth > MAX_PRESET_DEPTH:
            raise ValueError(f"nested {depth} levels deep, more than {MAX_PRESET_DEPTH}")
        data = json.loads(text)
    except (OSError, ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ValueError(f"preset {str(path)!r}: not a preset file ({str(exc).splitlines()[0][:120]})") from None
    if not isinstance(data, dict) or not isinstance(data.get("params"), dict):
        raise ValueError(f"preset {str(path)!r}: no 'params' table")
    if data.get("estimator") not in (None, name):
        raise ValueError(f"preset {str(path)!r} is for estimator {data['estimator']!r}, not {name!r}")
    params = dict(data["params"])
    references = reference_params(name)  # the estimator's own: a preset is no reference of itself
    for key, value in params.items():
        wrong = range_violation(key, value, references)
        if wrong is not None:
            raise ValueError(f"preset {str(path)!r}: params.{key} = {wrong}")
    return params


def json_depth(text: str) -> int:
    """The deepest nesting of arrays and objects in JSON ``text`` (brackets inside strings do
    not count), found without parsing it: a linear scan, whatever the depth."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest
