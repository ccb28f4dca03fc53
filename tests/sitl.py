"""ArduPilot SITL for the tests: a real autopilot (ArduCopter/ArduPlane with EKF3, its MAVLink
stack and a physics model) started as a separate program, on loopback only.

The binaries are not part of the project: they are looked for in ``$AHRS_SITL_DIR``, else
``../shared/sitl`` beside the checkout (ArduPilot, GPL-3.0, github.com/ArduPilot/ardupilot;
the folder's README names the commit). A test that needs one skips, with the reason, where it
is absent. Every serial port is a ``udpclient`` to a port on 127.0.0.1 (SITL sends first, opens
no TCP listener and does not wait for a client); the process is ended by its PID.
"""

from __future__ import annotations

import os
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

#: where ArduPilot's own SITL home is (its autotest's CMAC field), lat, lon, alt m, heading °
HOME = "-35.363261,149.165230,584,353"


def sitl_dir() -> Path:
    given = os.environ.get("AHRS_SITL_DIR")
    return Path(given) if given else Path(__file__).resolve().parents[1].parent / "shared" / "sitl"


def binary(vehicle: str) -> Path:
    """The SITL program of ``vehicle`` ("arducopter" or "arduplane"), or skip the test."""
    path = sitl_dir() / vehicle
    if not (path.is_file() and os.access(path, os.X_OK)):
        pytest.skip(f"ArduPilot SITL {vehicle} not found at {path} (set AHRS_SITL_DIR)")
    return path


def _udp_port_free(port: int) -> bool:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("0.0.0.0", port))
    except OSError:
        return False
    finally:
        s.close()
    return True


def free_instance() -> int:
    """An instance number ``-I`` whose simulator input port (UDP 5501 + 10·I) is free."""
    start = os.getpid() % 40
    for k in range(40):
        instance = 10 + (start + k) % 40
        if _udp_port_free(5501 + 10 * instance):
            return instance
    pytest.skip("no free SITL instance port (UDP 5601-5991)")


class Sitl:
    """One running SITL: ``serial`` maps a serial port number to a UDP port on 127.0.0.1 it
    sends to; ``params`` are written to a defaults file after the vehicle's own."""

    def __init__(self, vehicle: str, workdir: Path, serial: dict[int, int], params: dict[str, float] | None = None,
                 model: str = "quad") -> None:
        exe = binary(vehicle)
        defaults = [sitl_dir() / "params" / ("copter.parm" if vehicle == "arducopter" else "plane.parm")]
        if params:
            extra = workdir / "test.parm"
            extra.write_text("".join(f"{name} {value}\n" for name, value in params.items()))
            defaults.append(extra)
        self.instance = free_instance()
        cmd = [str(exe), "--model", model, "--speedup", "1", f"-I{self.instance}", "-w",
               "--defaults", ",".join(str(p) for p in defaults), "--home", HOME]
        for n, port in serial.items():
            cmd += [f"--serial{n}", f"udpclient:127.0.0.1:{port}"]
        self.output = workdir / "sitl.out"
        self._out = open(self.output, "wb")
        self.process = subprocess.Popen(cmd, cwd=workdir, stdin=subprocess.DEVNULL, stdout=self._out,
                                        stderr=subprocess.STDOUT)

    def alive(self) -> bool:
        return self.process.poll() is None

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self._out.close()

    def __enter__(self) -> "Sitl":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def service_beside(service_port: int, gcs_port: int, log_dir: Path, *, imu: str = "highres", imu_hz: float = 200.0,
                   estimator: str | None = "ekf", odometry: dict | None = None, **sections: dict):
    """The service's validated configuration beside SITL: the autopilot's IMU stream taken on
    ``udpin:127.0.0.1:service_port`` (SITL's serial port is a ``udpclient`` to it), ground links
    to ``gcs_port``, the log in ``log_dir``; ``odometry`` the ``[mavlink.odometry]`` table (None:
    off), ``estimator`` None for the default; ``sections`` are added whole."""
    from ahrs_service import config as config_mod

    data: dict = {
        "source": {"type": "mavlink", "mavlink_connection": f"udpin:127.0.0.1:{service_port}",
                   "mavlink_imu": imu, "mavlink_imu_hz": imu_hz},
        "mavlink": {"endpoints": [f"udpout:127.0.0.1:{gcs_port}"]},
        "log": {"directory": str(log_dir)},
    }
    if estimator is not None:
        data["estimator"] = {"name": estimator}
    if odometry is not None:
        data["mavlink"]["odometry"] = odometry
    data.update(sections)
    return config_mod.validate(data)


class GroundStation:
    """A pymavlink ground station on a SITL serial port (``udpin`` on 127.0.0.1:``port``): says
    HEARTBEAT once a second (ArduPilot sends STATUSTEXT only on links it has heard from), asks
    for each of ``streams`` (message name → Hz) every 2 s, and keeps what arrives of them as
    (host monotonic receive time s, message) in ``received[name]``, and every STATUSTEXT's text
    in ``texts``. Runs on a thread until :meth:`close`."""

    def __init__(self, streams: dict[str, float] | None = None) -> None:
        from pymavlink import mavutil

        from tests.test_autopilot import free_udp_port

        self.port = free_udp_port()
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{self.port}", source_system=255, source_component=190)
        self.streams = dict(streams or {})
        self.received: dict[str, list] = {name: [] for name in self.streams}
        self.texts: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        from pymavlink import mavutil

        mav = mavutil.mavlink
        asked = said = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if self.conn.clients and now - said > 1.0:
                self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                said = now
            if self.conn.target_system and now - asked > 2.0:
                for name, hz in self.streams.items():
                    self.conn.mav.command_long_send(1, 1, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                    getattr(mav, f"MAVLINK_MSG_ID_{name}"), int(1e6 / hz), 0, 0, 0, 0, 0)
                asked = now
            m = self.conn.recv_match(blocking=True, timeout=0.1)
            if m is None:
                continue
            kind = m.get_type()
            if kind in self.received:
                self.received[kind].append((time.monotonic(), m))
            elif kind == "STATUSTEXT":
                self.texts.append(str(m.text))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        self.conn.close()


def wait_until(condition, seconds: float, step: float = 0.05) -> bool:
    """Polls ``condition()`` until true or ``seconds`` passed (bounded)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step)
    return bool(condition())
