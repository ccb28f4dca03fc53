"""`pip install ahrs-service` (no extras) must be enough for `ahrs-service run`, and a command
that needs an extra must say which one in one line.

The optional packages are installed in the test environment, so a subprocess blocks their
import (a meta-path finder that raises ModuleNotFoundError for them, as if they were absent)
and then runs the real command line.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

from ahrs_service.cli import OPTIONAL_MODULES
from ahrs_service.logs.reader import read_log

# everything an extra brings (and the test tools), none of which the service may import
BLOCKED = sorted(set(OPTIONAL_MODULES) | {"pandas", "statsmodels", "pytest", "msgpack"})

_RUNNER = textwrap.dedent(
    """
    import sys

    BLOCKED = set(sys.argv[1].split(","))

    class Block:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, Block())
    from ahrs_service.cli import main

    code = main(sys.argv[2:])
    leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
    print("LEAKED", ",".join(leaked))
    sys.exit(code)
    """
)


def _cli(*args: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", _RUNNER, ",".join(BLOCKED), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_default_run_needs_no_extra(tmp_path):
    # the embedded default: simulated GY-80, MAVLink udpout to 127.0.0.1:14550, robust estimator
    proc = _cli("run", "--duration", "1.5", "--log-dir", str(tmp_path))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "LEAKED \n" in proc.stdout
    logs = sorted(tmp_path.glob("*.mcap"))
    assert len(logs) == 1
    log = read_log(logs[0])
    assert log.damage is None and len(log) > 0 and log.counts["/attitude"] == len(log)


def test_a_command_without_its_extra_names_the_extra_in_one_line(tmp_path):
    proc = _cli("evaluate", "--estimators", "madgwick", "--out", str(tmp_path / "out"))
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert "pip install 'ahrs-service[" in lines[0] and lines[0].startswith("ahrs-service evaluate: needs")


def test_the_lower_bounds_ci_tests_are_the_ones_pyproject_declares():
    """.ci/lower_bounds.sh runs the MCAP, MAVLink and config tests on .ci/lower-bounds.txt:
    each pin there must be the lower bound of that dependency in pyproject.toml."""
    import re
    from pathlib import Path

    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    from packaging.version import Version

    root = Path(__file__).resolve().parents[1]
    deps = tomllib.loads((root / "pyproject.toml").read_text())["project"]["dependencies"]
    lower = {}
    for spec in deps:
        m = re.match(r"([A-Za-z0-9_.-]+)\s*>=\s*([0-9.]+)", spec)
        if m:
            lower[m.group(1).lower()] = Version(m.group(2))
    pins = [line.split("==") for line in (root / ".ci" / "lower-bounds.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    assert {name for name, _ in pins} == {"mcap", "pymavlink", "tomlkit"}
    for name, version in pins:
        assert Version(version) == lower[name.lower()], name
