"""Admission: what bounds the server's work and memory, whoever the clients are.

- :class:`WorkPool`: the threads that run inspections, in two lanes. The **main** lane has
  ``workers`` threads; the **fast** lane has threads of its own that only run requests whose
  measured cost is at most ``fast_lane_ms``, so that a 2 ms check never waits behind 30 ms
  locates (SPEC §6.1 allows any order between requests). Each lane admits by count (its
  threads + ``queue_depth``: the memory of the bodies read) and by cost (the expected
  milliseconds of work it holds, from :class:`CostModel`, at most ``max_queue_ms`` per thread:
  the wait a new request would see). A request gets a :class:`Slot` at once, or joins the
  lane's FIFO of :class:`Waiter` s (a front-end that can stop reading, the TCP one, waits
  there: backpressure instead of BUSY), or is refused.
- :class:`CostModel`: the measured time each inspection holds a worker (an exponentially
  weighted mean per inspection), which decides its lane and its weight in the queue.
- :class:`ByteBudget`: one server-wide budget for the bytes the server holds for requests and
  replies (bodies being received, replies waiting to be sent). A frame is admitted only when its
  bytes fit, so the memory held for clients is bounded by the budget, not by the number of
  clients times the frame limit.
- :class:`Admission`: what one request holds (a slot, bytes), released exactly once.

All are thread-safe: slots and bytes are taken on the event loop and released from worker
threads or the loop; a waiter is woken on its own event loop.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Literal, TypeVar

from ..process import MAX_NICE, lower_this_thread

_T = TypeVar("_T")
LaneName = Literal["main", "fast", "try"]
TRY_PREFIX = "try:"
"""A console try's cost-model key is its inspection's name behind this (:func:`try_key`):
tries, with options a production request never has, learn their own cost and run in a lane
of their own, so that they neither teach production's estimates nor take its threads."""
TRY_BUDGET_SHARE = 0.5
"""The share of the byte budget tries may hold at once; the rest stays for production."""


def try_key(inspection: str) -> str:
    """The cost model's and the pool's key for a console try of ``inspection``."""
    return TRY_PREFIX + inspection


MIN_RETRY_MS = 5.0
"""The least wait a BUSY suggests while work is ahead (unmeasured costs count as 0 ms): a
retry sooner would only be refused again."""


class CostModel:
    """How long each kind of work holds a worker, in milliseconds: an exponentially weighted
    mean of the measured durations per key (an inspection's name). Unknown keys have no cost
    yet (None) and run in the main lane until measured."""

    def __init__(self, weight: float = 0.2) -> None:
        self._weight = weight
        self._lock = threading.Lock()
        self._mean: dict[str, float] = {}

    def estimate(self, key: str | None) -> float | None:
        if key is None:
            return None
        with self._lock:
            return self._mean.get(key)

    def observe(self, key: str | None, ms: float) -> None:
        if key is None:
            return
        with self._lock:
            old = self._mean.get(key)
            self._mean[key] = ms if old is None else old + self._weight * (ms - old)

    def snapshot(self) -> dict[str, float]:
        with self._lock:
            return dict(self._mean)


class PeakCost(CostModel):
    """The slowest recent duration per key, in milliseconds: each measurement replaces the
    estimate when it is higher, else the estimate decays towards it by ``decay`` per
    measurement (1 %: one slow run among fast ones counts for a few hundred runs). For a
    decision that must hold for the exceptional run, not the mean one (what may run on the
    event loop)."""

    def __init__(self, decay: float = 0.01) -> None:
        super().__init__(weight=decay)

    def observe(self, key: str | None, ms: float) -> None:
        if key is None:
            return
        with self._lock:
            old = self._mean.get(key)
            self._mean[key] = ms if old is None or ms >= old else old + self._weight * (ms - old)


