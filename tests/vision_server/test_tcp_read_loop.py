"""The TCP session's read loop waits on futures that live until they fire, not on tasks made
and cancelled every turn: a request costs the server one task (the request's own), a PING
none. Counted with a task factory, not timed (bench section 1 measured the old loop at eight
tasks and about 20 event-loop turns per INSPECT)."""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine
from typing import Any

import numpy as np
from loopback import client_for, run

from vision_server import ServerSettings, VisionServer
from vision_server.builtin import builtin_catalog

IMAGE = np.full((480, 640), 120, np.uint8)
REQUESTS = 20


def _server_side(made: list[str]) -> list[str]:
    return [name for name in made if "/vision_server/" in name or "/wireio/" in name]


def test_an_inspect_costs_one_server_task_and_a_ping_none() -> None:
    made: list[str] = []

    def counting(
        loop: asyncio.AbstractEventLoop, coro: Coroutine[Any, Any, Any], **kwargs: Any
    ) -> asyncio.Task[Any]:
        made.append(coro.cr_code.co_filename)
        return asyncio.Task(coro, loop=loop, **kwargs)

    async def body() -> tuple[int, int]:
        server = VisionServer(builtin_catalog(), ServerSettings(port=0))
        await server.start()
        client = client_for(server)
        try:
            await client.connect()
            await client.inspect("brightness", IMAGE)  # the connection's own tasks are made
            loop = asyncio.get_running_loop()
            loop.set_task_factory(counting)
            for _ in range(REQUESTS):
                await client.ping()
            pings = len(_server_side(made))
            made.clear()
            for _ in range(REQUESTS):
                result = await client.inspect("brightness", IMAGE)
                assert result.passed
            inspects = len(_server_side(made))
            loop.set_task_factory(None)
        finally:
            await client.close()
            await server.stop()
        return pings, inspects

    pings, inspects = run(body())
    assert pings == 0
    assert inspects == REQUESTS
