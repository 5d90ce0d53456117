"""CPU priority of the work that can wait: the main lane's threads and the worker processes.

On a machine whose cores the main lane keeps busy (two cores, two 30 ms locates in flight), a
cheap request needs the event loop, a fast-lane thread and its client to get a core at once,
not after the scheduler's next turn. Running the main lane's workers at a higher niceness than
the rest of the server gives that priority by cost: a woken event loop preempts a locate
instead of queueing behind it (bench section 2c measures it).

Niceness is set relative to the server process's own (its main thread's), so it does not add
up when a lowered thread starts another process. Raising niceness needs no privilege; lowering
it needs CAP_SYS_NICE, so a worker that was born lower than asked (inherited) stays so.
Linux gives each thread its own niceness (``setpriority`` on the thread's id); elsewhere it
belongs to the whole process, so there only a worker *process* is lowered.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading

MAX_NICE = 19
POLICIES = ("nice", "idle")
"""How the worker processes yield: ``nice`` (a higher niceness: they still get a share of a
busy machine; a woken event loop waits up to the scheduler's slice, a few ms, for a core) or
``idle`` (``SCHED_IDLE``: they run only on cores nothing else wants, so a woken event loop or
fast-lane thread preempts them at once; but any other busy process on the machine starves them
and their requests end in DEADLINE_EXCEEDED). Measured in bench section 2c."""


def process_niceness() -> int:
    """The niceness of this process's main thread (the server's own priority)."""
    return os.getpriority(os.PRIO_PROCESS, os.getpid())


def target_niceness(by: int) -> int:
    """The niceness of work lowered by ``by`` below this process's own (clamped at 19)."""
    return min(process_niceness() + by, MAX_NICE)


def _set_thread(tid: int, niceness: int) -> None:
    # Lowering a niceness needs privilege: without it the thread keeps the one it has.
    with contextlib.suppress(PermissionError):
        os.setpriority(os.PRIO_PROCESS, tid, niceness)


def lower_this_thread(by: int) -> None:
    """Run the calling thread ``by`` (0..19) below this process's own niceness. Leaves the
    thread as it is where niceness is per process, or when ``by`` is 0."""
    if by > 0 and sys.platform == "linux":
        _set_thread(threading.get_native_id(), target_niceness(by))


def run_this_process_at(niceness: int | None, policy: str = "nice") -> None:
    """Set a process that has just started (its one thread; threads it starts later inherit
    it) to ``niceness``; None leaves it as it is. ``policy`` "idle": Linux's ``SCHED_IDLE``
    as well, so that any other runnable task preempts it at once (see
    :data:`POLICIES`)."""
    if niceness is not None:
        _set_thread(0, niceness)
    if policy == "idle" and hasattr(os, "SCHED_IDLE"):
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
