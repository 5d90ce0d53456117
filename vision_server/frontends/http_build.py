"""The console's API for building inspections on the image (docs/console.md, "Building
inspections: the API"): routes added to the console's application, behind its sign-in, roles
and same-origin rule like every ``/api/*`` path.

- a try of a whole edited or new inspection mapping (``config`` in a try's request, see
  :meth:`BuildRoutes.draft`: the try itself stays :meth:`HttpFrontend.try_`, one way in);
- ``PUT /api/inspections/{name}``: save an inspection whole (:mod:`.http_save_whole`);
- ``GET /api/schema``: every key of every inspection and job step type
  (:func:`vision_server.config.inspection_schema`);
- ``POST /api/inspections/{name}/template``: cut a template from an image and keep it
  beside the configuration (:mod:`.templates`);
- ``GET /api/inspections/{name}/reads``: the texts the inspection's last results read.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from aiohttp import web

from protocol import CellvisionError
from yamlfile import NAME

from ..config import ConfigError, Tuner, parse_draft
from ..inspections import Inspection
from ..service import InspectionService
from . import http_save, http_save_whole

if TYPE_CHECKING:
    from .http import HttpFrontend

log = logging.getLogger("vision_server")

BUILD_INTEGRATOR_ROUTES = frozenset({"/api/inspections/{name}"})
"""The paths of this module that change the configuration: the integrator's."""
MAX_SAVE_BYTES = 64 * 1024
"""The largest body of a whole save (the mapping and the reason)."""
MAX_WHY = 500
"""The longest reason a save may give, characters."""


def _error(status: int, code: str, message: str) -> Exception:
    """The console's JSON error (its middleware renders it)."""
    from .http import HttpError  # http imports this module: taken when called

    return HttpError(status, code, message)


def check_draft_name(name: str) -> None:
    """A name that no inspection has: it may be a draft's, if it is a name at all."""
    if not NAME.fullmatch(name):
        raise _error(
            400,
            "BAD_REQUEST",
            f"{name[:80]!r} is not an inspection's name (letters, digits, '_', '-' and '.', at "
            "most 64)",
        )


class BuildRoutes:
    """The building API of the console ``console`` over ``service``."""

    def __init__(self, console: HttpFrontend, service: InspectionService) -> None:
        self.console = console
        self.service = service

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_put("/api/inspections/{name}", self.save_whole)

    # ------------------------------------------------------------------ drafts

    def _tuner(self) -> Tuner:
        tune = self.service.catalog.tune
        if not isinstance(tune, Tuner):
            raise _error(
                400,
                "BAD_REQUEST",
                "this server's inspections do not come from a configuration file: it tries "
                "and saves no edited inspection",
            )
        return tune

    async def draft(
        self, name: str, spec: Mapping[str, Any], options: Mapping[str, Any]
    ) -> Inspection | None:
        """The inspection a try's ``config`` describes, validated as the file's loader would
        with the image size each running camera declares (400 CONFIG_INVALID naming the key
        path); None when the try gives no ``config`` (then the inspection must be configured)."""
        config = spec.get("config")
        configured = name in self.service.catalog.inspections
        if config is None:
            if not configured:
                raise _error(
                    404,
                    "UNKNOWN_INSPECTION",
                    f"no inspection named {name!r}: a try of a new inspection gives its whole "
                    "mapping as config",
                )
            return None
        if options:
            raise _error(400, "BAD_REQUEST", "give options or config, not both")
        if not isinstance(config, dict):
            raise _error(400, "BAD_REQUEST", "config must be the inspection's mapping (an object)")
        if config.get("name") != name:
            raise _error(
                400,
                "BAD_REQUEST",
                f"config's name {config.get('name')!r} is not {name!r}, the inspection tried",
            )
        tuner = self._tuner()
        cameras = http_save.declared_cameras(
            tuner.cameras, http_save.opened_cameras(self.service.catalog)
        )
        written = tuner.written.get(name)
        try:
            # A template is read from disk: not on the event loop.
            return await asyncio.to_thread(
                parse_draft, config, base_dir=tuner.base_dir, cameras=cameras, written=written
            )
        except ConfigError as exc:
            raise _error(400, "CONFIG_INVALID", str(exc)) from None

    # ------------------------------------------------------------------ save whole

    async def save_whole(self, request: web.Request) -> web.Response:
        """``PUT /api/inspections/{name}`` ``{"config": {...}, "why": "..."}``."""
        from .http import _json_body, _read_at_most

        name = request.match_info["name"]
        check_draft_name(name)
        body = await _json_body(request, await _read_at_most(request, MAX_SAVE_BYTES))
        config = body.get("config")
        why = body.get("why", "")
        if why is None:
            why = ""
        if not isinstance(why, str) or len(why) > MAX_WHY:
            raise _error(400, "BAD_REQUEST", f"why must be a text of at most {MAX_WHY} characters")
        if not isinstance(config, dict):
            raise _error(400, "BAD_REQUEST", "config must be the inspection's mapping (an object)")
        console = self.console
        path = console.config_path
        if path is None:
            raise _error(403, "CONFIG_REFUSED", "this server runs without a configuration file")
        if not console.settings.allow_save:
            raise _error(403, "CONFIG_REFUSED", "saving is off (server.allow_reload: false)")
        async with console._save_lock:
            served = console._all_written()
            opened = http_save.opened_cameras(self.service.catalog)
            saved = await asyncio.to_thread(_save_whole, path, name, config, opened, why)
            try:
                catalog = await self.service.reload()
            except CellvisionError as exc:
                # The file validated but the server could not take it: put the old text
                # back so that file and server agree.
                await asyncio.to_thread(http_save.undo, saved.saved)
                raise _error(422, "CONFIG_REFUSED", exc.message) from None
            await asyncio.to_thread(http_save.prune_backups, path, spare=saved.saved.backup)
        log.info(
            "console: inspection %r %s in %s (why: %s)",
            name,
            "created" if saved.created else "saved whole",
            path.name,
            json.dumps(why),
        )
        now = console._all_written()
        also = [
            other
            for other in sorted(set(served) | set(now))
            if other != name and served.get(other) != now.get(other)
        ]
        return web.json_response(
            {
                "config_hash": catalog.config_hash,
                "backup": saved.saved.backup.name,
                "also_changed": also,
                "notes": list(catalog.notes),
                "created": saved.created,
            }
        )


def _save_whole(
    path: Any, name: str, config: Any, opened: Any, why: str
) -> http_save_whole.SavedWhole:
    """Edit, validate and write the file (in a thread): CONFIG_REFUSED naming file,
    inspection and key, or why the file cannot be written."""
    try:
        return http_save_whole.save_whole(path, name, config, opened=opened, why=why)
    except (http_save.SaveRefused, ConfigError) as exc:
        raise _error(422, "CONFIG_REFUSED", str(exc)) from None
    except (OSError, UnicodeError) as exc:
        raise _error(500, "CONFIG_REFUSED", f"cannot save {path.name}: {exc}") from None


__all__ = ["BUILD_INTEGRATOR_ROUTES", "BuildRoutes", "check_draft_name"]
