"""Kernels compiled in a child process (ahrs_service.kernels): a first start under systemd
extends the start timeout while it compiles, and a reload to another estimator compiles
without stalling the loop. A real sd_notify socket (a unix datagram socket bound here and
passed as NOTIFY_SOCKET), the real ``ahrs-service`` process, a cold numba cache of its own."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys

import pytest

from ahrs_service import kernels
from ahrs_service.systemd import Notifier

from tests.test_daemon import FakeSystemd, ahrs_service_command, running, write_config

pytestmark = pytest.mark.timeout(240)


def _child_running(monkeypatch, code: str) -> None:
    """Compile children run ``python -c code`` instead of ``ahrs-service compile``."""
    monkeypatch.setattr(kernels, "child_command", lambda names, nice=0: [sys.executable, "-c", code])


def test_waiting_for_a_compile_child_extends_the_timeout_and_pings_the_watchdog(tmp_path, monkeypatch):
    notify = FakeSystemd(tmp_path)
    _child_running(monkeypatch, "import time; time.sleep(0.6)")
    notifier = Notifier({"NOTIFY_SOCKET": notify.path, "WATCHDOG_USEC": "100000"})  # ping every 50 ms
    child = kernels.compile_in_child(["madgwick"], notifier, extend_s=20.0, every_s=5.0)
    notifier.close()
    assert child.ok and child.poll()
    notify.wait_for("never", 0.3)  # collect what was sent
    lines = [m for _, m in notify.messages]
    assert lines[0].startswith("STATUS=compiling the madgwick kernels")
    # one at once, then at the watchdog's pace (never slower: a loaded machine only adds waits)
    assert lines.count("EXTEND_TIMEOUT_USEC=20000000") >= 2
    assert lines.count("WATCHDOG=1") == lines.count("EXTEND_TIMEOUT_USEC=20000000")


def test_a_failing_child_is_reported_and_a_stop_ends_a_running_one(tmp_path, monkeypatch):
    _child_running(monkeypatch, "import sys; print('numba: out of memory', file=sys.stderr); sys.exit(3)")
    # valenti as not yet in this process, whatever ran before here: the child is started
    monkeypatch.setattr(kernels, "loaded", lambda name: False)
    compiler = kernels.ReloadCompiler()
    before = kernels.LoopCounters(ticks=10, missed_ticks=1, overruns=1, samples=9)
    assert compiler.needed("valenti", "madgwick", before) and compiler.child is not None
    compiler.child.wait(60.0)
    done = compiler.poll(kernels.LoopCounters(ticks=50, missed_ticks=1, overruns=1, samples=49))
    assert done is not None and not done.ok and done.error == "numba: out of memory"
    assert done.during == kernels.LoopCounters(40, 0, 0, 40)
    assert "valenti" not in compiler.compiled and compiler.child is None
    # the running estimator, or one this process has, needs no child
    assert not compiler.needed("madgwick", "madgwick", before) and compiler.child is None

    _child_running(monkeypatch, "import time; time.sleep(60)")
    stops = iter([False, True])
    child = kernels.compile_in_child(["robust"], Notifier({}), stop=lambda: next(stops))
    assert child.poll() and not child.ok  # killed: SIGTERM during a first start ends it at once


def _reload_line(output: str) -> re.Match:
    pattern = (r"reload: valenti compiled in a child process in ([\d.]+) s; the loop meanwhile ran (\d+) ticks, "
               r"missed (\d+) \((\d+) overruns\), estimated (\d+) samples; loading it from the cache held the loop (\d+) ms")
    match = re.search(pattern, output)
    assert match, output[-3000:]
    return match


# the start and the reload each wait as systemd would (FakeSystemd.wait_as_systemd): up to the
# unit's 15 min, as long as the service keeps extending the timeout while a child compiles
@pytest.mark.timeout(1900)
def test_a_cold_start_extends_the_start_timeout_and_a_reload_compiles_without_stalling_the_loop(tmp_path):
    notify = FakeSystemd(tmp_path)
    cfg = tmp_path / "config.toml"
    write_config(cfg, tmp_path / "logs", 14996)  # madgwick at 200 Hz, simulated GY-80 at rest
    cache = tmp_path / "numba-cache"  # cold: every kernel is compiled
    with running(["run", "--config", str(cfg), "--no-log"], tmp_path, notify,
                 env={"NUMBA_CACHE_DIR": str(cache)}) as proc:
        # as systemd waits: 90 s (DefaultTimeoutStartSec), extended by each EXTEND_TIMEOUT_USEC
        # while the child compiles; on a busy computer the compile takes as long as it takes
        assert notify.wait_as_systemd("READY=1", 90), "no READY, and no EXTEND_TIMEOUT_USEC kept the start alive"
        before_ready = [m for _, m in notify.messages[:-1]]
        # the start compiled in a child while telling systemd to wait
        assert before_ready[0].startswith("STATUS=compiling the madgwick kernels")
        assert sum(m.startswith("EXTEND_TIMEOUT_USEC=") for m in before_ready) >= 2
        assert any(p.suffix == ".nbi" for p in cache.rglob("*"))  # the child filled the cache

        # reload to an estimator this process has never run: compiled in a child, loop runs on
        cfg.write_text(cfg.read_text().replace('name = "madgwick"', 'name = "valenti"').replace("beta = 0.1\n", ""))
        mark = len(notify.messages)
        proc.send_signal(signal.SIGHUP)
        assert notify.wait_as_systemd("READY=1", 90), "the reload neither completed nor kept extending its timeout"
        after_hup = [m for _, m in notify.messages[mark:-1]]
        during = after_hup[after_hup.index("RELOADING=1"):]  # (pings sent before it may come first)
        assert any(m.startswith("EXTEND_TIMEOUT_USEC=") for m in during)  # systemd's reload timeout
        assert notify.wait_for("STATUS=valenti", 10)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=30) == 0
    output = proc.stdout.read()
    line = _reload_line(output)
    print(line.group(0))  # pytest -s: how long the compile took, the loop meanwhile, the cache load
    seconds, ticks, missed, overruns, samples, load_ms = (float(g) for g in line.groups())
    # the service's own counters over the compile: the loop kept its schedule (a compile on
    # the loop would have run no tick and missed every one of them in one burst) and went on
    # estimating with the old estimator
    assert ticks > 0 and samples > 0
    assert missed < ticks
    assert "reload: compiling valenti in a child process; madgwick runs meanwhile" in output


def test_compile_refuses_an_unknown_estimator_in_one_line(tmp_path):
    from ahrs_service import estimators

    proc = subprocess.run(ahrs_service_command() + ["compile", "madgwik"], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "ahrs-service compile: error: unknown estimator 'madgwik'; available: " + ", ".join(estimators.names())]


# A fresh interpreter: the service started as `ahrs-service run` starts it; the numba
# dispatchers of the package counted after start() and again after two seconds of its loop.
# A kernel first called inside the loop (compiled on a first start, loaded from the cache on
# every other) holds the loop while the part's FIFO fills: the default run's first start lost
# 21-176 samples to the attitude variance's and the simulated motion's kernels that way.
_KERNELS_AFTER_START = r"""
import json, sys
from numba.core.registry import CPUDispatcher
import ahrs_service.service as service_mod
from ahrs_service import cli

