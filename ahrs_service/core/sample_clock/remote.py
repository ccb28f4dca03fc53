"""Sample times from a remote node's own timestamps (DroneCAN RawIMU µs), mapped onto the host.

The node stamps each sample on its clock; the host receives it a transport latency later.
What is left of the package's line model is the offset between the two clocks (the node's
timestamps already carry the index and the period). Used by
:class:`ahrs_service.protocols.dronecan.imu_source.DroneCanImuSource`.
"""

from __future__ import annotations


class SensorClockMap:
    """Maps a node's µs clock onto the host's monotonic ns clock.

    offset = host receive time − sensor time. Transport latency only ever adds to that
    difference, so the estimate follows new minima at once and rises only slowly
    (``rise_fraction`` of the excess per sample) — enough to follow crystal drift of the two
    clocks, too slow for latency jitter to show in the time steps. A jump of more than
    ``reset_s`` (node reboot, clock step) restarts the estimate.
    """

    def __init__(self, rise_fraction: float = 1e-3, reset_s: float = 1.0) -> None:
        self.rise_fraction = rise_fraction
        self.reset_ns = int(reset_s * 1e9)
        self.offset_ns: int | None = None
        self.resets = 0

    def map(self, sensor_us: int, host_ns: int) -> int:
        """Host-clock time (ns) of a sensor timestamp (µs) received at ``host_ns``."""
        self.update(sensor_us, host_ns)
        return self.to_host(sensor_us)

    def to_host(self, sensor_us: int) -> int:
        """Host-clock time (ns) of a sensor timestamp (µs) with the current offset."""
        return sensor_us * 1000 + (self.offset_ns or 0)

    def update(self, sensor_us: int, host_ns: int) -> None:
        """Feeds one observation: sensor time ``sensor_us`` (µs) received at ``host_ns`` (ns)."""
        d = host_ns - sensor_us * 1000
        off = self.offset_ns
        if off is None or abs(d - off) > self.reset_ns:
            if off is not None:
                self.resets += 1
            off = d
        elif d < off:
            off = d
        else:
            off += int((d - off) * self.rise_fraction)
        self.offset_ns = off


__all__ = ["SensorClockMap"]
