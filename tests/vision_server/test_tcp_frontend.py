"""The TCP front-end as a thin adapter: what it hands the service for a protocol request (the
arrival stamp, the absolute deadline, the images as a loader), and its one error table."""

from __future__ import annotations

import asyncio
import os
import signal
import threading
import time
from typing import Any

import numpy as np
import pytest
from loopback import client_for, run, wait_until

from protocol import Busy, Error, ErrorCode, payload_from_array
from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ServerSettings, TcpSettings
from vision_server.frontends.tcp import TcpFrontend, error_frame
from vision_server.service import ImageNeeds, InspectionService, InspectReply, InspectRequest
from vision_server.service.builtin import MeanIntensityPresence, builtin_catalog

GRAY = np.full((48, 64), 200, np.uint8)


class Recording(InspectionService):
    """A service that records the requests it is given and answers each at once."""

    def __init__(self) -> None:
        super().__init__(builtin_catalog())
        self.requests: list[InspectRequest] = []

    async def inspect(self, request: InspectRequest, *, admission: Any = None) -> InspectReply:
        self.requests.append(request)
        return InspectReply(request.inspection, "tool", True, {}, 0.0, 0.0, "hash")


def test_the_deadline_is_stamped_when_the_whole_frame_has_arrived() -> None:
    """SPEC §6.1: the deadline counts from the moment the whole request frame is received;
    the service gets it as an absolute time, not a budget that starts at pool submission."""
    service = Recording()

    async def body() -> None:
        frontend = TcpFrontend(service, TcpSettings(port=0))
        await frontend.start()
        try:
            async with client_for(frontend) as client:  # type: ignore[arg-type]
                sent = time.monotonic()
                await client.inspect("brightness", GRAY, deadline_s=1.5, overlay=True)
                answered = time.monotonic()
        finally:
            await frontend.stop()
            service.close()
        [request] = service.requests
        assert sent <= request.arrived <= answered
        assert request.deadline is not None
        assert request.deadline - request.arrived == pytest.approx(1.5)
        assert request.overlay == ".png"
        assert request.peer.startswith("127.0.0.1:")
        # The images go to the service undecoded: it decodes them in a worker.
        assert callable(request.images)
        loaded = request.images(ImageNeeds("brightness", False, 10**6))
        assert np.array_equal(loaded.color, GRAY)

    run(body())


def test_the_error_table_gives_the_code_to_the_request_that_failed() -> None:
    frame = error_frame(Busy("all 2 inspection slots are taken"), 42)
    assert frame == Error(42, int(ErrorCode.BUSY), "all 2 inspection slots are taken", False, {})
    assert payload_from_array(GRAY)  # the payload codec the front-end uses is importable


def test_sighup_reloads_in_a_thread_while_the_connections_are_served() -> None:
    """SIGHUP went to the reloader on the event loop (a camera's open or close could stall
    every connection); now it takes the service's path, in a thread, as RELOAD does."""
    threads: list[threading.Thread] = []
    entered, release = threading.Event(), threading.Event()
    fresh = Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("second", "tool", 0.0, 255.0)],
    )

    def reloader() -> Catalog:
        threads.append(threading.current_thread())
        entered.set()
        release.wait(20.0)
        return fresh

    async def body() -> None:
        async with App(builtin_catalog(), ServerSettings(port=0), reloader=reloader) as app:
            app.install_signals(asyncio.Event(), reload=True)
            os.kill(os.getpid(), signal.SIGHUP)
            assert await asyncio.to_thread(entered.wait, 10.0)
            async with client_for(app) as client:  # served while the reload is under way
                await client.ping()
                release.set()
                await wait_until(lambda: app.catalog is fresh, "the new catalog serves")
                assert {i["name"] for i in await client.list_inspections()} == {"second"}

    run(body())
    assert threads
    assert threading.main_thread() not in threads
