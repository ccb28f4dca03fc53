"""Import paths of modules that moved to another floor (docs/design.md, "Floors").

The old paths keep working for one release: importing one gives the module at its new path
behind a :class:`DeprecationWarning` that names it. Nothing here imports the project: the
table is text, and a moved module is imported only when its old name is asked for.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import types
import warnings

#: old module path → new module path(s); an old package's submodules follow it. Where one old
#: module was split (a part and its simulated twin), its names are looked up in each new
#: module in turn.
MOVED: dict[str, str | tuple[str, ...]] = {
    "ahrs_service.quaternion": "ahrs_service.core.quaternion",
    "ahrs_service.sample_clock": "ahrs_service.core.sample_clock",
    "ahrs_service.paths": "ahrs_service.core.paths",
    "ahrs_service.vibration": "ahrs_service.core.vibration",
    "ahrs_service.estimators.layout": "ahrs_service.core.layout",
    "ahrs_service.drivers.base": "ahrs_service.core.samples",
    "ahrs_service.drivers.calibration": "ahrs_service.core.calibration",
    "ahrs_service.drivers.recorded": "ahrs_service.recorded",
    "ahrs_service.drivers.mavlink_imu": "ahrs_service.protocols.mavlink.imu_source",
    "ahrs_service.drivers.can": "ahrs_service.protocols.dronecan",
    "ahrs_service.drivers.can.source": "ahrs_service.protocols.dronecan.imu_source",
    "ahrs_service.drivers.can.sim_node": "ahrs_service.protocols.dronecan.sim_node",
    "ahrs_service.drivers.sim_bus": "ahrs_service.drivers.sim.bus",
    "ahrs_service.drivers.i2c": "ahrs_service.drivers.parts",
    "ahrs_service.drivers.i2c.bus": ("ahrs_service.drivers.buses.i2c", "ahrs_service.drivers.sim.bus"),
    "ahrs_service.drivers.i2c.device": ("ahrs_service.drivers.device", "ahrs_service.drivers.sim.register_device"),
    "ahrs_service.drivers.i2c.boards": ("ahrs_service.drivers.boards.i2c", "ahrs_service.drivers.boards"),
    "ahrs_service.drivers.imu": "ahrs_service.drivers.parts",
    "ahrs_service.drivers.imu.boards": "ahrs_service.drivers.boards.transport",
    "ahrs_service.drivers.spi": "ahrs_service.drivers.buses",
    "ahrs_service.drivers.spi.bus": ("ahrs_service.drivers.buses.spi", "ahrs_service.drivers.sim.bus"),
    "ahrs_service.drivers.gpio": "ahrs_service.drivers.buses",
    "ahrs_service.drivers.gpio.drdy": ("ahrs_service.drivers.buses.drdy", "ahrs_service.drivers.sim.drdy"),
    "ahrs_service.logs.command": "ahrs_service.log_commands",
    "ahrs_service.logs.replay": "ahrs_service.replay",
    "ahrs_service.logs.fleet": "ahrs_service.fleet",
    "ahrs_service.logs.broad_import": "ahrs_service.evaluation.broad_import",
}
# each register part's driver moved to drivers/parts/, its simulated twin to drivers/sim/
for _part, _bus in (("adxl345", "i2c"), ("ak8963", "i2c"), ("hmc5883l", "i2c"), ("l3g4200d", "i2c"),
                    ("l3gd20", "i2c"), ("lsm303dlhc", "i2c"), ("mpu9250", "i2c"), ("st_fifo", "i2c"),
                    ("ak09916", "imu"), ("bmi088", "imu"), ("icm20948", "imu"), ("icm42688p", "imu")):
    MOVED[f"ahrs_service.drivers.{_bus}.{_part}"] = (f"ahrs_service.drivers.parts.{_part}",
                                                    f"ahrs_service.drivers.sim.{_part}")


#: names that left a module that still exists: module → {old name: "new.module:new_name"};
#: the key ``"*"`` forwards every other name the new module has (a module that became a
#: package of the same name). Such a module ends with
#: ``def __getattr__(name): return _moved.moved_name(__name__, name)``.
MOVED_NAMES: dict[str, dict[str, str]] = {
    "ahrs_service.config": {
        "Checker": "ahrs_service.core.settings:Checker",
        "IDENTITIES": "ahrs_service.protocols.mavlink.settings:IDENTITIES",
        "ODOMETRY": "ahrs_service.protocols.mavlink.settings:ODOMETRY",
        "ODOMETRY_RULES": "ahrs_service.protocols.mavlink.settings:ODOMETRY_RULE_NAMES",
        "MIN_STREAM_HZ": "ahrs_service.protocols.mavlink.component:MIN_RATE_HZ",
    },
    "ahrs_service.mavlink_bridge": {
        "CONFIG_RANGE_FACTOR": "ahrs_service.estimators.settings:CONFIG_RANGE_FACTOR",
    },
    "ahrs_service.drivers.transport": {
        "TransportDevice": "ahrs_service.drivers.device:TransportDevice",
        "TransportError": "ahrs_service.drivers.device:TransportError",
        "PartIdentityError": "ahrs_service.drivers.device:PartIdentityError",
    },
    "ahrs_service.protocols.dronecan": {  # the codec module became the DroneCAN package
        "*": "ahrs_service.protocols.dronecan.messages",
    },
    "ahrs_service.drivers.i2c.boards": {  # a moved module whose name means something narrower now
        "board_names": "ahrs_service.drivers.boards:i2c_board_names",
    },
    "ahrs_service.drivers.fifo": {
        "SimulatedFifo": "ahrs_service.drivers.sim.fifo:SimulatedFifo",
        "SimulatedFifoDevice": "ahrs_service.drivers.sim.fifo:SimulatedFifoDevice",
        "SimulatedFrameFifo": "ahrs_service.drivers.sim.fifo:SimulatedFrameFifo",
    },
}


def moved_name(module: str, name: str):
    """The object ``module.name`` became (a DeprecationWarning says where); AttributeError if none."""
    table = MOVED_NAMES.get(module, {})
    new = table.get(name)
    if new is None and "*" in table and not name.startswith("_"):
        everything = table["*"]
        if name != everything.rpartition(".")[2] and hasattr(importlib.import_module(everything), name):
            new = f"{everything}:{name}"
    if new is None:
        raise AttributeError(f"module {module!r} has no attribute {name!r}")
    new_module, _, new_name = new.partition(":")
    warnings.warn(f"{module}.{name} moved to {new_module}.{new_name}; the old path will be removed in the next release",
                  DeprecationWarning, stacklevel=3)
    return getattr(importlib.import_module(new_module), new_name)


def _targets(old: str) -> tuple[str, ...] | None:
    if old in MOVED:
        found = MOVED[old]
        return (found,) if isinstance(found, str) else found
    for before, after in MOVED.items():
        if isinstance(after, str) and old.startswith(before + "."):
            return (after + old[len(before):],)
    return None


def new_path(old: str) -> str | None:
    """The (first) module path that replaced ``old``, or ``None`` when ``old`` did not move."""
    found = _targets(old)
    return found[0] if found else None


class _Forward(types.ModuleType):
    """Stands at an old path and hands out the attributes of the module at the new one."""

    def __init__(self, name: str, targets: tuple[str, ...]) -> None:
        super().__init__(name)
        self.__path__: list[str] = []  # so that an old package's submodules import too
        self._targets = targets

    def __getattr__(self, attribute: str):
        if attribute.startswith("__"):
            raise AttributeError(attribute)
        if attribute in MOVED_NAMES.get(self.__name__, {}):
            return moved_name(self.__name__, attribute)
        for target in self._targets:
            module = importlib.import_module(target)
            if hasattr(module, attribute):
                return getattr(module, attribute)
        raise AttributeError(f"module {self.__name__!r} (moved to {', '.join(self._targets)}) has no attribute {attribute!r}")

    def __dir__(self) -> list[str]:
        return sorted({name for target in self._targets for name in dir(importlib.import_module(target))})


class _MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Last on ``sys.meta_path``: consulted only for names no real module answers."""

    def find_spec(self, fullname, path=None, target=None):
        if _targets(fullname) is None:
            return None
        return importlib.util.spec_from_loader(fullname, self, is_package=True)

    def create_module(self, spec):
        targets = _targets(spec.name)
        warnings.warn(f"{spec.name} moved to {' and '.join(targets)}; the old path will be removed in the next release",
                      DeprecationWarning, stacklevel=2)
        for target in targets:
            importlib.import_module(target)  # an error names the new path now, not at first use
        return _Forward(spec.name, targets)

    def exec_module(self, module) -> None:
        pass


def install() -> None:
    """Put the finder last on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
