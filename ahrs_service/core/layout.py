"""Named slots of a flat float64 array, declared once: estimator states, sample rows and
parameter vectors.

The compiled estimator steps keep their whole state in one float64 array (no allocation per
sample, one array to snapshot into a log). A :class:`Layout` names the consecutive runs of
slots in that array, each with its length and meaning, and computes every offset itself::

    ST = Layout("robust state", [
        Slot("gq", 4, "q_g, I←S"),
        Slot("aq", 4, "q_a, E6←I"),
        ...
    ], start=K.HEADER)
    s[ST.index.gq + 1]          # in a kernel: a compile-time constant
    state[ST.slices.gq]         # in Python: a slice

``index`` is a namedtuple of first indices and ``slices`` one of slices. numba reads a
module-level namedtuple of integers as a constant, so ``s[I.gq + 1]`` compiles to the same
machine code as a literal offset (benchmarks/README.md, "Named state").

:func:`param_index` does the same for a parameter dataclass: the packed parameter vector
follows the order of the dataclass fields, so the dataclass is the one declaration.
"""

from __future__ import annotations

import dataclasses
from collections import namedtuple
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence


@dataclass(frozen=True)
class Slot:
    """A run of ``size`` consecutive float64 slots named ``name``; ``doc`` gives meaning and unit."""

    name: str
    size: int
    doc: str = ""


class Layout:
    """Consecutive named slots from ``start`` (default 0) on, in the order given.

    ``within`` = (first, size) makes an overlay: the slots must fit inside that region of
    another layout (scratch space reused under other names).
    """

    def __init__(self, title: str, slots: Sequence[Slot], start: int = 0, within: tuple[int, int] | None = None) -> None:
        self.title = title
        self.slots = tuple(slots)
        offsets = {}
        at = start
        for slot in self.slots:
            if slot.size < 1:
                raise ValueError(f"{title}: slot {slot.name!r} has size {slot.size}")
            if slot.name in offsets:
                raise ValueError(f"{title}: slot {slot.name!r} declared twice")
            offsets[slot.name] = at
            at += slot.size
        if within is not None and (start < within[0] or at > within[0] + within[1]):
            raise ValueError(f"{title}: slots {start}..{at} do not fit in {within[0]}..{within[0] + within[1]}")
        self.start = start
        #: one past the last slot: the array length when the layout is a whole state
        self.end = at
        self.size = at - start
        names = [slot.name for slot in self.slots]
        self.index: Any = namedtuple(f"{_identifier(title)}_index", names)(*offsets.values())
        self.slices: Any = namedtuple(f"{_identifier(title)}_slices", names)(
            *(slice(offsets[s.name], offsets[s.name] + s.size) for s in self.slots)
        )

    def describe(self) -> list[tuple[str, int, int, str]]:
        """(name, first index, size, meaning) of every slot, in order: the table for the docs."""
        return [(s.name, getattr(self.index, s.name), s.size, s.doc) for s in self.slots]

    def __repr__(self) -> str:
        return f"Layout({self.title!r}, {self.start}..{self.end})"


def param_index(params_cls: type) -> NamedTuple:
    """Namedtuple of the packed parameter vector's indices, one per field of the dataclass
    ``params_cls`` (``Estimator._pack`` packs the fields in declaration order)."""
    names = [f.name for f in dataclasses.fields(params_cls)]
    return namedtuple(f"{params_cls.__name__}_index", names)(*range(len(names)))  # type: ignore[return-value]


def _identifier(title: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in title.title())
