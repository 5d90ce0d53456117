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
from typing import Any

from aiohttp import web

from protocol import InvalidArgument, UnknownInspection

from .http_common import HttpError, json_object, read_at_most
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
        raw = await read_at_most(request, RESET_MAX_BYTES, self.timeout_s)
        try:
            body = json_object(raw if raw.strip() else b"{}", "the body")
        except HttpError as exc:
            raise InvalidArgument(exc.message) from None  # the reset's documented code
        unknown = sorted(set(body) - {"inspection"})
        if unknown:
            raise InvalidArgument(f"unknown key(s) in the body: {', '.join(unknown)}")
        return body


__all__ = ["OnlineRoutes"]
