"""The time a camera sees: :class:`Clock`, the system's (:data:`SYSTEM_CLOCK`) and a manual one.

Cameras read the time for deadlines, playback pacing, stall detection and frame timestamps,
and they wait on their condition variable until a deadline. Both go through a clock so that
the logic can be tested with :class:`ManualClock`, whose time moves only when the test says
so: no test verdict depends on how fast a shared machine happens to be.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol

__all__ = ["SYSTEM_CLOCK", "Clock", "ManualClock", "SystemClock"]


class Clock(Protocol):
    """Time for a camera. ``monotonic`` and ``wait_until`` deadlines are in the same seconds."""

    def monotonic(self) -> float:
        """Seconds on a clock that never goes back (deadlines, pacing)."""
        ...

    def time(self) -> float:
        """Seconds since the epoch (frame timestamps)."""
        ...

    def wait_until(self, cond: threading.Condition, deadline: float) -> None:
        """Wait on ``cond`` (held by the caller) until notified or ``monotonic() >= deadline``.

        May return early (spuriously): callers re-check their predicate and the time.
        """
        ...


class SystemClock:
    """The real time: ``time.monotonic`` and ``time.time``."""

    def monotonic(self) -> float:
        return time.monotonic()

    def time(self) -> float:
        return time.time()

    def wait_until(self, cond: threading.Condition, deadline: float) -> None:
        remaining = deadline - time.monotonic()
        if remaining > 0:
            cond.wait(remaining)


SYSTEM_CLOCK = SystemClock()
"""The clock every camera uses unless it is given another."""


class ManualClock:
    """A clock that stands still until :meth:`advance` moves it (for tests).

    ``time()`` is ``epoch_s`` plus the same offset as ``monotonic()``. :meth:`advance` wakes
    every thread waiting in :meth:`wait_until`, which then re-checks its deadline;
    :attr:`waiters` says how many threads are waiting, so that a test can advance the time
    only once a grab or a reader is parked on it.
    """

    _LIVENESS_S = 1.0
    """A waiter wakes this often (real seconds) to re-check: no lost wake-up can hang it."""

    def __init__(self, start_s: float = 1000.0, *, epoch_s: float = 1_700_000_000.0) -> None:
        self._lock = threading.Lock()
        self._now = start_s
        self._epoch_offset = epoch_s - start_s
        self._conds: list[threading.Condition] = []
        self._waiters = 0

    def monotonic(self) -> float:
        with self._lock:
            return self._now

    def time(self) -> float:
        with self._lock:
            return self._now + self._epoch_offset

    @property
    def waiters(self) -> int:
        """Threads waiting in :meth:`wait_until` right now."""
        with self._lock:
            return self._waiters

    def advance(self, seconds: float) -> None:
        """Move the time forward by ``seconds`` (>= 0) and wake every waiter."""
        if not seconds >= 0:
            raise ValueError(f"a clock only moves forward, got {seconds!r} s")
        with self._lock:
            self._now += seconds
            conds = list(self._conds)
        for cond in conds:
            with cond:
                cond.notify_all()

    def wait_until(self, cond: threading.Condition, deadline: float) -> None:
        # Checking the time and registering happen under our lock, and advance() moves the
        # time under it too before notifying under ``cond``, which the caller holds until
        # cond.wait releases it: an advance is either seen here or wakes the wait.
        with self._lock:
            if self._now >= deadline:
                return
            if not any(c is cond for c in self._conds):
                self._conds.append(cond)
            self._waiters += 1
        try:
            cond.wait(self._LIVENESS_S)
        finally:
            with self._lock:
                self._waiters -= 1
