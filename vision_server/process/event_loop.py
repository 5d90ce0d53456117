"""The event loop ``serve`` runs on: Python's own asyncio loop, or uvloop (libuv's, a
well-kept C implementation of the same interface) when it is installed and chosen
(``server: event_loop``). Bench section 1 measures both in one run."""

from __future__ import annotations

import asyncio
import importlib.util
from collections.abc import Callable

EVENT_LOOPS = ("asyncio", "uvloop")
"""The loops ``server: event_loop`` names."""


def uvloop_available() -> bool:
    """Whether uvloop can be imported (the extra ``uvloop``; not on Windows)."""
    return importlib.util.find_spec("uvloop") is not None


def loop_factory(name: str) -> Callable[[], asyncio.AbstractEventLoop]:
    """What makes a new loop of kind ``name`` (for ``asyncio.Runner(loop_factory=...)``);
    ValueError naming the fix when uvloop is asked for and not installed."""
    if name == "asyncio":
        return asyncio.new_event_loop
    if name != "uvloop":
        raise ValueError(f"event_loop {name!r}: one of {', '.join(EVENT_LOOPS)}")
    if not uvloop_available():
        raise ValueError(
            "event_loop 'uvloop' needs the uvloop package (pip install 'cellvision[uvloop]'); "
            "or set event_loop: asyncio"
        )
    import uvloop

    make: Callable[[], asyncio.AbstractEventLoop] = uvloop.new_event_loop
    return make


__all__ = ["EVENT_LOOPS", "loop_factory", "uvloop_available"]
