"""The operator desk: calls from robots waiting for a person's decision (SPEC §6.6).

A robot's skill that cannot go on posts an OPERATOR_CALL through the TCP front-end; the call
waits here, open, until a person answers it on the console's Operator page (the HTTP
front-end), its deadline passes, the robot goes away or the server stops. The desk knows
neither protocol: it holds plain records, images ready for a browser (PNG or JPEG bytes), and
one future per call that the front-end awaits.

Bounded: at most ``max_calls`` open calls and ``max_image_bytes`` bytes of their images, the
desk's own limit (a call may wait for minutes: its images must not hold the service's byte
budget that admits INSPECTs). A call beyond is refused with BUSY; a call whose images alone
exceed the limit with INVALID_ARGUMENT. Runs in the server's event loop only (no locks).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from protocol import (
    OPERATOR_CHOICES,
    BadImage,
    Busy,
    CellvisionError,
    DeadlineExceeded,
    ErrorCode,
    ImageEncoding,
    ImagePayload,
    InvalidArgument,
    ShuttingDown,
    array_from_payload,
)
from protocol.images import compressed_header

MAX_CALLS = 16
"""Open calls the desk holds by default (a cell has a few robots, each with one call)."""
MAX_IMAGE_BYTES = 32 * 1024 * 1024
"""Bytes of images (as stored: PNG or JPEG) the desk holds by default, all calls together."""
MAX_IMAGES_PER_CALL = 4
RECENT_KEPT = 20
"""Closed calls remembered, so that a late answer is told what became of its call."""

Outcome = Literal["answered", "expired", "withdrawn", "stopped"]


class CallClosed(LookupError):
    """An answer for a call that is not open (any more): ``closed`` says what became of it,
    None when the desk never had that id."""

    def __init__(self, call_id: int, closed: ClosedCall | None) -> None:
        self.call_id = call_id
        self.closed = closed
        if closed is None:
            why = "no such call"
        elif closed.outcome == "answered":
            why = f"already answered {closed.choice!r} by {closed.by}"
            if closed.reason:
                why += f" ({closed.reason})"
        else:
            why = {
                "expired": "its deadline passed: the robot stopped waiting",
                "withdrawn": "the robot withdrew it (it closed its connection)",
                "stopped": "the server stopped",
            }[closed.outcome]
        super().__init__(f"call {call_id} is not open: {why}")


@dataclass(frozen=True)
class DeskImage:
    """One image of a call as a browser shows it: ``mime`` ``image/png`` or ``image/jpeg``,
    its size in pixels and its protocol role (``color`` or ``overlay``)."""

    mime: str
    data: bytes
    width: int
    height: int
    role: str


MAX_REASON_CHARS = 500
"""The longest reason an answer may give (characters)."""


@dataclass(frozen=True)
class DeskAnswer:
    """A person's answer: ``choice``, who gave it (``by``: the name and where, for a log;
    ``operator``: the signed-in name alone, "" when unknown), when (``answered_at``, Unix
    seconds) and why (``reason``, "" when none was given)."""

    choice: str
    by: str
    answered_at: float
    reason: str = ""
    operator: str = ""


@dataclass
class OpenCall:
    """A call waiting for a person. Times: ``posted_at`` and ``expires_at`` Unix seconds
    (``expires_at`` None: no deadline)."""

    id: int
    peer: str
    message: str
    choices: tuple[str, ...]
    inspection: str
    skill: str
    images: tuple[DeskImage, ...]
    posted_at: float
    expires_at: float | None
    answer: asyncio.Future[DeskAnswer] = field(repr=False)
    result_id: int | None = None
    """The failed result's id in the server's result log (OPERATOR_CALL ``result_id``): its
    row is annotated with the answer."""

    @property
    def image_bytes(self) -> int:
        return sum(len(image.data) for image in self.images)


@dataclass(frozen=True)
class ClosedCall:
    """What became of a call: ``outcome`` and, when answered, the answer."""

    id: int
    peer: str
    message: str
    outcome: Outcome
    closed_at: float
    choice: str = ""
    by: str = ""
    reason: str = ""
    operator: str = ""
    result_id: int | None = None


def desk_image(payload: ImagePayload, *, max_pixels: int, where: str) -> DeskImage:
    """``payload`` as a browser shows it: PNG and JPEG as they came (their header checked
    against ``max_pixels`` without decoding them), raw gray8/bgr8 encoded as PNG. depth16 is
    BAD_IMAGE: a person is shown colour. CPU work for raw images: call it in a thread."""
    encoding = payload.encoding
    if encoding is ImageEncoding.DEPTH16:
        raise BadImage(f"{where}: a depth16 image cannot be shown to a person; send colour")
    if encoding in (ImageEncoding.PNG, ImageEncoding.JPEG):
        header = compressed_header(payload, max_pixels=max_pixels)
        mime = "image/png" if encoding is ImageEncoding.PNG else "image/jpeg"
        return DeskImage(mime, bytes(payload.data), header.width, header.height, payload.role)
    pixels = array_from_payload(payload, max_pixels=max_pixels)
    ok, png = cv2.imencode(".png", pixels)
    if not ok:  # pragma: no cover - OpenCV encodes any uint8 gray or BGR array
        raise BadImage(f"{where}: the image could not be encoded for the console")
    height, width = pixels.shape[:2]
    return DeskImage("image/png", np.asarray(png).tobytes(), width, height, payload.role)


class OperatorDesk:
    """The open operator calls of one server. See the module."""

    def __init__(
        self, *, max_calls: int = MAX_CALLS, max_image_bytes: int = MAX_IMAGE_BYTES
    ) -> None:
        if max_calls < 1 or max_image_bytes < 0:
            raise ValueError("max_calls must be >= 1 and max_image_bytes >= 0")
        self.max_calls = max_calls
        self.max_image_bytes = max_image_bytes
        self._open: dict[int, OpenCall] = {}
        self._recent: deque[ClosedCall] = deque(maxlen=RECENT_KEPT)
        self._ids = itertools.count(1)
        self.counts: dict[Outcome, int] = {
            "answered": 0,
            "expired": 0,
            "withdrawn": 0,
            "stopped": 0,
        }

    # ------------------------------------------------------------------ what is open

    def open_calls(self) -> list[OpenCall]:
        """The open calls, newest first."""
        return sorted(self._open.values(), key=lambda c: c.id, reverse=True)

    def recent(self) -> list[ClosedCall]:
        """The latest closed calls, newest first."""
        return list(reversed(self._recent))

    @property
    def image_bytes(self) -> int:
        """Bytes of images the open calls hold now."""
        return sum(call.image_bytes for call in self._open.values())

    # ------------------------------------------------------------------ robots

    def post(
        self,
        *,
        peer: str,
        message: str,
        choices: Sequence[str] = OPERATOR_CHOICES,
        inspection: str = "",
        skill: str = "",
        images: Sequence[DeskImage] = (),
        timeout_s: float | None = None,
        result_id: int | None = None,
    ) -> OpenCall:
        """Open a call; BUSY when the desk is full, INVALID_ARGUMENT when the call can never
        fit (too many images, or more bytes than the desk holds at all)."""
        if len(images) > MAX_IMAGES_PER_CALL:
            raise InvalidArgument(
                f"an operator call shows at most {MAX_IMAGES_PER_CALL} images, this one has "
                f"{len(images)}",
                details={"option": "images"},
            )
        size = sum(len(image.data) for image in images)
        if size > self.max_image_bytes:
            raise InvalidArgument(
                f"the call's images are {size} bytes, more than the {self.max_image_bytes} "
                "bytes the operator desk holds; send the overlay as PNG or JPEG, or fewer images",
                details={"size": size, "max_size": self.max_image_bytes},
            )
        if len(self._open) >= self.max_calls:
            raise Busy(
                f"the operator desk already holds {len(self._open)} open calls, its limit; "
                "answer or let some expire first"
            )
        if self.image_bytes + size > self.max_image_bytes:
            raise Busy(
                f"the operator desk holds {self.image_bytes} bytes of images; this call's "
                f"{size} more would pass its limit of {self.max_image_bytes}"
            )
        now = time.time()
        call = OpenCall(
            id=next(self._ids),
            peer=peer,
            message=message,
            choices=tuple(choices),
            inspection=inspection,
            skill=skill,
            images=tuple(images),
            posted_at=now,
            expires_at=None if timeout_s is None else now + timeout_s,
            answer=asyncio.get_running_loop().create_future(),
            result_id=result_id,
        )
        self._open[call.id] = call
        return call

    async def wait(
        self,
        call: OpenCall,
        *,
        timeout_s: float | None,
        stop_when: Mapping[asyncio.Event, CellvisionError] | None = None,
    ) -> DeskAnswer:
        """The answer to ``call``. DEADLINE_EXCEEDED after ``timeout_s``; when one of the
        events of ``stop_when`` is set first, its error (e.g. SHUTTING_DOWN). The call is
        closed on the way out, whatever happened (also when the waiter is cancelled)."""
        stops = dict(stop_when or {})
        watchers: dict[asyncio.Future[Any], CellvisionError] = {
            asyncio.ensure_future(event.wait()): exc for event, exc in stops.items()
        }
        waiting: set[asyncio.Future[Any]] = {call.answer, *watchers}
        outcome: Outcome = "withdrawn"
        try:
            done, _ = await asyncio.wait(
                waiting, timeout=timeout_s, return_when=asyncio.FIRST_COMPLETED
            )
            if call.answer.cancelled():  # the desk was closed: the server stops
                outcome = "stopped"
                raise ShuttingDown("the server is stopping; the operator call was not answered")
            if call.answer.done():  # answered, also when a stop crossed the answer
                outcome = "answered"
                return call.answer.result()
            for watcher in done:
                exc = watchers[watcher]
                outcome = "stopped" if exc.code is ErrorCode.SHUTTING_DOWN else "withdrawn"
                raise exc
            outcome = "expired"
            raise DeadlineExceeded(
                f"nobody answered the operator call within {timeout_s:g} s",
                details={"call": call.id},
            )
        finally:
            for watcher in watchers:
                watcher.cancel()
            self._close(call, outcome)

    # ------------------------------------------------------------------ people

    def find(self, call_id: int) -> OpenCall | None:
        """The open call ``call_id``, or None."""
        return self._open.get(call_id)

    def answer(
        self, call_id: int, choice: str, *, by: str, reason: str = "", operator: str = ""
    ) -> DeskAnswer:
        """Answer an open call; CallClosed when it is not open, INVALID_ARGUMENT when
        ``choice`` is not one the call offers or ``reason`` is longer than MAX_REASON_CHARS.
        (Which choices need a reason is the console's rule, not the desk's.)"""
        call = self._open.get(call_id)
        if call is None or call.answer.done():
            raise CallClosed(call_id, self._closed(call_id))
        if choice not in call.choices:
            raise InvalidArgument(
                f"call {call_id} offers {', '.join(call.choices)}; {choice!r} is not one of them",
                details={"option": "choice"},
            )
        if len(reason) > MAX_REASON_CHARS:
            raise InvalidArgument(
                f"the reason has {len(reason)} characters, at most {MAX_REASON_CHARS}",
                details={"option": "reason"},
            )
        answer = DeskAnswer(choice, by, time.time(), reason, operator)
        call.answer.set_result(answer)
        return answer

    def close(self) -> None:
        """The server stops: every open call ends (its waiter answers SHUTTING_DOWN)."""
        for call in list(self._open.values()):
            if not call.answer.done():
                call.answer.cancel()
            self._close(call, "stopped")

    # ------------------------------------------------------------------ bookkeeping

    def _close(self, call: OpenCall, outcome: Outcome) -> None:
        if self._open.pop(call.id, None) is None:
            return
        answer: DeskAnswer | None = None
        if call.answer.done() and not call.answer.cancelled():
            answer = call.answer.result()
            outcome = "answered"
        elif not call.answer.done():
            call.answer.cancel()
        self.counts[outcome] += 1
        self._recent.append(
            ClosedCall(
                call.id,
                call.peer,
                call.message,
                outcome,
                time.time(),
                answer.choice if answer else "",
                answer.by if answer else "",
                answer.reason if answer else "",
                answer.operator if answer else "",
                call.result_id,
            )
        )

    def _closed(self, call_id: int) -> ClosedCall | None:
        return next((c for c in self._recent if c.id == call_id), None)


def call_json(call: OpenCall, now: float, image_url: str) -> dict[str, Any]:
    """An open call as the console's API shows it (docs/console.md); ``image_url`` is a
    format string with ``{call}`` and ``{index}``."""
    return {
        "id": call.id,
        "peer": call.peer,
        "message": call.message,
        "choices": list(call.choices),
        "inspection": call.inspection or None,
        "skill": call.skill or None,
        "posted_at": call.posted_at,
        "waiting_s": max(now - call.posted_at, 0.0),
        "expires_at": call.expires_at,
        "result_id": call.result_id,
        "images": [
            {
                "url": image_url.format(call=call.id, index=i),
                "width": image.width,
                "height": image.height,
                "role": image.role,
            }
            for i, image in enumerate(call.images)
        ],
    }


def closed_json(call: ClosedCall) -> dict[str, Any]:
    return {
        "id": call.id,
        "peer": call.peer,
        "message": call.message,
        "outcome": call.outcome,
        "closed_at": call.closed_at,
        "choice": call.choice or None,
        "by": call.by or None,
        "operator": call.operator or None,
        "reason": call.reason or None,
        "result_id": call.result_id,
    }


__all__ = [
    "MAX_CALLS",
    "MAX_IMAGE_BYTES",
    "MAX_REASON_CHARS",
    "CallClosed",
    "ClosedCall",
    "DeskAnswer",
    "DeskImage",
    "OpenCall",
    "OperatorDesk",
    "call_json",
    "closed_json",
    "desk_image",
]
