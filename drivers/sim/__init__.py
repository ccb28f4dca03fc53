"""The motion and sensor simulator: trajectories, sensor error models, a simulated IMU board.

* :mod:`.motion` — :class:`Trajectory` and the built-in motions (``profile(name)``);
* :mod:`.sensor_model` — :class:`SensorErrorModel` and the per-part presets ``PART_MODELS``;
* :mod:`.imu` — :class:`SimulatedImu`, whose ``physics(t)`` the simulated I2C and CAN devices read;
* :mod:`.clock` — ``MonotonicClock`` (real time) and ``ManualClock`` (tests);
* :mod:`.source` — :class:`SimulatedSource`, the simulator as an ``ImuSource`` without a bus.

See docs/simulator.md.
"""

from ahrs_service.drivers.sim.clock import ManualClock, MonotonicClock
from ahrs_service.drivers.sim.imu import SimulatedImu
from ahrs_service.drivers.sim.motion import MotionState, Trajectory, profile
from ahrs_service.drivers.sim.sensor_model import PART_MODELS, SensorErrorModel

__all__ = [
    "ManualClock",
    "MonotonicClock",
    "MotionState",
    "PART_MODELS",
    "SensorErrorModel",
    "SimulatedImu",
    "Trajectory",
    "profile",
]
