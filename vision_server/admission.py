"""Admission: what bounds the server's work and memory, whoever the clients are.

- :class:`WorkPool`: the threads that run inspections, with a bounded number of slots (workers +
  queue); a request gets a slot or BUSY, never an unbounded queue.
- :class:`ByteBudget`: one server-wide budget for the bytes the server holds for requests and
  replies (bodies being received, replies waiting to be sent). A frame is admitted only when its
  bytes fit, so the memory held for clients is bounded by the budget, not by the number of
  clients times the frame limit.
- :class:`Admission`: what one request holds (a slot, bytes), released exactly once.

All three are thread-safe: slots and bytes are taken on the event loop and released from worker
threads or the loop.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

_T = TypeVar("_T")


class WorkPool:
    """A thread pool with bounded admission: a slot is taken before the work is submitted and
    given back when the work returns; a full pool refuses instead of queueing."""

    def __init__(self, workers: int, queue_depth: int) -> None:
        self.capacity = workers + queue_depth
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="inspect")
        self._lock = threading.Lock()
        self._admitted = 0

    @property
    def admitted(self) -> int:
        """Slots taken: jobs running or waiting, and slots reserved for requests being read."""
        return self._admitted

    def try_reserve(self) -> bool:
        """Take a slot for work to be submitted later (:meth:`submit_reserved`); False when full."""
        with self._lock:
            if self._admitted >= self.capacity:
                return False
            self._admitted += 1
            return True

    def release(self) -> None:
        """Give back a reserved slot that will not be used."""
        with self._lock:
            self._admitted -= 1

    def submit_reserved(self, fn: Callable[[], _T]) -> asyncio.Future[_T]:
        """Run ``fn`` on a slot taken by :meth:`try_reserve`. The slot is held until ``fn``
        returns, even if the awaiting request gave up (its deadline passed)."""

        def job() -> _T:
            try:
                return fn()
            finally:
                self.release()

        return asyncio.get_running_loop().run_in_executor(self._executor, job)

    def try_submit(self, fn: Callable[[], _T]) -> asyncio.Future[_T] | None:
        """Take a slot and run ``fn`` in it; None when the pool is full."""
        if not self.try_reserve():
            return None
        return self.submit_reserved(fn)

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


class ByteBudget:
    """A server-wide count of bytes held for clients, with a hard limit."""

    def __init__(self, limit: int) -> None:
        if limit <= 0:
            raise ValueError(f"a byte budget must be positive, got {limit}")
        self.limit = limit
        self._lock = threading.Lock()
        self._used = 0
        self.peak = 0
        """The most bytes held at once since start (for health output and tests)."""
        self.refused = 0
        """How many reservations did not fit."""

    @property
    def used(self) -> int:
        return self._used

    def try_reserve(self, n: int) -> bool:
        with self._lock:
            if n < 0 or self._used + n > self.limit:
                self.refused += 1
                return False
            self._used += n
            self.peak = max(self.peak, self._used)
            return True

    def release(self, n: int) -> None:
        with self._lock:
            self._used -= n
            if self._used < 0:  # a double release is a bug; never let it widen the budget
                raise RuntimeError(f"byte budget released {-self._used} bytes more than reserved")


class Admission:
    """What one request holds: maybe a pool slot, some budget bytes. ``release`` gives back
    whatever is still held; it is idempotent, so every path may call it."""

    def __init__(self, pool: WorkPool | None, budget: ByteBudget | None) -> None:
        self._pool = pool
        self._budget = budget
        self._lock = threading.Lock()
        self.slot = False
        """True while a reserved pool slot is held and not yet handed to the pool."""
        self.bytes = 0

    def take_slot(self) -> bool:
        if self._pool is None or not self._pool.try_reserve():
            return False
        self.slot = True
        return True

    def take_bytes(self, n: int) -> bool:
        """Reserve ``n`` more bytes; True when they fit (always True without a budget)."""
        if n <= 0 or self._budget is None:
            return True
        if not self._budget.try_reserve(n):
            return False
        with self._lock:
            self.bytes += n
        return True

    def hand_slot_to_pool(self) -> bool:
        """The slot goes to :meth:`WorkPool.submit_reserved` (the job gives it back)."""
        with self._lock:
            had, self.slot = self.slot, False
        return had

    def release(self) -> None:
        with self._lock:
            slot, self.slot = self.slot, False
            n, self.bytes = self.bytes, 0
        if slot and self._pool is not None:
            self._pool.release()
        if n and self._budget is not None:
            self._budget.release(n)
