"""CPU priority for helpers that share a machine with the service (the viewer, its browser).

``idle`` puts the process in Linux's ``SCHED_IDLE`` class: it runs only on CPU time that no
normal process wants, so however much a software-rendered page costs, the service's labeling
thread is never kept waiting by it. Children (a browser launched from the process) inherit the
class. Where ``SCHED_IDLE`` is not available the process falls back to the lowest nice level.
``low`` is ``nice 10``; ``normal`` changes nothing.
"""

from __future__ import annotations

import os

PRIORITIES = ("idle", "low", "normal")


def lower_priority(priority: str) -> str:
    """Applies ``priority`` (one of :data:`PRIORITIES`) to this process; returns what it did."""
    if priority not in PRIORITIES:
        raise ValueError(f"priority must be one of {', '.join(PRIORITIES)}, not {priority!r}")
    if priority == "normal":
        return "normal"
    if priority == "idle":
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
            return "SCHED_IDLE"
        except (AttributeError, OSError):
            os.nice(19)
            return "nice 19"
    os.nice(10)
    return "nice 10"
