"""Every public name the project's modules had before the floors (docs/design.md) still imports
from its old module path: from the same module where it stayed, behind a DeprecationWarning
that names the new place where it moved (``ahrs_service/_moved.py``).

``fixtures/public_names_before_floors.json`` lists, per module of the tree before the move,
the names it defined at module level (classes, functions, constants; not underscored ones).
"""

from __future__ import annotations

import importlib
import json
import sys
import warnings
from pathlib import Path

import pytest

from ahrs_service import _moved

BEFORE = json.loads((Path(__file__).parent / "fixtures" / "public_names_before_floors.json").read_text())


def _fresh_import(module: str):
    for loaded in [m for m in sys.modules if m == module or m.startswith(module + ".")]:
        if _moved._targets(loaded) is not None:  # an old path: forget its forwarder, so it warns again
            del sys.modules[loaded]
    return importlib.import_module(module)


@pytest.mark.parametrize("module", sorted(BEFORE))
def test_every_public_name_still_imports_from_its_old_module(module):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        old = _fresh_import(module)
        missing = [name for name in BEFORE[module] if not hasattr(old, name)]
    assert missing == []
    moved = _moved._targets(module) is not None
    deprecations = [str(w.message) for w in caught if issubclass(w.category, DeprecationWarning)]
    if moved:
        assert any(w.startswith(f"{module} moved to ") for w in deprecations), deprecations
    else:
        moved_names = set(_moved.MOVED_NAMES.get(module, {}))
        assert all(any(f"{module}.{name} moved" in w for w in deprecations) for name in moved_names & set(BEFORE[module]))


def test_a_moved_module_gives_the_same_objects_as_its_new_path():
    with pytest.warns(DeprecationWarning, match="ahrs_service.quaternion moved to ahrs_service.core.quaternion"):
        old = _fresh_import("ahrs_service.quaternion")
    from ahrs_service.core import quaternion

    assert old.quat_mul is quaternion.quat_mul


def test_a_split_module_finds_each_name_where_it_went():
    with pytest.warns(DeprecationWarning, match="parts.icm42688p and ahrs_service.drivers.sim.icm42688p"):
        old = _fresh_import("ahrs_service.drivers.imu.icm42688p")
    from ahrs_service.drivers.parts.icm42688p import ICM42688P
    from ahrs_service.drivers.sim.icm42688p import SimulatedICM42688P

    assert (old.ICM42688P, old.SimulatedICM42688P) == (ICM42688P, SimulatedICM42688P)


def test_a_name_that_never_existed_is_still_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        getattr(importlib.import_module("ahrs_service.config"), "not_a_name")
    with pytest.raises(ImportError):
        importlib.import_module("ahrs_service.drivers.not_a_module")
