"""Which CPU the control loop runs on, and which the rest of afmctl runs on (Linux).

The loop thread spins for the last ``loop.spin_s`` before each deadline and needs the
interpreter lock then; any other thread of afmctl that runs on the same CPU at that moment
(the dispatcher writing the run log, the zenoh process serialising a batch, a simulator)
either preempts it or is preempted while holding the lock, and the loop waits. With
``loop.cpu`` the loop thread gets a CPU of its own: it is pinned there, and every other
thread afmctl starts (feeder, dispatcher, zenoh process and its pipe threads, and in
``afmctl run`` the main thread with the in-process simulator) is pinned to the other CPUs.

``loop.cpu``: ``"auto"`` (default) — with ``loop.realtime_priority`` set, the highest CPU
this process may use, when it may use two or more; without it no pinning, because helper
threads crowded onto the other CPUs at normal priority are preempted there while holding
the interpreter lock, and the loop waits for them (priority inversion); an integer — that
CPU (it must be one the process may use); ``"none"`` — no pinning. See docs/CONTROLLER.md and the ``bench:loop-zenoh`` section of docs/BENCHMARKS.md.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Any

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CpuPlan:
    """``loop_cpu``: the loop thread's CPU; ``others``: every other thread's CPUs (both None:
    no pinning); ``why``: one line for the run's events."""

    loop_cpu: int | None
    others: frozenset[int] | None
    why: str


_ALLOWED: list[frozenset[int] | None] = []


def allowed_cpus() -> frozenset[int] | None:
    """The CPUs this process may run on, or None where the OS cannot say (not Linux). Read
    once, at the first call — before afmctl pins any of its threads (a pinned thread would
    report only its own CPUs)."""
    if not _ALLOWED:
        try:
            _ALLOWED.append(frozenset(os.sched_getaffinity(0)))
        except (AttributeError, OSError):
            _ALLOWED.append(None)
    return _ALLOWED[0]


def plan(setting: int | str | None, allowed: frozenset[int] | None, realtime: bool = True) -> CpuPlan:
    """The pinning for ``loop.cpu`` = ``setting`` on a process allowed ``allowed`` CPUs;
    ``realtime``: ``loop.realtime_priority`` is set (``"auto"`` pins only then)."""
    if setting is None or setting == "none":
        return CpuPlan(None, None, "loop.cpu none: no CPU pinning")
    if setting == "auto" and not realtime:
        return CpuPlan(None, None, "no CPU pinning (loop.cpu auto pins with loop.realtime_priority)")
    if allowed is None:
        return CpuPlan(None, None, "CPU pinning not available on this OS")
    if len(allowed) < 2:
        return CpuPlan(None, None, f"one CPU available ({sorted(allowed)}): no CPU pinning")
    cpu = max(allowed) if setting == "auto" else int(setting)
    if cpu not in allowed:
        return CpuPlan(None, None, f"loop.cpu {cpu} is not one of the CPUs this process may use "
                                   f"{sorted(allowed)}: no CPU pinning")
    others = allowed - {cpu}
    return CpuPlan(cpu, others, f"loop thread on CPU {cpu}, other afmctl threads on CPU "
                                f"{','.join(str(c) for c in sorted(others))}")


def plan_for(loop: Any) -> CpuPlan:
    """:func:`plan` for this process and a config's ``[loop]`` section (``cpu``,
    ``realtime_priority``)."""
    return plan(loop.cpu, allowed_cpus(), loop.realtime_priority is not None)


def pin_this_thread(cpus: frozenset[int] | None) -> bool:
    """Pin the calling thread (only it) to ``cpus``; False when ``cpus`` is None or the OS
    refuses."""
    if not cpus:
        return False
    try:
        os.sched_setaffinity(0, cpus)   # pid 0: the calling thread (Linux)
        return True
    except (AttributeError, OSError) as err:
        log.warning("cannot pin a thread to CPU %s: %s", sorted(cpus), err)
        return False
