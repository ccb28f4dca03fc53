"""The floors of docs/design.md hold: no upward import, no import across the middle floor, no circle."""

from __future__ import annotations

import textwrap
from pathlib import Path

import floors
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def project_imports() -> list[floors.Import]:
    return floors.imports_of(floors.modules_of(ROOT))


def test_the_checker_sees_the_whole_project(project_imports):
    modules = floors.modules_of(ROOT)
    assert {"ahrs_service.core.quaternion", "ahrs_service.estimators.madgwick", "ahrs_service.drivers.sim.motion",
            "ahrs_service.protocols.mavlink.odometry", "ahrs_service.logs.writer", "ahrs_service.service"} <= set(modules)
    assert len(project_imports) > 300  # module-level and function-level imports alike
    assert {imp.where for imp in project_imports} >= {"module", "function"}


def test_no_module_imports_a_floor_above_its_own_or_across_the_middle_floor(project_imports):
    assert floors.violations(project_imports) == []


def test_the_import_graph_has_no_circle(project_imports):
    assert floors.cycles(project_imports) == []


def _tree(tmp_path: Path, files: dict[str, str]) -> list[floors.Import]:
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(textwrap.dedent(text))
    return floors.imports_of(floors.modules_of(tmp_path))


def test_a_deliberate_upward_import_inside_a_function_is_caught(tmp_path):
    imports = _tree(tmp_path, {
        "ahrs_service/__init__.py": "",
        "ahrs_service/core/__init__.py": "",
        "ahrs_service/core/quaternion.py": "def f():\n    from ahrs_service.service import Service\n",
        "ahrs_service/service.py": "from ahrs_service.core import quaternion\n",
    })
    found = floors.violations(imports)
    assert len(found) == 1
    assert found[0].startswith("ahrs_service.core.quaternion:2 (function) imports ahrs_service.service")


def test_a_deliberate_import_across_the_middle_floor_is_caught(tmp_path):
    imports = _tree(tmp_path, {
        "ahrs_service/__init__.py": "",
        "drivers/__init__.py": "",
        "drivers/part.py": "from ahrs_service.logs import writer\n",
        "logs/__init__.py": "",
        "logs/writer.py": "from ..drivers import part  # relative, still across\n",
    })
    found = floors.violations(imports)
    assert [line.split(" ")[0] for line in found] == ["ahrs_service.drivers.part:1", "ahrs_service.logs.writer:1"]


def test_a_deliberate_circle_is_caught(tmp_path):
    imports = _tree(tmp_path, {
        "ahrs_service/__init__.py": "",
        "ahrs_service/a.py": "from ahrs_service import b\n",
        "ahrs_service/b.py": "if TYPE_CHECKING:\n    from ahrs_service.c import x\n",
        "ahrs_service/c.py": "def f():\n    import ahrs_service.a\n",
    })
    assert floors.cycles(imports) == [["ahrs_service.a", "ahrs_service.b", "ahrs_service.c"]]


def test_every_package_folder_is_listed_for_installation():
    """A non-editable install (the systemd recipe's) ships only the packages pyproject.toml lists,
    and each needs its ``__init__.py``."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert setuptools["package-dir"] == {package: folder for folder, package in floors.PACKAGE_DIRS.items()}
    source_folders = {}
    for folder, package in floors.PACKAGE_DIRS.items():
        for module in (ROOT / folder).rglob("*.py"):
            parts = module.parent.relative_to(ROOT / folder).parts
            if "__pycache__" not in parts:
                source_folders[".".join([package, *parts])] = module.parent
    assert sorted(source_folders) == sorted(setuptools["packages"])
    assert [name for name, path in source_folders.items() if not (path / "__init__.py").exists()] == []