class LoopCosts:
    """What a run would hold the event loop for (ms), per key (an inspection, with or without
    drawing its overlay) and image size: the slowest recent cost per byte of image
    (:class:`PeakCost`; bytes, so that a colour image counts its three channels) times the
    request's bytes, known only up to the largest image measured so far (a cost that grows
    faster than the image is never extrapolated)."""

    def __init__(self, decay: float = 0.01) -> None:
        self._per_byte = PeakCost(decay)
        self._lock = threading.Lock()
        self._largest: dict[str, int] = {}

    def estimate(self, key: str, size: int) -> float | None:
        """The cost of a run on ``size`` bytes of images; None when unknown."""
        with self._lock:
            largest = self._largest.get(key)
        per_byte = self._per_byte.estimate(key)
        if largest is None or per_byte is None or not 0 < size <= largest:
            return None
        return per_byte * size

    def observe(self, key: str, ms: float, size: int) -> None:
        size = max(size, 1)
        self._per_byte.observe(key, ms / size)
        with self._lock:
            self._largest[key] = max(self._largest.get(key, 0), size)


@dataclass(frozen=True)
class Slot:
    """A place in a lane, held from admission until the work returns. ``cost_ms`` is what it
    weighs in the lane's queue (its estimate when admitted, 0 when unknown)."""

    lane: Lane
    key: str | None
    cost_ms: float


class Waiter:
    """A request waiting for a slot in a lane's FIFO; :meth:`wait` returns the slot that a
    finishing job handed over."""

    def __init__(self, pool: WorkPool, lane: Lane, key: str | None, cost_ms: float) -> None:
        self._pool = pool
        self.lane = lane
        self.key = key
        self.cost_ms = cost_ms
        self._loop = asyncio.get_running_loop()
        self._future: asyncio.Future[Slot] = self._loop.create_future()

    def grant(self, slot: Slot) -> None:
        """Hand ``slot`` over (from any thread); a waiter that gave up passes it on."""
        try:
            self._loop.call_soon_threadsafe(self._granted, slot)
        except RuntimeError:  # its event loop is closed: the server has stopped
            self._pool.release(slot)

    def _granted(self, slot: Slot) -> None:
        if self._future.done():
            self._pool.release(slot)
        else:
            self._future.set_result(slot)

    async def wait(self, timeout_s: float) -> Slot | None:
        """The slot, or None after ``timeout_s`` (the waiter is then gone from the queue)."""
        try:
            async with asyncio.timeout(timeout_s):
                return await asyncio.shield(self._future)
        except TimeoutError:
            return self._give_up()
        except asyncio.CancelledError:
            self._give_up_and_return()
            raise

    def _give_up(self) -> Slot | None:
        self._pool.forget(self)
        if not self._future.done():
            self._future.cancel()
            return None
        # Granted at the last moment: take it after all.
        return None if self._future.cancelled() else self._future.result()

    def _give_up_and_return(self) -> None:
        slot = self._give_up()
        if slot is not None:
            self._pool.release(slot)


class Lane:
    """One queue with its own threads. Counters are guarded by the pool's lock."""

    def __init__(
        self,
        name: LaneName,
        threads: int,
        queue_depth: int,
        max_queue_ms: float,
        *,
        nice: int = 0,
    ) -> None:
        self.name: LaneName = name
        self.threads = threads
        self.capacity = threads + queue_depth
        self.max_cost_ms = max_queue_ms * threads
        self.admitted = 0
        self.admitted_cost_ms = 0.0
        self.waiters: deque[Waiter] = deque()
        self.nice = nice
        """How much lower than the server's other threads this lane's threads run (niceness
        added, vision_server/process/cpu_priority.py)."""
        self.executor = ThreadPoolExecutor(
            max_workers=threads,
            thread_name_prefix=f"inspect-{name}",
            initializer=lower_this_thread,
            initargs=(nice,),
        )

    def has_room(self, cost_ms: float) -> bool:
        if self.admitted >= self.capacity:
            return False
        # A request heavier than the whole bound is still admitted into an empty lane.
        return self.admitted == 0 or self.admitted_cost_ms + cost_ms <= self.max_cost_ms

    def full_because(self, cost_ms: float) -> str:
        """Why a request of ``cost_ms`` finds no room, in words: the slot count or the queued
        work's bound (``max_queue_ms``), whichever refuses it (for BUSY's message)."""
        if self.admitted >= self.capacity:
            return (
                f"all {self.capacity} inspection slots of the {self.name} lane are taken "
                f"({self.threads} running + queue_depth)"
            )
        if self.admitted and self.admitted_cost_ms + cost_ms > self.max_cost_ms:
            return (
                f"the {self.name} lane holds {self.admitted_cost_ms:.0f} ms of measured work in "
                f"{self.admitted} request(s); one more of about {cost_ms:.0f} ms would pass its "
                f"bound of {self.max_cost_ms:.0f} ms (max_queue_ms x {self.threads} threads)"
            )
        return (
            f"{len(self.waiters)} request(s) already wait for the {self.name} lane (first come, "
            "first served)"
        )

    def expected_wait_ms(self, cost_ms: float) -> float:
        """When a slot is likely to be free for one more request: the queued work ahead
        (admitted and waiting) spread over the lane's threads; at least
        :data:`MIN_RETRY_MS` when there is work ahead whose cost is not measured yet."""
        waiting = sum(w.cost_ms for w in self.waiters)
        expected = (self.admitted_cost_ms + waiting + cost_ms) / self.threads
        if self.admitted or self.waiters:
            return max(expected, MIN_RETRY_MS)
        return expected


