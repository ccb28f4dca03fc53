"""DroneCAN: the message codec (:mod:`.messages`), the IMU source that reads a DroneCAN node
(:mod:`.imu_source`) and a simulated IMU node for tests and demos (:mod:`.sim_node`).

See docs/drivers-can.md.
"""

from ahrs_service import _moved


def __getattr__(name: str):  # the codec's names, from when it was this module, for one release
    return _moved.moved_name(__name__, name)
