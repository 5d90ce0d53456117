"""What every handler of the web console shares: its one error type and error body, the
service's error codes as HTTP statuses, the bounded reading of a request's body and query, and
what a route module may ask of the console (:class:`Console`).

Every route module (:mod:`.http`, :mod:`.http_build`, :mod:`.http_history`, :mod:`.http_impact`,
...) raises :class:`HttpError` (or lets a service error through); the console's error
middleware renders both, so that every error on every path has one shape
(docs/console.md, "Errors") and no module writes its own.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from aiohttp import web

from protocol import CellvisionError, ErrorCode, InvalidArgument

from ..config import ConsoleSettings
from ..results import MAX_ROW_ID, ResultStore
from ..service import ImageNeeds, Images

HTTP_STATUS: dict[ErrorCode, int] = {
    ErrorCode.NOT_AUTHENTICATED: 401,
    ErrorCode.UNKNOWN_INSPECTION: 404,
    ErrorCode.UNKNOWN_CAMERA: 404,
    ErrorCode.BAD_IMAGE: 400,
    ErrorCode.IMAGE_TOO_LARGE: 413,
    ErrorCode.INVALID_ARGUMENT: 400,
    ErrorCode.BAD_METADATA: 400,
    ErrorCode.FRAME_TOO_LARGE: 413,
    ErrorCode.CONFIG_INVALID: 422,
    ErrorCode.INSPECTION_FAILED: 422,
    ErrorCode.CAMERA_UNAVAILABLE: 503,
    ErrorCode.BUSY: 503,
    ErrorCode.SHUTTING_DOWN: 503,
    ErrorCode.DEADLINE_EXCEEDED: 504,
    ErrorCode.INTERNAL_ERROR: 500,
}
"""The one table from the service's error codes to HTTP statuses (others: 400)."""

audit = logging.getLogger("vision_server.audit")
"""What people did through the console (sign-ins of named users, saves, reverts, trained
templates, operators' answers), with who and why: ``vision-server serve`` logs it at INFO
whatever its verbosity, so that the server's log holds it (docs/console.md)."""

RETRY_AFTER_S = 1
"""``Retry-After`` of a BUSY answer, seconds (unless the error gives its own)."""


class HttpError(Exception):
    """An error of the console's own (not the service's): HTTP ``status``, ``code`` and
    ``message``; ``details`` go into the error body beside them (e.g. ``key``, the key at
    fault); ``retry_after`` (seconds) is sent as ``Retry-After``."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        details: Mapping[str, Any] | None = None,
        retry_after: int | None = None,
    ) -> None:
        super().__init__(message)
        self.status = status
        self.code = code
        self.message = message
        self.details = dict(details or {})
        self.retry_after = retry_after


def error_response(
    status: int,
    code: str,
    message: str,
    *,
    details: Mapping[str, Any] | None = None,
    retry_after: int | None = None,
) -> web.Response:
    """The console's error body ``{"error": {"code", "message", ...details}}``."""
    error = {**(details or {}), "code": code, "message": message}
    response = web.json_response({"error": error}, status=status)
    if retry_after is None and code == "BUSY":
        retry_after = RETRY_AFTER_S
    if retry_after is not None:
        response.headers["Retry-After"] = str(retry_after)
    return response


def http_error_response(exc: HttpError) -> web.Response:
    return error_response(
        exc.status, exc.code, exc.message, details=exc.details, retry_after=exc.retry_after
    )


def service_error(exc: CellvisionError) -> web.Response:
    """The HTTP form of a service error (see :data:`HTTP_STATUS`)."""
    return error_response(HTTP_STATUS.get(exc.code, 400), exc.code.name, exc.message)


# ----------------------------------------------------------------------------- request bodies


async def read_at_most(request: web.Request, limit: int, timeout_s: float | None = None) -> bytes:
    """The body, 413 beyond ``limit`` bytes (declared or sent), read no further; 408 when it
    has not all arrived within ``timeout_s`` (what a signed-out request may make the server
    hold: no more, and no longer)."""
    declared = request.content_length
    if declared is not None and declared > limit:
        raise HttpError(413, "TOO_LARGE", f"the body has {declared} bytes, limit {limit}")
    raw = b""
    try:
        async with asyncio.timeout(timeout_s):
            while len(raw) <= limit:
                more = await request.content.read(limit + 1 - len(raw))
                if not more:
                    return raw
                raw += more
    except TimeoutError:
        raise HttpError(408, "TIMEOUT", f"the body did not arrive within {timeout_s:g} s") from None
    raise HttpError(413, "TOO_LARGE", f"the body has more than {limit} bytes")


def json_object(raw: bytes | str, what: str) -> dict[str, Any]:
    """``raw`` as a JSON object whose every text is valid Unicode; 400 ``BAD_REQUEST`` naming
    ``what`` otherwise. JSON's ``\ud800`` escapes make lone surrogates, which no file, log or
    database can write: refused here, once, before any handler keeps one (a reason, a why, a
    token)."""
    try:
        value = json.loads(raw)
    except ValueError as exc:
        raise HttpError(400, "BAD_REQUEST", f"{what} is not JSON: {exc}") from None
    except RecursionError:  # [[[[...]]]]: nesting deeper than the parser goes
        raise HttpError(400, "BAD_REQUEST", f"{what} is JSON nested too deeply") from None
    if not isinstance(value, dict):
        raise HttpError(400, "BAD_REQUEST", f"{what} must be a JSON object")
    if not _valid_text(value):
        raise HttpError(
            400, "BAD_REQUEST", f"{what} holds text that is not valid Unicode (a lone surrogate)"
        )
    return value


