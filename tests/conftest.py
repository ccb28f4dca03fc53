"""Shared fixtures: the development recordings, small trajectory helpers, a ground station."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BROAD_DIR = Path(os.environ.get("AHRS_BROAD_DIR", REPO.parent / "shared" / "data" / "broad"))


@pytest.fixture(scope="session")
def broad_dir() -> Path:
    """Folder of the BROAD development recordings; skips the test when it is absent."""
    if not BROAD_DIR.is_dir() or not any(BROAD_DIR.glob("*.hdf5")):
        pytest.skip(f"BROAD recordings not found at {BROAD_DIR} (set AHRS_BROAD_DIR)")
    return BROAD_DIR


@pytest.fixture
def gcs():
    """A pymavlink ground station on a free loopback port, as (connection, port)."""
    from tests.test_service import make_gcs

    conn, port = make_gcs()
    yield conn, port
    conn.close()
