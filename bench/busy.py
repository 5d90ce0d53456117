"""BUSY for the benchmarks' clients: SPEC §6.1 asks a client to retry a BUSY answer later.

When the project's client retries by itself (``VisionClient(busy_timeout_s=...)``, after the
server's ``details.retry_after_ms``, counting in ``client.busy_retries``), the benchmarks use
that, so that they measure what a robot program gets. Otherwise (the client of today) they
retry by hand with exponential back-off: 5 ms doubling up to 200 ms, with jitter.
"""

from __future__ import annotations

import asyncio
import inspect
import random
import time
from collections.abc import Iterable
from typing import Any

from protocol import Busy, Result
from robot_client import VisionClient

from .servers import HOST

BACKOFF_S = 0.005
BACKOFF_MAX_S = 0.2
CLIENT_RETRIES: bool = "busy_timeout_s" in inspect.signature(VisionClient.__init__).parameters
"""Whether this VisionClient retries BUSY by itself (decided once, from its signature)."""


def retry_mode() -> str:
    """How BUSY is retried in this run, for the report."""
    if CLIENT_RETRIES:
        return (
            "by the client itself (`VisionClient(busy_timeout_s=...)`, after the server's "
            "retry-after hint)"
        )
    return (
        "by hand, with exponential back-off (5 ms doubling up to 200 ms, with jitter): this "
        "VisionClient has no `busy_timeout_s`"
    )


def make_client(port: int, *, busy_timeout_s: float, request_timeout_s: float = 60.0) -> Any:
    """A VisionClient for ``port`` on loopback that retries BUSY for up to ``busy_timeout_s``
    seconds by itself when it can (else :class:`Retrier` does)."""
    kwargs: dict[str, Any] = {"request_timeout_s": request_timeout_s}
    if CLIENT_RETRIES:
        kwargs["busy_timeout_s"] = busy_timeout_s
    return VisionClient(HOST, port, **kwargs)


class Retrier:
    """Sends INSPECT until it is answered, retrying BUSY (by the client or by hand) until
    ``until`` (``time.perf_counter()`` seconds), and counts the BUSY answers."""

    def __init__(self, seed: int) -> None:
        self._rng = random.Random(seed)
        self._busy = 0  # seen here: by hand, or the last BUSY a client gave up on

    async def inspect(
        self, client: Any, inspection: str, image: Any, *, until: float, **kwargs: Any
    ) -> Result | None:
        """The RESULT, or None when BUSY was still the answer at ``until``."""
        backoff = BACKOFF_S
        while True:
            try:
                result: Result = await client.inspect(inspection, image, **kwargs)
            except Busy:
                self._busy += 1
                if CLIENT_RETRIES or time.perf_counter() >= until:
                    return None
                await asyncio.sleep(backoff * self._rng.uniform(0.5, 1.0))
                backoff = min(2.0 * backoff, BACKOFF_MAX_S)
                continue
            return result

    def busy(self, clients: Iterable[VisionClient]) -> int:
        """BUSY answers so far: those seen here plus those the clients retried by themselves."""
        return self._busy + sum(int(getattr(c, "busy_retries", 0)) for c in clients)
