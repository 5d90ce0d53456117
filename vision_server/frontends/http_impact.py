"""The console's impact preview: ``POST /api/inspections/{name}/impact`` (docs/console.md,
"Impact before save").

The pending change of the Inspections page (a try's ``options``, or the whole edited
``config``) is replayed over the inspection's newest stored images by the engine that
``vision-server replay`` uses (:func:`vision_server.service.replay`), so that the page and the
command line give the same flips for the same change and log. The route needs the integrator's
role (``required_role`` in :mod:`.http`), comes through the console's sign-in and CSRF rules,
and runs each image in the service's try lane without writing a row to the result log. A
browser that goes away cancels the run (the console's handlers are cancelled with their
connection).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Mapping
from typing import Any

from aiohttp import web

from ..config import ConsoleSettings, Tuner
from ..inspections import Inspection
from ..service import (
    DEFAULT_LAST,
    MAX_LAST,
    Change,
    ChangeRefused,
    InspectionService,
    changed_inspection,
    replay,
)
from . import http_save
from .http_common import HttpError, bounded_json, nested_options

IMPACT_PATH = "/api/inspections/{name}/impact"
MAX_BODY_BYTES = 64 * 1024
"""The largest body: a try's request part's limit (an edited config is a few KiB)."""
IMPACT_DEADLINE_S = 120.0
"""How long one preview may run, seconds; the answer then says ``complete: false``."""
MAX_RUNNING = 2
"""Previews at once (each holds one image at a time; they share the one try thread)."""


class ImpactRoutes:
    """The impact preview over ``service``. ``written(name)`` gives inspection ``name`` as
    written in the configuration (what a try's dotted options are laid over)."""

    def __init__(
        self,
        service: InspectionService,
        settings: ConsoleSettings,
        written: Callable[[str], dict[str, Any]],
    ) -> None:
        self.service = service
        self.settings = settings
        self.written = written
        self.running = 0

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_post(IMPACT_PATH, self.impact)

    async def impact(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        catalog = self.service.catalog
        catalog.inspection(name)  # UNKNOWN_INSPECTION: 404
        log = self.service.results
        if log is None:
            raise HttpError(404, "NO_RESULT_LOG", "this server keeps no result log to replay")
        body = await bounded_json(request, MAX_BODY_BYTES, self.settings.request_timeout_s)
        if self.running >= MAX_RUNNING:  # before any work: a third preview costs nothing
            raise HttpError(
                503,
                "BUSY",
                f"{self.running} impact previews are running; try again when one ends",
                retry_after=5,
            )
        # Counted from here, the reading of the change included (it awaits a worker).
        self.running += 1
        try:
            inspection, last = await self._changed(name, body)
            report = await replay(
                self.service,
                log,
                inspection,
                last=last,
                current_config_hash=catalog.config_hash,
                deadline=time.monotonic() + IMPACT_DEADLINE_S,
                per_image_s=self.settings.try_deadline_s,
            )
        finally:
            self.running -= 1
        answer = report.to_json()
        answer["store_images"] = getattr(log, "store_images", None)
        return web.json_response(answer, headers={"Cache-Control": "no-store"})

    async def _changed(self, name: str, body: Mapping[str, Any]) -> tuple[Inspection, int]:
        """The changed inspection a body asks a preview of, and its ``last``; 400 naming the
        key at fault."""
        catalog = self.service.catalog
        try:
            change, last = _parse(body)
            if change.options is not None:
                # Dotted keys of the page ("circle.min_radius_px") nested as a try nests them.
                change = Change(options=nested_options(self.written(name), change.options))
            # A whole config is read with the image size each running camera declares, as a
            # save reads it (a simulated camera's size is known once it is open).
            tuner = catalog.tune
            cameras = None
            if change.config is not None and isinstance(tuner, Tuner):
                cameras = http_save.declared_cameras(
                    tuner.cameras, http_save.opened_cameras(catalog)
                )
            # Building it may read template files: in a worker, not on the event loop.
            inspection = await asyncio.to_thread(
                changed_inspection, catalog, name, change, cameras=cameras
            )
        except ChangeRefused as exc:
            raise HttpError(
                400, exc.code, exc.message, details={"key": exc.key} if exc.key else None
            ) from None
        return inspection, last


def _parse(body: Mapping[str, Any]) -> tuple[Change, int]:
    """The change and ``last`` of a request body; ChangeRefused naming the key at fault."""
    unknown = sorted(set(body) - {"options", "config", "last"})
    if unknown:
        raise ChangeRefused(
            "BAD_REQUEST", f"unknown key {unknown[0]!r}: the body takes options or config, and last"
        )
    last = body.get("last", DEFAULT_LAST)
    if isinstance(last, bool) or not isinstance(last, int) or not 1 <= last <= MAX_LAST:
        raise ChangeRefused(
            "BAD_REQUEST", f"last must be an integer in 1..{MAX_LAST}, got {last!r}", "last"
        )
    options, config = body.get("options"), body.get("config")
    if (options is None) == (config is None):
        raise ChangeRefused(
            "BAD_REQUEST", "give the pending change as options or as config (exactly one)"
        )
    if options is not None:
        if not isinstance(options, dict):
            raise ChangeRefused("BAD_REQUEST", "options must be a JSON object", "options")
        return Change(options=options), last
    if not isinstance(config, dict):
        raise ChangeRefused("BAD_REQUEST", "config must be a JSON object", "config")
    return Change(config=config), last


__all__ = ["IMPACT_PATH", "ImpactRoutes"]
