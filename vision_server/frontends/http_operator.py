"""The console's operator API: the open operator calls and their answers (docs/console.md,
"Operator"). Routes added to the console's application, behind its sign-in like every
``/api/*`` path; the calls themselves come from robots over the TCP protocol (SPEC §6.6).

- ``GET /api/operator/calls``: the open calls, newest first, and the latest closed ones.
- ``GET /api/operator/calls/{id}/images/{index}``: one image of an open call (PNG or JPEG).
- ``POST /api/operator/calls/{id}/answer`` with ``{"choice": "retry"}``: answer a call; 409 when
  it is not open any more (answered by someone else, expired, withdrawn), saying what became of it.
"""

from __future__ import annotations

import time

from aiohttp import web

from protocol import InvalidArgument

from ..service import CallClosed, OperatorDesk, call_json, closed_json

IMAGE_URL = "/api/operator/calls/{call}/images/{index}"


class OperatorRoutes:
    """The operator API over ``desk``; ``who(request)`` names the person's browser for the
    robot's log (the answer's ``by``)."""

    def __init__(self, desk: OperatorDesk) -> None:
        self.desk = desk

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/operator/calls", self.calls)
        router.add_get(r"/api/operator/calls/{id:\d{1,9}}/images/{index:\d{1,2}}", self.image)
        router.add_post(r"/api/operator/calls/{id:\d{1,9}}/answer", self.answer)

    async def calls(self, request: web.Request) -> web.Response:
        desk = self.desk
        now = time.time()
        return web.json_response(
            {
                "now": now,
                "calls": [call_json(c, now, IMAGE_URL) for c in desk.open_calls()],
                "recent": [closed_json(c) for c in desk.recent()],
                "limits": {"max_calls": desk.max_calls, "max_image_bytes": desk.max_image_bytes},
            },
            headers={"Cache-Control": "no-store"},
        )

    async def image(self, request: web.Request) -> web.Response:
        call_id, index = int(request.match_info["id"]), int(request.match_info["index"])
        call = next((c for c in self.desk.open_calls() if c.id == call_id), None)
        if call is None or index >= len(call.images):
            raise web.HTTPNotFound(reason=f"call {call_id} has no open image {index}")
        image = call.images[index]
        return web.Response(
            body=image.data, content_type=image.mime, headers={"Cache-Control": "no-store"}
        )

    async def answer(self, request: web.Request) -> web.Response:
        call_id = int(request.match_info["id"])
        try:
            body = await request.json()
        except ValueError as exc:
            raise InvalidArgument(f"the body is not JSON: {exc}") from None
        choice = body.get("choice") if isinstance(body, dict) else None
        if not isinstance(choice, str):
            raise InvalidArgument('the body must be {"choice": "retry" | "continue" | "abort"}')
        try:
            answer = self.desk.answer(call_id, choice, by=_who(request))
        except CallClosed as exc:
            gone = exc.closed
            return web.json_response(
                {
                    "error": {"code": "CALL_CLOSED", "message": str(exc)},
                    "call": None if gone is None else closed_json(gone),
                },
                status=404 if gone is None else 409,
            )
        return web.json_response(
            {
                "call": call_id,
                "choice": answer.choice,
                "by": answer.by,
                "answered_at": answer.answered_at,
            }
        )


def _who(request: web.Request) -> str:
    peer = request.transport.get_extra_info("peername") if request.transport else None
    return "console " + (f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "unknown")


__all__ = ["OperatorRoutes"]
