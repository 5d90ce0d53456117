"""The console's operator API: the open operator calls and their answers (docs/console.md,
"Operator"). Routes added to the console's application, behind its sign-in like every
``/api/*`` path; the calls themselves come from robots over the TCP protocol (SPEC §6.6).

- ``GET /api/operator/calls``: the open calls, newest first, and the latest closed ones.
- ``GET /api/operator/calls/{id}/images/{index}``: one image of an open call (PNG or JPEG).
- ``POST /api/operator/calls/{id}/answer`` with ``{"choice": "continue", "reason": "..."}``:
  answer a call as the signed-in person; 409 when it is not open any more (answered by someone
  else, expired, withdrawn), saying what became of it. The choices of ``console:
  operator_reason_for`` need a reason (400 without one). The answer goes to the robot with the
  person's name and reason, into the server's log, and onto the failed result's row in the
  result log when the call named one (``result_id``).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from aiohttp import web

from protocol import InvalidArgument

from ..config import ConsoleSettings
from ..results import ResultLogError
from ..service import (
    MAX_REASON_CHARS,
    CallClosed,
    InspectionService,
    OperatorDesk,
    call_json,
    closed_json,
)
from .http_common import HttpError, audit, bounded_json

ANSWER_MAX_BYTES = 4096
"""The largest answer body: a choice and a reason of at most 500 characters."""
IMAGE_URL = "/api/operator/calls/{call}/images/{index}"
log = logging.getLogger("vision_server")


class OperatorRoutes:
    """The operator API over ``desk``; ``who(request)`` names the signed-in person (their
    name, or their role without one) for the robot's log, the server's and the result log."""

    def __init__(
        self,
        desk: OperatorDesk,
        who: Callable[[web.Request], str] | None = None,
        settings: ConsoleSettings | None = None,
        service: InspectionService | None = None,
    ) -> None:
        self.desk = desk
        self.who = who or (lambda request: "console")
        self.settings = settings or ConsoleSettings()
        self.service = service

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
                "answers": {
                    "reason_for": list(self.settings.operator_reason_for),
                    "reasons": list(self.settings.operator_reasons),
                    "max_reason_chars": MAX_REASON_CHARS,
                },
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
            body = await bounded_json(request, ANSWER_MAX_BYTES, self.settings.request_timeout_s)
        except HttpError as exc:
            if exc.status != 400:  # too large (413), too slow (408): as they are
                raise
            raise InvalidArgument(exc.message) from None  # the answer's documented code
        choice = body.get("choice") if isinstance(body, dict) else None
        if not isinstance(choice, str):
            raise InvalidArgument(
                'the body must be {"choice": "retry" | "continue" | "abort", "reason": "..."}'
            )
        reason = _reason(body.get("reason"))
        call = self.desk.find(call_id)
        needs_reason = choice in self.settings.operator_reason_for
        if call is not None and choice in call.choices and needs_reason and not reason:
            raise InvalidArgument(
                f"answering {choice!r} needs a reason (console: operator_reason_for): "
                'send {"choice": "' + choice + '", "reason": "..."}',
                details={"option": "reason"},
            )
        name = self.who(request)
        by = f"{name} ({_where(request)})" if name != "console" else _where(request)
        try:
            answer = self.desk.answer(call_id, choice, by=by, reason=reason, operator=name)
        except CallClosed as exc:
            gone = exc.closed
            return web.json_response(
                {
                    "error": {"code": "CALL_CLOSED", "message": str(exc)},
                    "call": None if gone is None else closed_json(gone),
                },
                status=404 if gone is None else 409,
            )
        audit.info(
            "operator call %d (%s, %s) answered %r by %s%s",
            call_id,
            call.skill if call is not None else "",
            call.inspection if call is not None else "",
            answer.choice,
            answer.by,
            f": {answer.reason}" if answer.reason else "",
        )
        result_id = call.result_id if call is not None else None
        annotated = await self._annotate(result_id, name, answer.choice, reason, answer.answered_at)
        return web.json_response(
            {
                "call": call_id,
                "choice": answer.choice,
                "by": answer.by,
                "operator": answer.operator,
                "reason": answer.reason or None,
                "answered_at": answer.answered_at,
                "result_id": result_id,
                "annotated": annotated,
            }
        )

    async def _annotate(
        self, result_id: int | None, name: str, choice: str, reason: str, at: float
    ) -> bool:
        """Write the answer onto the failed result's row; False (logged) when it cannot be."""
        results = self.service.results if self.service is not None else None
        if result_id is None or results is None:
            return False
        try:
            done = await asyncio.to_thread(
                results.annotate, result_id, name=name, choice=choice, reason=reason, at=at
            )
        except ResultLogError as exc:
            log.warning("the answer to result %d is not in the result log: %s", result_id, exc)
            return False
        if not done:
            log.warning("the answer to result %d is not in the result log (no such row)", result_id)
        return bool(done)


def _where(request: web.Request) -> str:
    peer = request.transport.get_extra_info("peername") if request.transport else None
    return "console " + (f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "unknown")


def _reason(value: object) -> str:
    """An answer's reason: absent, null or a string of at most MAX_REASON_CHARS characters on
    one line (it goes into logs: no control characters); "" when none."""
    if value is None:
        return ""
    if not isinstance(value, str):
        raise InvalidArgument("reason must be a string", details={"option": "reason"})
    reason = value.strip()
    if len(reason) > MAX_REASON_CHARS:
        raise InvalidArgument(
            f"the reason has {len(reason)} characters, at most {MAX_REASON_CHARS}",
            details={"option": "reason"},
        )
    if any(ord(c) < 32 or ord(c) == 127 for c in reason):
        raise InvalidArgument(
            "the reason must be one line without control characters",
            details={"option": "reason"},
        )
    return reason


__all__ = ["OperatorRoutes"]
