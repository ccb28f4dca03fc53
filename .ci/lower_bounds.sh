#!/usr/bin/env bash
# The tests that exercise mcap, pymavlink and tomlkit, on the lower bounds pyproject.toml
# declares (.ci/lower-bounds.txt): those versions are installed into .ci-lower-bounds/ and put
# in front of the test environment's own with PYTHONPATH (subprocesses inherit it).
set -euo pipefail
cd "$(dirname "$0")/.."
rm -rf .ci-lower-bounds
.venv/bin/pip install -q --no-deps --target .ci-lower-bounds -r .ci/lower-bounds.txt
PYTHONPATH="$PWD/.ci-lower-bounds" .venv/bin/python - <<'PY'
import importlib.metadata as m
import mcap, pymavlink, tomlkit  # noqa: F401
print("lower bounds:", ", ".join(f"{n} {m.version(n)}" for n in ("mcap", "pymavlink", "tomlkit")))
PY
PYTHONPATH="$PWD/.ci-lower-bounds" .venv/bin/python -m pytest -q -p no:cacheprovider \
    tests/test_logs_writer.py tests/test_logs_encoding.py tests/test_logs_fixtures.py tests/test_logs_recover.py \
    tests/test_logs_replay.py tests/test_mavlink.py tests/test_config_file.py
