"""Helpers the loopback integration tests share: run an async test body with a deadline, wait
for a condition set by worker threads, a server on its own event loop in a thread, a client for
it, and an inspection that blocks until the test releases it.

Importable as ``loopback`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable, Coroutine, Iterator
from dataclasses import dataclass, field
from typing import Any, TypeVar

from robot_client import VisionClient
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.results import ResultLog
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import builtin_catalog

T = TypeVar("T")


def run(coro: Coroutine[Any, Any, T], timeout_s: float = 30.0) -> T:
    """Run one async test body with an overall deadline (no pytest-asyncio here)."""

    async def guarded() -> T:
        async with asyncio.timeout(timeout_s):
            return await coro

    return asyncio.run(guarded())


async def wait_until(predicate: Callable[[], bool], what: str, timeout_s: float = 10.0) -> None:
    async with asyncio.timeout(timeout_s):
        # Polling: what we wait for happens in worker threads, which set no asyncio.Event.
        while not predicate():  # noqa: ASYNC110
            await asyncio.sleep(0.005)
    assert predicate(), what


@contextlib.contextmanager
def server_in_thread(
    catalog: Catalog | None = None, *, results: ResultLog | None = None, **settings: Any
) -> Iterator[VisionServer]:
    """A server (default: the built-in catalog) on port 0, on its own event loop in a thread,
    for tests that use blocking sockets or the blocking client."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="test-server", daemon=True)
    thread.start()
    server = VisionServer(
        catalog or builtin_catalog(), ServerSettings(port=0, **settings), results=results
    )
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(10.0)
        yield server
    finally:
        with contextlib.suppress(RuntimeError):  # not started
            asyncio.run_coroutine_threadsafe(server.stop(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()


def client_for(server: VisionServer, **kwargs: Any) -> VisionClient:
    kwargs.setdefault("request_timeout_s", 10.0)
    return VisionClient("127.0.0.1", server.port, **kwargs)


@dataclass(eq=False)
class Gate:
    """An inspection whose runs block their worker thread until ``release`` is set."""

    name: str = "gate"
    camera: str = "tool"
    type: str = "test_gate"  # a type of its own: its data follows no real type's schema
    uses_depth: bool = False
    frames: int = 1
    release: threading.Event = field(default_factory=threading.Event)
    entered: int = 0
    finished: int = 0
    report_shape: bool = False
    """Answer with the image's shape instead of ``{"gate": True}``."""
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        with self._lock:
            self.entered += 1
        released = self.release.wait(20.0)
        with self._lock:
            self.finished += 1
        if not released:
            raise RuntimeError("the test never released the gate")
        if self.report_shape:
            return InspectionOutcome(True, {"shape": list(image.color.shape)})
        return InspectionOutcome(True, {"gate": True})
