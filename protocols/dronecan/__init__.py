"""DroneCAN: the message codec (:mod:`.messages`), the IMU source that reads a DroneCAN node
(:mod:`.imu_source`) and a simulated IMU node for tests and demos (:mod:`.sim_node`).

See docs/drivers-can.md.
"""


def __getattr__(name: str):
    # the codec was the module ahrs_service.protocols.dronecan before it became this package
    import importlib
    import warnings

    if name.startswith("_") or name in ("messages", "imu_source", "sim_node"):
        raise AttributeError(name)
    messages = importlib.import_module(f"{__name__}.messages")
    if not hasattr(messages, name):
        raise AttributeError(name)
    warnings.warn(f"{__name__}.{name} moved to {__name__}.messages.{name}; "
                  "the old path will be removed in the next release", DeprecationWarning, stacklevel=2)
    return getattr(messages, name)
