"""A Dask cluster started by hand, as docs/fleet.md tells a user: a ``dask scheduler`` and
``dask worker`` processes (one thread each) on 127.0.0.1, for the tests and benchmarks that run
through ``--scheduler``.

    with hand_started_cluster(workers=2) as address:
        cli_main([..., "--scheduler", address])

``config``: Dask settings for the scheduler and workers (e.g.
``execution.LOCAL_CLUSTER_CONFIG``), written to a configuration file in a folder named by
``DASK_CONFIG``, as docs/fleet.md shows for a cluster of one's own; ``pids`` receives the
processes' ids (a benchmark watching their memory).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Iterator


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def dask_cli() -> str:
    """The ``dask`` command of this interpreter's environment."""
    return str(Path(sys.executable).with_name("dask"))


def stop_processes(procs: list[subprocess.Popen]) -> None:
    """Ends hand-started ``dask`` processes: SIGTERM (workers before their scheduler), then
    SIGKILL whatever has not exited 30 s on."""
    for p in reversed(procs):
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()


def _nested(flat: dict[str, Any]) -> dict[str, Any]:
    """``{"a.b.c": v}`` as ``{"a": {"b": {"c": v}}}`` (a Dask YAML file's shape; JSON is YAML)."""
    out: dict[str, Any] = {}
    for dotted, value in flat.items():
        *parents, leaf = dotted.split(".")
        node = out
        for name in parents:
            node = node.setdefault(name, {})
        node[leaf] = value
    return out


@contextlib.contextmanager
def hand_started_cluster(workers: int = 2, *, config: dict[str, Any] | None = None,
                         pids: list[int] | None = None, timeout_s: float = 120.0) -> Iterator[str]:
    """A scheduler and ``workers`` single-threaded workers; yields the scheduler's address once
    every worker has joined, and stops them all on the way out."""
    from distributed import Client

    port = free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, DASK_DISTRIBUTED__WORKER__DAEMON="False")
    with tempfile.TemporaryDirectory(prefix="dask-config-") as folder:
        if config:
            Path(folder, "ahrs.yaml").write_text(json.dumps(_nested(config)))
            env["DASK_CONFIG"] = folder
        procs = [subprocess.Popen(
            # the HTTP server (health, metrics) stays up without a dashboard: loopback, any port
            [dask_cli(), "scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard",
             "--dashboard-address", "127.0.0.1:0"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
        )]
        try:
            for _ in range(workers):
                procs.append(subprocess.Popen(
                    [dask_cli(), "worker", address, "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                     "--no-dashboard", "--dashboard-address", "127.0.0.1:0", "--death-timeout", "60"],
                    stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                ))
            if pids is not None:
                pids.extend(p.pid for p in procs)
            with Client(address, timeout=f"{timeout_s}s", set_as_default=False) as client:
                client.wait_for_workers(workers, timeout=timeout_s)
            yield address
        finally:
            stop_processes(procs)
