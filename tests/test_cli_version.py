"""``ahrs-service --version`` prints the installed package's version and exits 0."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent


def test_version_prints_the_package_version():
    proc = subprocess.run([sys.executable, "-m", "ahrs_service.cli", "--version"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    assert version("ahrs-service") == declared  # the editable install is this checkout
    assert proc.stdout == f"ahrs-service {declared}\n"
    assert proc.stderr == ""


def test_version_is_listed_in_help():
    proc = subprocess.run([sys.executable, "-m", "ahrs_service.cli", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "--version" in proc.stdout
