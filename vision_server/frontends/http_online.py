"""The console's online API: the running counts, verdict strips and last graphics of every
inspection, by camera (docs/console.md, "Online view"), from the in-memory
:class:`~.online_board.OnlineBoard` (never the result log).

- ``GET /api/online`` (operator): the board; with ``If-None-Match`` equal to its ``ETag``, 304
  with no body while nothing changed, so that a page polling an idle cell costs nothing.
- ``POST /api/online/reset`` (integrator): zero the counts and strips, of one inspection with
  ``{"inspection": NAME}``, else of all.
"""

from __future__ import annotations

import asyncio
import json
from typing import Any

from aiohttp import web

from protocol import InvalidArgument, UnknownInspection

from .online_board import OnlineBoard

RESET_MAX_BYTES = 4096
"""The largest reset body: an inspection's name, not an upload."""


class OnlineRoutes:
    """The online API over ``board``; ``timeout_s``: how long a reset's body may take."""

    def __init__(self, board: OnlineBoard, *, timeout_s: float = 10.0) -> None:
        self.board = board
        self.timeout_s = timeout_s

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/online", self.online)
        router.add_post("/api/online/reset", self.reset)

    async def online(self, request: web.Request) -> web.Response:
        board = self.board
        headers = {"Cache-Control": "no-cache"}
        tag = board.etag()
        if request.headers.get("If-None-Match") == tag:
            return web.Response(status=304, headers={**headers, "ETag": tag})
        # Drawing a result that ran with request options rebuilds its inspection (a template
        # read from disk): in a worker, not on the loop every connection shares.
        tag, snapshot = await asyncio.to_thread(board.snapshot)
        return web.json_response(snapshot, headers={**headers, "ETag": tag})

    async def reset(self, request: web.Request) -> web.Response:
        body = await self._body(request)
        name = body.get("inspection")
        if name is not None and not isinstance(name, str):
            raise InvalidArgument('the body must be {} or {"inspection": "NAME"}')
        if name is not None and name not in self.board.service.catalog.inspections:
            raise UnknownInspection(f"no inspection named {name!r}")
        names = self.board.reset(name)
        return web.json_response({"reset": names, "sequence": self.board.sequence})

    async def _body(self, request: web.Request) -> dict[str, Any]:
        """The body as a JSON object (empty: ``{}``), at most :data:`RESET_MAX_BYTES`."""
        declared = request.content_length
        if declared is not None and declared > RESET_MAX_BYTES:
            raise web.HTTPRequestEntityTooLarge(max_size=RESET_MAX_BYTES, actual_size=declared)
        raw = b""
        try:
            async with asyncio.timeout(self.timeout_s):
                while len(raw) <= RESET_MAX_BYTES:
                    more = await request.content.read(RESET_MAX_BYTES + 1 - len(raw))
                    if not more:
                        break
                    raw += more
        except TimeoutError:
            raise InvalidArgument(f"the body did not arrive within {self.timeout_s:g} s") from None
        if len(raw) > RESET_MAX_BYTES:
            raise web.HTTPRequestEntityTooLarge(max_size=RESET_MAX_BYTES, actual_size=len(raw))
        if not raw.strip():
            return {}
        try:
            body = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise InvalidArgument(f"the body is not JSON: {exc}") from None
        if not isinstance(body, dict):
            raise InvalidArgument('the body must be {} or {"inspection": "NAME"}')
        unknown = sorted(set(body) - {"inspection"})
        if unknown:
            raise InvalidArgument(f"unknown key(s) in the body: {', '.join(unknown)}")
        return body


__all__ = ["OnlineRoutes"]
