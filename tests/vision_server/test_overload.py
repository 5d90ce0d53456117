"""Overload over real sockets: many clients, each keeping several requests in flight, against
a server with one worker and no queue. Every request is answered exactly once (a RESULT, or a
BUSY carrying retry_after_ms), whether the server waits unread (backpressure) or refuses at
once; nothing is lost. No timing assertions: counts only."""

from __future__ import annotations

import asyncio
from collections import Counter

import numpy as np
import pytest
from loopback import client_for, run

from protocol import Busy
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import InspectionRecord, builtin_catalog

GRAY = np.full((480, 640), 200, np.uint8)
CLIENTS = 8
PIPELINE = 4
ROUNDS = 3


@pytest.mark.parametrize("admission_wait_s", [30.0, 0.0], ids=["backpressure", "busy-at-once"])
def test_every_request_is_answered_exactly_once_under_overload(admission_wait_s: float) -> None:
    async def body() -> None:
        settings = ServerSettings(
            port=0, workers=1, queue_depth=0, fast_workers=0, admission_wait_s=admission_wait_s
        )
        answered_by_server: Counter[tuple[str, int]] = Counter()
        retry_hints: list[int] = []
        outcomes: Counter[str] = Counter()
        async with VisionServer(builtin_catalog(), settings) as server:

            def seen(record: InspectionRecord) -> None:
                request = record.request
                answered_by_server[(request.peer, request.request_id)] += 1

            server.service.subscribe(seen)
            clients = [client_for(server, request_timeout_s=60.0) for _ in range(CLIENTS)]
            await asyncio.gather(*(c.connect() for c in clients))

            async def one(client: object) -> None:
                assert hasattr(client, "inspect")
                for _ in range(ROUNDS):
                    try:
                        result = await client.inspect("brightness", GRAY)
                    except Busy as busy:
                        retry_hints.append(busy.details["retry_after_ms"])
                        outcomes["busy"] += 1
                    else:
                        assert result.passed
                        outcomes["result"] += 1

            await asyncio.gather(*(one(c) for c in clients for _ in range(PIPELINE)))
            await asyncio.gather(*(c.close() for c in clients))
        total = CLIENTS * PIPELINE * ROUNDS
        assert outcomes["result"] + outcomes["busy"] == total  # none lost
        assert outcomes["result"] == len(answered_by_server)  # each RESULT ran once
        assert set(answered_by_server.values()) == {1}
        assert all(hint >= 1 for hint in retry_hints)
        if admission_wait_s > 0:
            assert outcomes["busy"] == 0  # the server waited instead of refusing
        else:
            # 32 requests sent at once to one slot: refusals are certain, and each was counted.
            assert outcomes["busy"] > 0

    run(body(), timeout_s=120.0)
