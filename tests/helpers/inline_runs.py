"""Bringing an inspection onto the event loop in tests of ``inline_ms``: its first runs go to a
worker (their cost is not known yet) and a run that the machine's load happened to slow down
keeps it there for a while, so a test runs it until a run lands on the loop instead of
counting on the second one doing so."""

from __future__ import annotations

import threading
from collections.abc import Awaitable, Callable

RUNS_LIMIT = 2000
"""Enough for an estimate that one slowed run raised 50-fold to decay back (1 % a run)."""


async def until_on_the_loop(
    inspect: Callable[[], Awaitable[object]], threads: list[str], limit: int = RUNS_LIMIT
) -> None:
    """Await ``inspect()`` until the inspection's latest run (the last thread name it noted
    in ``threads``) was on this thread, the event loop's."""
    here = threading.current_thread().name
    for _ in range(limit):
        await inspect()
        if threads and threads[-1] == here:
            return
    raise AssertionError(f"no run on the event loop in {limit} runs: {threads[-5:]}")
