"""A person with the console open, without a browser: an HTTP client (aiohttp) in its own
process that asks the server what the page's JavaScript asks, at the page's rhythm.

What the page polls (vision_server/console/static/console.js and js/*.js); each poller starts a
round every interval, or at once when the previous round took longer (js/poll.js: never two at
once):

- every page: the status pill, ``GET /api/server`` every 3 s; the Operator badge,
  ``GET /api/operator/calls`` every 3 s;
- Cameras (the live view): the list, ``GET /api/cameras`` every 2 s; a card per camera
  fetching ``frame.jpg`` every ``1 / min(view_fps or fps or 5, 15)`` s for a server camera and
  every 1 s for a request camera (js/cameras.js); the online view's board, ``GET /api/online``
  every 1 s with ``If-None-Match`` (js/online.js: a 304 without a body while nothing changed);
- Server: ``GET /api/server`` every 2 s (js/server.js).

The viewer takes its page from a control queue (``"cameras"``, ``"server"``, ``"closed"``: no
console open, or ``"stop"``). On each command it puts the :class:`Segment` of the page it
leaves on its output queue, then ``("ready", page)`` once the new page has been answered (for
the Cameras page: the live camera's first frame). Frames of ``camera`` are recorded with
their capture time (``X-Frame-Timestamp``) and arrival time, both Unix seconds.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass, field
from typing import Any

EVERY_PAGE: tuple[tuple[str, float], ...] = (("api/server", 3.0), ("api/operator/calls", 3.0))
ONLINE_INTERVAL_S = 1.0
"""js/online.js's ``ONLINE_POLL_MS``: the Cameras page asks for the online board once a second."""
MAX_VIEW_FPS = 15.0
"""js/cameras.js: the most frames per second one card asks for."""
REQUEST_CAMERA_FPS = 1.0
DEFAULT_FPS = 5.0
FRAME_TIMESTAMP_HEADER = "X-Frame-Timestamp"


@dataclass
class Segment:
    """What the viewer did while one page was open."""

    page: str
    started: float = field(default_factory=time.time)
    ended: float = float("nan")
    requests: int = 0
    errors: int = 0
    bytes: int = 0
    cpu_s: float = 0.0
    """The viewer process's own CPU time over the segment (it shares the machine)."""
    frames: list[tuple[float, float]] = field(default_factory=list)
    """(captured, received) Unix seconds of each frame.jpg of the watched camera."""
    camera_fps: list[float] = field(default_factory=list)
    """The watched camera's frame rate as /api/cameras reported it (the server measures it)."""
    first_error: str = ""
    cards: int = 0
    """Camera cards on the page (a frame.jpg poller each)."""


async def _rest_of(interval_s: float, started: float) -> None:
    """Wait out what is left of a round that began at ``started`` (monotonic seconds)."""
    await asyncio.sleep(max(0.0, interval_s - (time.monotonic() - started)))


def frame_interval_s(camera: dict[str, Any]) -> float:
    """js/cameras.js's ``intervalMs`` for one card, in seconds."""
    if camera.get("source") == "request":
        rate = REQUEST_CAMERA_FPS
    else:
        rate = min(MAX_VIEW_FPS, camera.get("view_fps") or camera.get("fps") or DEFAULT_FPS)
    return max(1.0 / max(rate, 0.1), 1.0 / MAX_VIEW_FPS)


