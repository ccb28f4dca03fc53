"""Real-time scheduling of the estimation loop: the ``[service]`` section.

On a busy companion computer a loop at normal priority waits behind every CPU-bound process,
and the IMU's FIFO overflows meanwhile. PX4 and ArduPilot on Linux run their sensor threads
under SCHED_FIFO and lock their memory; the service does the same for the one thread that
drains the IMU and estimates (the thread that calls ``Service.run``), and for nothing else:

* the policy is set with ``SCHED_RESET_ON_FORK``, so threads and processes started later
  (a live calibration's fit, a reload's compile child) run at normal priority and cannot
  hold a CPU at the loop's priority;
* ``mlockall`` keeps the pages the loop touches resident (no major page fault in a tick);
  it is attempted only where the memory-lock limit allows the whole process, because a
  ``MCL_FUTURE`` lock under a finite limit makes later allocations fail;
* ``cpu_affinity`` pins the loop thread (threads it starts later inherit the set).

Where the process may not raise its priority or lock its memory, each refused setting is
one warning line that names how to allow it (docs/systemd.md, "Real-time scheduling"); the
service runs on at normal priority. Off by default: ``run`` from a terminal changes nothing;
the shipped systemd unit turns it on.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import resource
from dataclasses import dataclass, field
from typing import Any

from ahrs_service.core.settings import ConfigError, Section, boolean, choice, number

__all__ = ["SERVICE", "RealtimeSettings", "RealtimeOutcome", "apply_to_this_thread", "undo_memory_lock"]

#: the loop's priority the shipped systemd unit asks for (as PX4's sensor threads: high, but
#: below the kernel's own threaded interrupts at 50 on PREEMPT_RT kernels)
UNIT_PRIORITY = 40

_POLICIES = {"fifo": "SCHED_FIFO", "rr": "SCHED_RR"}

# <sys/mman.h>
_MCL_CURRENT = 1
_MCL_FUTURE = 2


def _cpu_list(key: str, v: Any) -> list[int]:
    """A list of CPU numbers (empty: any CPU)."""
    if not isinstance(v, list) or not all(isinstance(c, int) and not isinstance(c, bool) and 0 <= c < 4096 for c in v):
        raise ConfigError(f"{key}: expected a list of CPU numbers (e.g. [3]), or [] for any CPU; got {v!r}")
    return sorted(set(v))


SERVICE: Section = {
    # 0: normal scheduling; 1–99: the loop thread's real-time priority
    "realtime_priority": (0, number(0, 99, integer=True)),
    "realtime_policy": ("fifo", choice(tuple(_POLICIES))),
    # mlockall(MCL_CURRENT | MCL_FUTURE): needs LimitMEMLOCK=infinity (or CAP_IPC_LOCK)
    "lock_memory": (False, boolean),
    # CPUs the loop thread may run on; [] leaves the scheduler free
    "cpu_affinity": ([], _cpu_list),
}


@dataclass(frozen=True)
class RealtimeSettings:
    """What ``[service]`` asks for the loop thread. priority 0: normal scheduling."""

    priority: int = 0
    policy: str = "fifo"
    lock_memory: bool = False
    cpus: tuple[int, ...] = ()

    @classmethod
    def from_config(cls, section: dict[str, Any]) -> "RealtimeSettings":
        return cls(int(section["realtime_priority"]), str(section["realtime_policy"]),
                   bool(section["lock_memory"]), tuple(section["cpu_affinity"]))

    @property
    def wanted(self) -> bool:
        return bool(self.priority or self.lock_memory or self.cpus)


@dataclass
class RealtimeOutcome:
    """What :func:`apply_to_this_thread` did: ``applied`` and ``refused`` are one line each
    (refusals name the setting, the reason and how to allow it)."""

    applied: list[str] = field(default_factory=list)
    refused: list[str] = field(default_factory=list)
    memory_locked: bool = False


def apply_to_this_thread(settings: RealtimeSettings) -> RealtimeOutcome:
    """Applies ``settings`` to the calling thread (and, for the memory lock, the process)."""
    out = RealtimeOutcome()
    if settings.cpus:
        _set_affinity(settings.cpus, out)
    if settings.priority:
        _set_priority(settings.priority, settings.policy, out)
    if settings.lock_memory:
        _lock_memory(out)
    return out


def _set_affinity(cpus: tuple[int, ...], out: RealtimeOutcome) -> None:
    listed = ", ".join(map(str, cpus))
    try:
        os.sched_setaffinity(0, cpus)  # 0: the calling thread (Linux)
    except (OSError, ValueError) as exc:
        usable = sorted(os.sched_getaffinity(0))
        out.refused.append(f"[service] cpu_affinity = [{listed}] not applied ({_reason(exc)}): "
                           f"this process may run on CPUs {', '.join(map(str, usable))}")
        return
    out.applied.append(f"loop thread pinned to CPU {listed}")


def _set_priority(priority: int, policy: str, out: RealtimeOutcome) -> None:
    name = _POLICIES[policy]
    try:
        os.sched_setscheduler(0, getattr(os, name) | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
    except OSError as exc:
        out.refused.append(
            f"[service] realtime_priority = {priority} not applied ({_reason(exc)}); the loop runs at normal "
            f"priority. Allow it with LimitRTPRIO={priority} in the systemd unit, or an 'rtprio {priority}' line "
            f"for the user in /etc/security/limits.conf, or CAP_SYS_NICE")
        return
    out.applied.append(f"loop thread scheduled {name} at priority {priority}")


def _lock_memory(out: RealtimeOutcome) -> None:
    soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
    if soft != resource.RLIM_INFINITY and os.geteuid() != 0:
        out.refused.append(
            f"[service] lock_memory not applied: the memory-lock limit is {soft // 1024} KiB, less than the "
            f"process needs; allow it with LimitMEMLOCK=infinity in the systemd unit (or 'memlock unlimited' "
            f"in /etc/security/limits.conf)")
        return
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) != 0:
        err = ctypes.get_errno()
        out.refused.append(f"[service] lock_memory not applied ({os.strerror(err)}); allow it with "
                           f"LimitMEMLOCK=infinity in the systemd unit")
        return
    out.memory_locked = True
    out.applied.append("memory locked (mlockall)")


def undo_memory_lock() -> None:
    """``munlockall``: a service closed inside a longer-lived process (tests, tools) leaves
    no lock behind."""
    libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    libc.munlockall()


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.errno is not None:
        return os.strerror(exc.errno)
    return str(exc)
