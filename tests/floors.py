"""The layer rule of docs/design.md ("Floors"), checked on the source's own import statements.

Every ``import`` and ``from … import`` in the project's source is read with :mod:`ast` —
at module level, inside functions and under ``TYPE_CHECKING`` alike — and mapped to the
module it names, following ``pyproject.toml``'s ``package-dir`` (``drivers/`` installs as
``ahrs_service.drivers`` and so on). Two rules:

* a module imports only modules of its own floor or of the floors below it, and the three
  middle packages (drivers, protocols, logs) do not import each other;
* no circle: the graph of module imports has no cycle.

Strings passed to ``importlib`` are not imports (``ahrs_service._moved`` keeps the old paths
of moved modules that way).
"""

from __future__ import annotations

import ast
import dataclasses
from collections.abc import Iterable, Mapping
from pathlib import Path

#: folder → installed package (pyproject.toml, [tool.setuptools] package-dir)
PACKAGE_DIRS: dict[str, str] = {
    "ahrs_service": "ahrs_service",
    "drivers": "ahrs_service.drivers",
    "protocols": "ahrs_service.protocols",
    "logs": "ahrs_service.logs",
}

GROUND, ESTIMATORS, MIDDLE, APPLICATION = 0, 1, 2, 3
FLOOR_NAMES = {GROUND: "ground (core)", ESTIMATORS: "estimators", MIDDLE: "drivers/protocols/logs",
               APPLICATION: "application"}
#: the middle floor's rooms, which do not import each other
MIDDLE_PACKAGES = ("ahrs_service.drivers", "ahrs_service.protocols", "ahrs_service.logs")


def floor_of(module: str) -> tuple[int, str]:
    """(floor, room) of a project module; the room tells the middle packages apart."""
    if module in ("ahrs_service", "ahrs_service._moved") or module.startswith("ahrs_service.core"):
        return GROUND, "core"
    if module == "ahrs_service.estimators" or module.startswith("ahrs_service.estimators."):
        return ESTIMATORS, "estimators"
    for package in MIDDLE_PACKAGES:
        if module == package or module.startswith(package + "."):
            return MIDDLE, package
    return APPLICATION, "application"


@dataclasses.dataclass(frozen=True)
class Import:
    importer: str
    imported: str
    line: int
    where: str  # "module", "function" or "type-checking"


def modules_of(root: Path, package_dirs: Mapping[str, str] = PACKAGE_DIRS) -> dict[str, Path]:
    """Every project module's dotted name → its file."""
    found: dict[str, Path] = {}
    for folder, package in package_dirs.items():
        base = root / folder
        for path in sorted(base.rglob("*.py")):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


def _context(node: ast.AST, parents: Mapping[ast.AST, ast.AST]) -> str:
    parent = parents.get(node)
    while parent is not None:
        if isinstance(parent, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            return "function"
        if isinstance(parent, ast.If) and "TYPE_CHECKING" in ast.unparse(parent.test):
            return "type-checking"
        parent = parents.get(parent)
    return "module"


def imports_of(modules: Mapping[str, Path]) -> list[Import]:
    """The project-internal imports of every module (a ``from pkg import sub`` names ``pkg.sub``)."""
    found: list[Import] = []

    def known(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        parents = {child: parent for parent in ast.walk(tree) for child in ast.iter_child_nodes(parent)}
        is_package = path.name == "__init__.py"
        for node in ast.walk(tree):
            named: list[str] = []
            if isinstance(node, ast.Import):
                named = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                    base = ".".join(anchor + ([node.module] if node.module else []))
                for alias in node.names:
                    named.append(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
            else:
                continue
            for name in named:
                target = known(name) if name.startswith("ahrs_service") else None
                if target and target != module:
                    found.append(Import(module, target, node.lineno, _context(node, parents)))
    return found


def violations(imports: Iterable[Import]) -> list[str]:
    """One line per import that goes up a floor or across the middle floor."""
    bad = []
    for imp in imports:
        (floor_a, room_a), (floor_b, room_b) = floor_of(imp.importer), floor_of(imp.imported)
        if imp.imported == "ahrs_service":
            continue  # the package root: every module's parent
        if floor_b > floor_a or (floor_a == floor_b == MIDDLE and room_a != room_b):
            bad.append(f"{imp.importer}:{imp.line} ({imp.where}) imports {imp.imported}: "
                       f"{FLOOR_NAMES[floor_a]} may not import {FLOOR_NAMES[floor_b]}"
                       + (f" ({room_b})" if floor_b == MIDDLE else ""))
    return bad


def cycles(imports: Iterable[Import]) -> list[list[str]]:
    """The import graph's strongly connected components of more than one module (Tarjan)."""
    graph: dict[str, set[str]] = {}
    for imp in imports:
        if imp.imported != "ahrs_service":
            graph.setdefault(imp.importer, set()).add(imp.imported)
            graph.setdefault(imp.imported, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = 0

    def visit(start: str) -> None:  # iterative, so deep graphs do not hit the recursion limit
        nonlocal counter
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph[child]))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found
