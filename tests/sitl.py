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


def wait_until(condition, seconds: float, step: float = 0.05) -> bool:
    """Polls ``condition()`` until true or ``seconds`` passed (bounded)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step)
    return bool(condition())