class WorkPool:
    """Worker threads in lanes, with bounded admission (see the module)."""

    def __init__(
        self,
        workers: int,
        queue_depth: int,
        *,
        fast_workers: int = 1,
        fast_lane_ms: float = 5.0,
        max_queue_ms: float = 2000.0,
        main_lane_nice: int = 0,
        costs: CostModel | None = None,
    ) -> None:
        self.main = Lane("main", workers, queue_depth, max_queue_ms, nice=main_lane_nice)
        self.fast = (
            Lane("fast", fast_workers, queue_depth, max_queue_ms) if fast_workers > 0 else None
        )
        # One thread for tries, at the lowest priority: a pathological try (800 s) can take
        # it, never a production lane's threads, slots or cost bound.
        self.tries = Lane("try", 1, 2, max_queue_ms, nice=MAX_NICE)
        self.fast_lane_ms = fast_lane_ms
        self.costs = costs or CostModel()
        self._lock = threading.Lock()

    # ----------------------------------------------------------------- introspection

    @property
    def lanes(self) -> tuple[Lane, ...]:
        """The production lanes (what BUSY, WELCOME and the counters speak of)."""
        return (self.main,) if self.fast is None else (self.main, self.fast)

    @property
    def admitted(self) -> int:
        """Slots taken in every lane: jobs running or waiting, and slots reserved for requests
        being read."""
        return sum(lane.admitted for lane in self.lanes)

    @property
    def capacity(self) -> int:
        return sum(lane.capacity for lane in self.lanes)

    @property
    def waiting(self) -> int:
        """Requests waiting for a slot (their connections not read meanwhile)."""
        return sum(len(lane.waiters) for lane in self.lanes)

    def lane_for(self, key: str | None) -> tuple[Lane, float]:
        """The lane a request for ``key`` belongs to, and its cost estimate (0 when unknown)."""
        cost = self.costs.estimate(key)
        if key is not None and key.startswith(TRY_PREFIX):
            return self.tries, 0.0 if cost is None else cost
        if cost is not None and self.fast is not None and cost <= self.fast_lane_ms:
            return self.fast, cost
        return self.main, 0.0 if cost is None else cost

    def expected_wait_ms(self, key: str | None) -> float:
        lane, cost = self.lane_for(key)
        with self._lock:
            return lane.expected_wait_ms(cost)

    def full_because(self, key: str | None) -> str:
        """Why a request for ``key`` finds its lane full (see :meth:`Lane.full_because`)."""
        lane, cost = self.lane_for(key)
        with self._lock:
            return lane.full_because(cost)

    # ----------------------------------------------------------------- admission

    def _lanes_for(self, key: str | None) -> tuple[tuple[Lane, ...], float]:
        """The lanes a request for ``key`` may run in, its own first: a cheap request may
        also take a free main-lane slot when the fast lane is full; a costly one never takes
        the fast lane's."""
        lane, cost = self.lane_for(key)
        if lane is self.tries:
            return (lane,), cost
        return ((lane, self.main) if lane is not self.main else (lane,)), cost

    def try_reserve(self, key: str | None = None) -> Slot | None:
        """A slot for work on ``key`` now, or None when its lanes are full (or others wait
        for them: first come, first served)."""
        lanes, cost = self._lanes_for(key)
        with self._lock:
            return self._take_any(lanes, key, cost)

    def reserve_or_wait(self, key: str | None = None) -> Slot | Waiter:
        """A slot now, or a place in its own lane's queue (await :meth:`Waiter.wait`)."""
        lanes, cost = self._lanes_for(key)
        with self._lock:
            slot = self._take_any(lanes, key, cost)
            if slot is not None:
                return slot
            waiter = Waiter(self, lanes[0], key, cost)
            lanes[0].waiters.append(waiter)
            return waiter

    def _take_any(self, lanes: tuple[Lane, ...], key: str | None, cost: float) -> Slot | None:
        for lane in lanes:
            slot = self._take(lane, key, cost)
            if slot is not None:
                return slot
        return None

    def _take(self, lane: Lane, key: str | None, cost: float) -> Slot | None:
        if lane.waiters or not lane.has_room(cost):
            return None
        lane.admitted += 1
        lane.admitted_cost_ms += cost
        return Slot(lane, key, cost)

    def forget(self, waiter: Waiter) -> None:
        with self._lock:
            if waiter in waiter.lane.waiters:
                waiter.lane.waiters.remove(waiter)

    def release(self, slot: Slot) -> None:
        """Give back ``slot``; the lane's first waiters that now fit get slots."""
        lane = slot.lane
        granted: list[tuple[Waiter, Slot]] = []
        with self._lock:
            lane.admitted -= 1
            lane.admitted_cost_ms = max(lane.admitted_cost_ms - slot.cost_ms, 0.0)
            while lane.waiters and lane.has_room(lane.waiters[0].cost_ms):
                waiter = lane.waiters.popleft()
                lane.admitted += 1
                lane.admitted_cost_ms += waiter.cost_ms
                granted.append((waiter, Slot(lane, waiter.key, waiter.cost_ms)))
        for waiter, given in granted:
            waiter.grant(given)

    # ----------------------------------------------------------------- running

    def submit(self, slot: Slot, fn: Callable[[], _T]) -> asyncio.Future[_T]:
        """Run ``fn`` in ``slot``'s lane. The slot is held until ``fn`` returns, even if the
        awaiting request gave up (its deadline passed); the time it took teaches the cost
        model."""

        def job() -> _T:
            t0 = time.perf_counter()
            try:
                return fn()
            finally:
                self.costs.observe(slot.key, (time.perf_counter() - t0) * 1000.0)
                self.release(slot)

        return asyncio.get_running_loop().run_in_executor(slot.lane.executor, job)

    def shutdown(self) -> None:
        for lane in (*self.lanes, self.tries):
            lane.executor.shutdown(wait=False, cancel_futures=True)


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

    def try_reserve(self, n: int, *, share: float = 1.0) -> bool:
        """Reserve ``n`` bytes if they fit within ``share`` of the limit (a request class that
        may hold only part of the budget, leaving the rest to production)."""
        with self._lock:
            if n < 0 or self._used + n > self.limit * share:
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
        self.slot: Slot | None = None
        """The reserved pool slot while it is held and not yet handed to the pool."""
        self.bytes = 0

    def take_slot(self, key: str | None = None) -> bool:
        if self._pool is None:
            return False
        slot = self._pool.try_reserve(key)
        if slot is None:
            return False
        self.slot = slot
        return True

    def hold_slot(self, slot: Slot) -> None:
        """Hold a slot obtained elsewhere (a :class:`Waiter`'s)."""
        with self._lock:
            assert self.slot is None
            self.slot = slot

    def take_bytes(self, n: int, *, share: float = 1.0) -> bool:
        """Reserve ``n`` more bytes; True when they fit within ``share`` of the budget (always
        True without a budget)."""
        if n <= 0 or self._budget is None:
            return True
        if not self._budget.try_reserve(n, share=share):
            return False
        with self._lock:
            self.bytes += n
        return True

    def hand_slot_to_pool(self) -> Slot | None:
        """The slot goes to :meth:`WorkPool.submit` (the job gives it back)."""
        with self._lock:
            slot, self.slot = self.slot, None
        return slot

    def release(self) -> None:
        with self._lock:
            slot, self.slot = self.slot, None
            n, self.bytes = self.bytes, 0
        if slot is not None and self._pool is not None:
            self._pool.release(slot)
        if n and self._budget is not None:
            self._budget.release(n)
