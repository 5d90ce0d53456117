"""The console's history API: the configuration file's versions, their diffs, and a revert
(docs/console.md, "History"). Routes added to the console's application behind its sign-in
like every ``/api/*`` path; viewing is the operator's, a revert the integrator's
(``required_role`` in :mod:`.http`).

- ``GET /api/history?before=V&limit=N``: versions newest first, a page at a time.
- ``GET /api/history/{version}``: one version's metadata, its text and a unified diff from the
  previous kept version.
- ``POST /api/history/{version}/revert`` with ``{"why": "..."}``: write that version's text as
  a new version, validated as a save is (:func:`.http_save.validate`), and reload the server;
  a reload that fails puts the old text back.

The versions themselves are kept by :mod:`vision_server.config.history`; every write of the
file goes through :func:`.http_save.write_version`.
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
import secrets
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

from aiohttp import web

from ..config import ConfigError, history, redact_secrets
from ..service import InspectionService
from . import http_save
from .http_common import Console, HttpError, audit, int_param, json_object, read_at_most

MAX_BODY = 4096
"""The largest revert body (a reason, not an upload), bytes."""
MAX_LIMIT = 200
"""The most versions one page of ``GET /api/history`` lists."""
DEFAULT_LIMIT = 50

Who = Callable[[web.Request], str]
RouteHandler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def why_of(body: Mapping[str, Any]) -> str:
    """The ``why`` of a save's or a revert's body: a string of at most
    :data:`~vision_server.config.history.MAX_WHY` characters, stripped (absent: empty).
    Raises :class:`~.http_common.HttpError` (400)."""
    why = body.get("why", "")
    if why is None:
        return ""
    if not isinstance(why, str):
        raise HttpError(400, "BAD_REQUEST", "why must be a string (the reason for the change)")
    why = why.strip()
    if len(why) > history.MAX_WHY:
        raise HttpError(
            400,
            "BAD_REQUEST",
            f"why has {len(why)} characters, at most {history.MAX_WHY} are kept: shorten it",
        )
    return why


def _answers(handler: RouteHandler) -> RouteHandler:
    """``handler`` with the history's file errors as the console's errors."""

    async def wrapped(request: web.Request) -> web.StreamResponse:
        try:
            return await handler(request)
        except history.UnknownVersion as exc:
            raise HttpError(404, "NOT_FOUND", str(exc)) from None
        except OSError as exc:  # the file, the history's folder or a version cannot be read
            raise HttpError(
                500, "HISTORY_UNAVAILABLE", f"the configuration's history cannot be read: {exc}"
            ) from None

    return wrapped


class HistoryRoutes:
    """The history API of the configuration file of ``console`` (its ``config_path``; None:
    the server runs without one) served by ``service``. A revert holds the console's save lock
    (a revert and a save never interleave); ``console.who(request)`` names the person;
    ``console.settings.allow_save`` says whether the console may write the file
    (``server.allow_reload``)."""

    def __init__(self, console: Console, service: InspectionService) -> None:
        self.console = console
        self.service = service
        # The texts shown hide their secrets (tokens, passwords, PINs): an operator must not
        # read the admin's token in a diff. A changed secret still shows as a changed line,
        # by a fingerprint keyed with this secret, made at start and never shown.
        self._fingerprint_key = secrets.token_bytes(32)

    def shown(self, text: str) -> str:
        """``text`` as the API shows it: its secrets hidden (:func:`redact_secrets`)."""
        return redact_secrets(text, self._fingerprint)

    def _fingerprint(self, value: str) -> str:
        digest = hmac.new(self._fingerprint_key, value.encode("utf-8"), hashlib.sha256)
        return digest.hexdigest()[:8]

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/history", _answers(self.list_))
        router.add_get(r"/api/history/{version:\d{1,9}}", _answers(self.version))
        router.add_post(r"/api/history/{version:\d{1,9}}/revert", _answers(self.revert))

    def _history(self) -> history.History:
        if self.console.config_path is None:
            raise HttpError(404, "NOT_FOUND", "this server runs without a configuration file")
        return history.history_of(self.console.config_path)

    async def list_(self, request: web.Request) -> web.Response:
        versions = self._history()
        before = int_param(request.query, "before", None, 1, None)
        limit = int_param(request.query, "limit", DEFAULT_LIMIT, 1, MAX_LIMIT)
        page = await asyncio.to_thread(versions.versions, before=before, limit=limit + 1)
        more = len(page) > limit
        page = page[:limit]
        current = await asyncio.to_thread(_current_hash, versions.config)
        newest = page[0].number if page and before is None else None
        return web.json_response(
            {
                "versions": [v.json() for v in page],
                "next_before": page[-1].number if more and page else None,
                # Whether the file still holds the newest version's text (no edit outside the
                # console since): the next save records the file's text first otherwise.
                "file_config_hash": current,
                "served_config_hash": self.service.catalog.config_hash,
                "newest": newest,
                "limits": {
                    "max_versions": versions.bounds.max_versions,
                    "max_bytes": versions.bounds.max_bytes,
                },
            },
            headers={"Cache-Control": "no-store"},
        )

    async def version(self, request: web.Request) -> web.Response:
        versions = self._history()
        number = int(request.match_info["version"])

        def read() -> dict[str, Any]:
            meta = versions.get(number)
            text = versions.text(number)
            return {
                **meta.json(),
                "previous": versions.previous(number),
                "text": self.shown(text.decode("utf-8", "replace")),
                "diff": versions.diff(number, self.shown),
                "is_file": text == _read_or_none(versions.config),
            }

        body = await asyncio.to_thread(read)
        return web.json_response(body, headers={"Cache-Control": "no-store"})

    async def revert(self, request: web.Request) -> web.Response:
        versions = self._history()
        number = int(request.match_info["version"])
        raw = await read_at_most(request, MAX_BODY, self.console.settings.request_timeout_s)
        body = json_object(raw or b"{}", "the body")
        why = why_of(body)
        path = self.console.writable_config()
        who = self.console.who(request)
        async with self.console.save_lock:
            target = await asyncio.to_thread(versions.text, number)
            old = await asyncio.to_thread(path.read_bytes)
            if old == target:
                return web.json_response(
                    {
                        "changed": False,
                        "message": f"the configuration file already holds version {number}'s "
                        "text: nothing was written",
                        "version": None,
                        "reverted_to": number,
                        "config_hash": self.service.catalog.config_hash,
                        "notes": [],
                    }
                )
            opened = http_save.opened_cameras(self.service.catalog)
            saved = await asyncio.to_thread(
                _write_revert, path, number, target, old, opened, who, why
            )
            catalog = await self.console.reload_or_undo(
                saved,
                what=f"version {number} was written but the server could not load it, so the "
                "file was put back: ",
            )
        audit.info(
            "console: %s reverted %s to version %d as version %d (why: %s)",
            who,
            path.name,
            number,
            saved.version.number,
            json.dumps(why),
        )
        return web.json_response(
            {
                "changed": True,
                "version": saved.version.number,
                "reverted_to": number,
                "config_hash": catalog.config_hash,
                "notes": list(catalog.notes),
            }
        )


def _write_revert(
    path: Path,
    number: int,
    target: bytes,
    old: bytes,
    opened: Mapping[str, http_save.OpenedCamera],
    who: str,
    why: str,
) -> http_save.Saved:
    """Validate version ``number``'s text as a save's and write it (in a thread)."""
    try:
        text = target.decode("utf-8")
    except UnicodeError:
        raise HttpError(
            422, "CONFIG_REFUSED", f"version {number} is not UTF-8 text: it cannot be loaded"
        ) from None
    # As a save: the whole file by the loader, and each inspection the revert changes by the
    # rules a try applies (its ROI within the image each running camera declares).
    changed, _ = history.changed_between(old, target)
    try:
        config = http_save.validate(text, path, opened=opened)
        present = {i.name for i in config.inspections}
        for name in changed:
            if name in present:
                http_save.validate(text, path, inspection=name, opened=opened)
    except ConfigError as exc:
        raise HttpError(
            422, "CONFIG_REFUSED", f"version {number} cannot be loaded as it is now: {exc}"
        ) from None
    try:
        version = http_save.write_version(
            path, text, old=old, who=who, why=why, kind=history.REVERT, reverted_to=number
        )
    except http_save.SaveRefused as exc:
        raise HttpError(422, "CONFIG_REFUSED", str(exc)) from None
    except OSError as exc:
        raise HttpError(500, "CONFIG_REFUSED", f"cannot write {path.name}: {exc}") from None
    return http_save.Saved(path, old, version)


def _read_or_none(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError:
        return None


def _current_hash(path: Path) -> str | None:
    data = _read_or_none(path)
    return None if data is None else history.config_hash(data)


__all__ = ["HistoryRoutes", "why_of"]
