"""Bringing an inspection onto the event loop in tests of ``inline_ms``: its first runs go to a
worker (their cost is not known yet) and a run that the machine's load happened to slow down
keeps it there for a while, so a test runs it until a run lands on the loop instead of
counting on the second one doing so."""

from __future__ import annotations

import threading
import time
from collections.abc import Awaitable, Callable

from vision_server.inspections import InspectionInput, InspectionOutcome

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


class FailsSlowly:
    """An inspection, cheap while it passes; once ``fail_after_ms`` is set each run burns that
    much CPU and then raises ``error()`` (a search that finds nothing in a large image, or a
    bug deep in an inspection). Notes the thread of each run in ``threads``."""

    camera = "tool"
    uses_depth = False
    frames = 1

    def __init__(self, name: str, error: Callable[[], Exception]) -> None:
        self.name = name
        self.type = f"test_{name}"
        self._error = error
        self.fail_after_ms = 0.0
        self.threads: list[str] = []

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        self.threads.append(threading.current_thread().name)
        if self.fail_after_ms:
            end = time.perf_counter() + self.fail_after_ms / 1000.0
            while time.perf_counter() < end:
                pass
            raise self._error()
        return InspectionOutcome(True, {})