def signatures():
    out = {}
    for name, module in list(sys.modules.items()):
        if name.startswith("ahrs_service"):
            for attr, value in list(vars(module).items()):
                if isinstance(value, CPUDispatcher):
                    out[f"{value.py_func.__module__}.{value.py_func.__qualname__}"] = len(value.signatures)
    return out

run = service_mod.Service.run
def counted_run(self):
    before = signatures()
    code = run(self)
    after = signatures()
    new = sorted(k for k in after if after[k] > before.get(k, 0))
    print("KERNELS-IN-LOOP " + json.dumps({"new": new, "known": len(before)}), flush=True)
    return code
service_mod.Service.run = counted_run
sys.exit(cli.main(sys.argv[1:]))
"""


@pytest.mark.parametrize("source", [
    None,  # the embedded default: the simulated GY-80, robust
    'type = "simulated_spi"\nboard = "icm42688p"\nboard_options = { odr_hz = 1000 }\n',
])
def test_the_loop_compiles_and_loads_no_kernel_after_start(tmp_path, source):
    args = ["run", "--duration", "2", "--log-dir", str(tmp_path / "logs")]
    if source is not None:
        config = tmp_path / "ahrs.toml"
        config.write_text(f'[source]\n{source}\n[estimator]\nname = "madgwick"\n'
                          '[mavlink]\nendpoints = ["udpout:127.0.0.1:14551"]\n')
        args += ["-c", str(config)]
    done = subprocess.run([sys.executable, "-c", _KERNELS_AFTER_START, *args],
                          capture_output=True, text=True, timeout=200)
    assert done.returncode == 0, done.stderr[-2000:]
    line = re.search(r"^KERNELS-IN-LOOP (.*)$", done.stdout, re.M)
    assert line is not None, done.stdout[-2000:] + done.stderr[-2000:]
    found = json.loads(line.group(1))
    assert found["known"] >= 10  # the counting saw the pipeline's kernels
    assert found["new"] == []


@pytest.mark.timeout(1200)
def test_a_start_that_compiles_says_so_first_and_a_cached_one_does_not(tmp_path):
    """From a terminal a cold start used to compile for minutes before its first line; now a
    line says what is happening before the compile, and a start on a filled cache has none."""
    config = tmp_path / "ahrs.toml"
    config.write_text('[estimator]\nname = "madgwick"\n[mavlink]\nendpoints = ["udpout:127.0.0.1:14551"]\n')
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}  # cold
    args = ahrs_service_command() + ["run", "-c", str(config), "--duration", "1", "--no-log"]
    lines = []
    for _ in range(2):
        done = subprocess.run(args, capture_output=True, text=True, timeout=900, env=env)
        assert done.returncode == 0, done.stderr[-2000:]
        lines.append(done.stderr.splitlines())
    cold, warm = lines
    says = [i for i, x in enumerate(cold) if "compiling the madgwick kernels" in x]
    compiled = [i for i, x in enumerate(cold) if "compiled the madgwick kernels in" in x]
    assert len(says) == 1 and (not compiled or says[0] < compiled[0]), cold[-10:]
    assert not any("compiling the madgwick kernels" in x for x in warm), warm[-10:]