class _Page:
    def __init__(self, session: Any, base: str, segment: Segment, camera: str) -> None:
        self.session, self.base, self.segment, self.camera = session, base, segment, camera
        self.ready = asyncio.Event()

    async def get(self, path: str) -> tuple[bytes, Any]:
        """One GET; the body and the response (None when it failed)."""
        try:
            async with self.session.get(self.base + path) as response:
                body = await response.read()
                self.segment.requests += 1
                self.segment.bytes += len(body)
                if response.status >= 400 and response.status != 404:
                    self._error(f"GET /{path}: HTTP {response.status}")
                return body, response
        except Exception as exc:  # noqa: BLE001 - counted; the page keeps polling
            self.segment.requests += 1
            self._error(f"GET /{path}: {type(exc).__name__}: {exc}")
            return b"", None

    def _error(self, text: str) -> None:
        self.segment.errors += 1
        self.segment.first_error = self.segment.first_error or text

    async def poll(self, path: str, interval_s: float, *, ready: bool = False) -> None:
        while True:
            started = time.monotonic()
            _, response = await self.get(path)
            if ready and response is not None and response.status == 200:
                self.ready.set()
            await _rest_of(interval_s, started)

    async def cameras(self) -> list[dict[str, Any]]:
        body, response = await self.get("api/cameras")
        if response is None or response.status != 200:
            return []
        listing: list[dict[str, Any]] = json.loads(body)["cameras"]
        for info in listing:
            if info["name"] == self.camera and isinstance(info.get("fps"), (int, float)):
                self.segment.camera_fps.append(float(info["fps"]))
        return listing

    async def list_cameras(self) -> None:
        while True:
            await asyncio.sleep(2.0)  # the first listing is the one the page opened with
            await self.cameras()

    async def online(self) -> None:
        """The online view's board, asked with the ETag of the one the page has."""
        tag: str | None = None
        while True:
            started = time.monotonic()
            headers = {"If-None-Match": tag} if tag else {}
            try:
                async with self.session.get(self.base + "api/online", headers=headers) as reply:
                    body = await reply.read()
                    self.segment.requests += 1
                    self.segment.bytes += len(body)
                    if reply.status == 200:
                        tag = reply.headers.get("ETag")
                    elif reply.status != 304:
                        self._error(f"GET /api/online: HTTP {reply.status}")
            except Exception as exc:  # noqa: BLE001 - counted; the page keeps polling
                self.segment.requests += 1
                self._error(f"GET /api/online: {type(exc).__name__}: {exc}")
            await _rest_of(ONLINE_INTERVAL_S, started)

    async def card(self, info: dict[str, Any]) -> None:
        name = info["name"]
        path = f"api/cameras/{name}/frame.jpg"
        interval_s = frame_interval_s(info)
        tick = 0
        while True:
            tick += 1
            started = time.monotonic()
            _, response = await self.get(f"{path}?t={tick}")
            received = time.time()
            if name == self.camera and response is not None and response.status == 200:
                captured = float(response.headers.get(FRAME_TIMESTAMP_HEADER, "nan"))
                self.segment.frames.append((captured, received))
                self.ready.set()
            await _rest_of(interval_s, started)

    async def run(self) -> None:
        async with asyncio.TaskGroup() as group:
            for path, interval_s in EVERY_PAGE:
                group.create_task(self.poll(path, interval_s))
            if self.segment.page == "server":
                group.create_task(self.poll("api/server", 2.0, ready=True))
            elif self.segment.page == "cameras":
                listing = await self.cameras()
                group.create_task(self.list_cameras())
                group.create_task(self.online())
                self.segment.cards = len(listing)
                for info in listing:
                    group.create_task(self.card(info))


async def _view(base: str, camera: str, control: Any, out: Any) -> None:
    import aiohttp

    timeout = aiohttp.ClientTimeout(total=60.0)
    async with aiohttp.ClientSession(timeout=timeout) as session:
        segment = Segment("closed")
        cpu0 = time.process_time()
        task: asyncio.Task[None] | None = None
        while True:
            command = await asyncio.to_thread(control.get)
            if task is not None:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
                task = None
            segment.ended = time.time()
            segment.cpu_s = time.process_time() - cpu0
            out.put(("segment", segment))
            if command == "stop":
                return
            segment, cpu0 = Segment(command), time.process_time()
            if command != "closed":
                page = _Page(session, base, segment, camera)
                task = asyncio.create_task(page.run())
                await page.ready.wait()
            out.put(("ready", command))


def main(base: str, camera: str, control: Any, out: Any) -> None:
    """The viewer process's body (multiprocessing, spawn): ``base`` is the console's URL
    (ending in ``/``), ``camera`` the camera whose frames are recorded."""
    asyncio.run(_view(base, camera, control, out))


__all__ = ["Segment", "frame_interval_s", "main"]
