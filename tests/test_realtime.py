"""Real-time scheduling of the estimation loop (``[service]``, ahrs_service.realtime): the
loop's own thread, and no other, runs SCHED_FIFO; memory locked; a process that may not
raise its priority or lock its memory says so in one line, names how to allow it, and runs on.

The service runs for real (the embedded default's simulated GY-80); the kernel's answers are
read back with ``sched_getscheduler``/``sched_getaffinity`` per thread and /proc's VmLck. A
process without the privilege is made with ``setpriv`` dropping CAP_SYS_NICE and CAP_IPC_LOCK
(as root), or is this very process (as another user without an rtprio limit).
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from ahrs_service import config as config_mod
from ahrs_service.core.settings import ConfigError

from tests.test_daemon import ahrs_service_command
from tests.test_demo_accuracy import _log_events

pytestmark = pytest.mark.timeout(300)


def _can_raise_priority() -> bool:
    """Whether a thread of this process may take SCHED_FIFO (tried in a throw-away thread)."""
    result: list[bool] = []

    def probe() -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(1))
            result.append(True)
        except OSError:
            result.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return result[0]


@pytest.mark.parametrize("key, value, expected", [
    ("realtime_priority", 100, "service.realtime_priority: 100 is out of range"),
    ("realtime_priority", 1.5, "service.realtime_priority: 1.5 is not an integer"),
    ("realtime_policy", "batch", "service.realtime_policy: 'batch' is not one of fifo, rr"),
    ("cpu_affinity", ["0"], "service.cpu_affinity: expected a list of CPU numbers"),
    ("lock_memory", "yes", "service.lock_memory: expected true or false"),
])
def test_the_service_section_refuses_what_cannot_be_in_one_line(key, value, expected):
    with pytest.raises(ConfigError) as err:
        config_mod.validate({"service": {key: value}})
    assert str(err.value).startswith(expected) and "\n" not in str(err.value)


def test_real_time_scheduling_is_off_by_default():
    section = config_mod.validate({}).service
    assert section == {"realtime_priority": 0, "realtime_policy": "fifo", "lock_memory": False, "cpu_affinity": []}


def _policy(tid: int) -> int | None:
    try:
        return os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK
    except OSError:  # the thread ended meanwhile
        return None


@pytest.mark.skipif(not _can_raise_priority(), reason="this process may not use SCHED_FIFO (no CAP_SYS_NICE, RLIMIT_RTPRIO 0)")
def test_the_loop_thread_alone_runs_fifo_on_its_cpu(tmp_path):
    from ahrs_service.service import Service

    cpu = min(os.sched_getaffinity(0))
    cfg = config_mod.validate({"estimator": {"name": "madgwick"}, "log": {"directory": str(tmp_path / "logs")},
                               "service": {"realtime_priority": 10, "cpu_affinity": [cpu]}})
    service = Service(cfg, duration_s=30.0)
    service.start()
    runner = threading.Thread(target=service.run, daemon=True)
    runner.start()
    try:
        # wait (bounded) until the loop has taken its priority: it does so as run() begins
        deadline = time.monotonic() + 60.0
        while _policy(runner.native_id) != os.SCHED_FIFO and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _policy(runner.native_id) == os.SCHED_FIFO
        assert os.sched_getparam(runner.native_id).sched_priority == 10
        assert os.sched_getaffinity(runner.native_id) == {cpu}
        # every other thread of the process (this one, the log writer's …) stays as it was
        tids = [int(t) for t in os.listdir("/proc/self/task")]
        fifo = [t for t in tids if _policy(t) == os.SCHED_FIFO]
        assert fifo == [runner.native_id], (fifo, tids)
        # and a thread the loop's thread starts does not inherit the priority (SCHED_RESET_ON_FORK):
        # the housekeeping and the samples go on meanwhile
        before = service.pipeline.samples
        deadline = time.monotonic() + 60.0
        while service.pipeline.samples <= before + 200 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert service.pipeline.samples > before + 200
    finally:
        service.request_stop()
        runner.join(30)
        files = list(service.log_writer.files)
        service.close()
    assert not runner.is_alive()
    messages = [m for f in files for _, m in _log_events(f)]
    assert "loop thread scheduled SCHED_FIFO at priority 10" in messages
    assert f"loop thread pinned to CPU {cpu}" in messages


def _madgwick_config(tmp_path: Path) -> Path:
    """The embedded default with madgwick (its kernels compile in seconds when the cache is cold)."""
    path = tmp_path / "config.toml"
    path.write_text('[estimator]\nname = "madgwick"\n')
    return path


def _unprivileged_prefix() -> list[str] | None:
    """A command prefix that runs a process without CAP_SYS_NICE and CAP_IPC_LOCK, or None."""
    if os.geteuid() == 0:
        setpriv = shutil.which("setpriv")
        if setpriv is None:
            return None
        return [setpriv, "--bounding-set", "-sys_nice,-ipc_lock", "--inh-caps", "-sys_nice,-ipc_lock"]
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return [] if soft == 0 else None


def test_a_process_that_may_not_raise_its_priority_says_how_and_runs_on(tmp_path):
    prefix = _unprivileged_prefix()
    if prefix is None:
        pytest.skip("no way to run the service without the right to real-time priority here "
                    "(as root: setpriv missing; as a user: RLIMIT_RTPRIO above 0)")
    limits = ["prlimit", "--rtprio=0", "--memlock=65536", "--"] if shutil.which("prlimit") else []
    proc = subprocess.run(
        [*prefix, *limits, *ahrs_service_command(), "run", "--config", str(_madgwick_config(tmp_path)),
         "--duration", "3", "--no-log", "--realtime-priority", "20", "--lock-memory"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    lines = proc.stderr.splitlines()
    priority = [x for x in lines if "[service] realtime_priority = 20 not applied" in x]
    memory = [x for x in lines if "[service] lock_memory not applied" in x]
    assert len(priority) == 1 and "LimitRTPRIO=20" in priority[0], lines[-20:]
    assert len(memory) == 1 and "LimitMEMLOCK=infinity" in memory[0], lines[-20:]
    # it ran on: the summary line of a finished run
    assert any("samples" in x for x in lines[-5:]), lines[-5:]


def _vm_locked_kib(pid: int) -> int | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmLck:"):
                return int(line.split()[1])
    except OSError:
        return None
    return 0


@pytest.mark.skipif(resource.getrlimit(resource.RLIMIT_MEMLOCK)[0] != resource.RLIM_INFINITY and os.geteuid() != 0,
                    reason="the memory-lock limit here is finite and the tests do not run as root")
def test_lock_memory_locks_the_process_memory(tmp_path):
    proc = subprocess.Popen([*ahrs_service_command(), "run", "--config", str(_madgwick_config(tmp_path)),
                             "--duration", "60", "--no-log", "--lock-memory"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    try:
        locked = 0
        deadline = time.monotonic() + 120.0
        while proc.poll() is None and time.monotonic() < deadline:
            locked = _vm_locked_kib(proc.pid) or 0
            if locked > 10_000:
                break
            time.sleep(0.1)
        assert locked > 10_000  # KiB: the interpreter, numpy and the loaded kernels
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=60)
    assert "Traceback" not in err
    assert "memory locked (mlockall)" in err
