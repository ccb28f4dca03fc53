"""How long a switch to another estimator holds the loop: compiling it there against loading
it from numba's cache after a child process compiled it (what ``Service.reload`` does).

    python benchmarks/kernel_load.py [--estimators madgwick,valenti,robust] [--markdown]

For each estimator, in a cold cache of its own (``NUMBA_CACHE_DIR`` in a temporary folder):
a fresh process first warms up the kernels every estimator shares (calibration, quaternion
output, through ``complementary_reduced``), then times ``kernels.warm_up(name)`` — the
compile a reload would run on the loop. A second fresh process, on the cache the first one
filled, does the same: that is the load from the cache, the only part of a reload's compile
that still blocks the loop. Both in the same run, one after the other, so the ratio holds on
a loaded machine even where the seconds do not.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile

_PROBE = """
import json, sys
from ahrs_service import kernels
kernels.warm_up("complementary_reduced")  # the kernels every estimator shares
print(json.dumps({"seconds": kernels.warm_up(sys.argv[1])}))
"""


def timed_warm_up(name: str, cache_dir: str) -> float:
    """Seconds ``kernels.warm_up(name)`` takes in a fresh process on ``cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", _PROBE, name], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["seconds"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimators", default="madgwick,valenti,robust")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    rows = []
    for name in args.estimators.split(","):
        with tempfile.TemporaryDirectory(prefix="ahrs-kernel-cache-") as cache:
            compile_s = timed_warm_up(name, cache)  # cold: compiles
            load_s = timed_warm_up(name, cache)  # warm: loads what the first one wrote
        rows.append((name, compile_s, load_s))
    print(f"# {platform.node()} {platform.machine()} python {platform.python_version()}")
    head = ("estimator", "compile on the loop s", "load from cache ms", "compile / load")
    if args.markdown:
        print("| " + " | ".join(head) + " |")
        print("|---|---:|---:|---:|")
        for name, c, load in rows:
            print(f"| `{name}` | {c:.1f} | {load * 1e3:.0f} | {c / load:.0f} |")
    else:
        print(f"{head[0]:<24}{head[1]:>24}{head[2]:>22}{head[3]:>16}")
        for name, c, load in rows:
            print(f"{name:<24}{c:>24.1f}{load * 1e3:>22.0f}{c / load:>16.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