def _valid_text(value: Any) -> bool:
    """Whether every string in ``value`` (keys too) encodes as UTF-8 (no lone surrogate).
    Iterative: the parser already bounded the nesting, the walk needs no stack of its own."""
    pending = [value]
    while pending:
        item = pending.pop()
        if isinstance(item, str):
            try:
                item.encode("utf-8")
            except UnicodeEncodeError:
                return False
        elif isinstance(item, dict):
            pending.extend(item.keys())
            pending.extend(item.values())
        elif isinstance(item, list):
            pending.extend(item)
    return True


async def bounded_json(request: web.Request, limit: int, timeout_s: float) -> dict[str, Any]:
    """The body as a JSON object, at most ``limit`` bytes, arrived within ``timeout_s``."""
    return json_object(await read_at_most(request, limit, timeout_s), "the body")


# ----------------------------------------------------------------------------- query strings


def int_param(
    query: Mapping[str, str], key: str, default: int | None, low: int, high: int | None
) -> Any:
    """Query parameter ``key`` as an integer in ``low..high`` (``default`` when absent)."""
    raw = query.get(key)
    if raw is None or raw == "":
        return default
    # Digits only: Python's int() also takes "1_0", " 10 " and "+10", which a URL should not.
    if not re.fullmatch(r"-?[0-9]{1,19}", raw):
        raise HttpError(400, "BAD_REQUEST", f"{key} must be an integer, got {raw[:40]!r}")
    value = int(raw)
    high = MAX_ROW_ID if high is None else high
    if value < low or value > high:
        raise HttpError(400, "BAD_REQUEST", f"{key} must be in {low}..{high or 'any'}")
    return value


def float_param(query: Mapping[str, str], key: str) -> float | None:
    """Query parameter ``key`` as a finite number (None when absent)."""
    raw = query.get(key)
    if raw is None or raw == "":
        return None
    try:
        value = float(raw)
    except ValueError:
        raise HttpError(400, "BAD_REQUEST", f"{key} must be a number, got {raw!r}") from None
    if not math.isfinite(value):
        raise HttpError(400, "BAD_REQUEST", f"{key} must be finite")
    return value


def peer_of(request: web.Request) -> str:
    """The browser's address as ``host:port`` (``unknown`` when the socket has none)."""
    peer = request.transport.get_extra_info("peername") if request.transport else None
    return f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "unknown"


# ----------------------------------------------------------------------------- options, JSON


def nested_options(written: Mapping[str, Any], options: Mapping[str, Any]) -> dict[str, Any]:
    """The page's options (dotted keys for nested ones) as the service's: a nested mapping
    laid over the configured one (``circle.min_radius_px`` keeps ``circle``'s other keys)."""
    out: dict[str, Any] = {}
    for key, value in options.items():
        if not isinstance(key, str) or not key:
            raise InvalidArgument("an option's key must be a non-empty string")
        if "." not in key:
            out[key] = value
            continue
        head, _, rest = key.partition(".")
        base = out.get(head, written.get(head, {}))
        if not isinstance(base, dict):
            raise InvalidArgument(f"option {key!r}: {head!r} is not a mapping")
        out[head] = {**base, **nested_options(base, {rest: value})}
    return out


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray | np.generic):
        return value.tolist()
    if isinstance(value, set | frozenset | tuple):
        return list(value)
    if isinstance(value, Path):
        return value.name
    return repr(value)


def dumps(value: Any) -> str:
    """JSON of an answer holding numpy values, sets or paths (a path as its name only)."""
    return json.dumps(value, default=_json_default)


# ----------------------------------------------------------------------------- the console


class Console(Protocol):
    """What a route module may use of the console that serves it (:class:`.http.HttpFrontend`)."""

    settings: ConsoleSettings
    config_path: Path | None
    save_lock: asyncio.Lock
    """Held while the configuration file is written and the server reloads."""

    def who(self, request: web.Request) -> str:
        """Who makes ``request``, for logs and the configuration's history."""
        ...

    def written(self, name: str) -> dict[str, Any]:
        """Inspection ``name`` as written in the configuration served (empty when unknown)."""
        ...

    def all_written(self) -> dict[str, Any]:
        """Every inspection as written in the configuration served."""
        ...

    def writable_config(self) -> Path:
        """The configuration file the console may write (else 403 ``CONFIG_REFUSED``)."""
        ...

    async def reload_or_undo(self, saved: Any, *, what: str = "") -> Any:
        """The server's new catalog after a console write (``saved``, an
        :class:`~.http_save.Saved`); the old text put back and 422 when it cannot load it."""
        ...

    def others_changed(self, name: str, served: Mapping[str, Any]) -> list[str]:
        """Inspections besides ``name`` that a save's reload also changed (hand edits)."""
        ...

    def result_log(self) -> ResultStore:
        """The server's result log (404 ``NOT_FOUND`` when it keeps none)."""
        ...

    async def camera_images(self, camera: str) -> Images | Callable[[ImageNeeds], Images]:
        """A try's images from ``camera``'s current frame (see ``source: camera``)."""
        ...

    def result_loader(self, result_id: Any) -> Callable[[ImageNeeds], Images]:
        """A try's images from a stored result's input (``source: result``)."""
        ...

    def recording_loader(
        self, camera: str, frame: Any, frames: int
    ) -> Callable[[ImageNeeds], Images]:
        """A try's images from frames of a recording camera (``source: recording``)."""
        ...


__all__ = [
    "HTTP_STATUS",
    "RETRY_AFTER_S",
    "audit",
    "Console",
    "HttpError",
    "bounded_json",
    "dumps",
    "error_response",
    "float_param",
    "http_error_response",
    "int_param",
    "json_object",
    "nested_options",
    "peer_of",
    "read_at_most",
    "service_error",
]
