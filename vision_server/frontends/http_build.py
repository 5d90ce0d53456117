"""The console's API for building inspections on the image (docs/console.md, "Building
inspections: the API"): routes added to the console's application, behind its sign-in, roles
and same-origin rule like every ``/api/*`` path.

- a try of a whole edited or new inspection mapping (``config`` in a try's request, see
  :meth:`BuildRoutes.draft`: the try itself stays :meth:`HttpFrontend.try_`, one way in);
- ``PUT /api/inspections/{name}``: save an inspection whole (:mod:`.http_save_whole`);
- ``GET /api/schema``: every key of every inspection and job step type
  (:func:`vision_server.config.inspection_schema`);
- ``POST /api/inspections/{name}/template``: cut a template from an image and keep it
  beside the configuration (:mod:`.template_files`);
- ``GET /api/inspections/{name}/reads``: the texts the inspection's last results read.
"""

from __future__ import annotations

import asyncio
import base64
import itertools
import json
import logging
from collections.abc import Mapping
from typing import Any

from aiohttp import web

from yamlfile import NAME

from ..config import ConfigError, Tuner, check_files, inspection_schema, parse_draft
from ..inspections import Inspection
from ..results import ProductionRows
from ..service import ImageNeeds, Images, InspectionService, InspectRequest
from . import http_save, http_save_whole, template_files
from .http_common import Console, HttpError, audit, bounded_json, int_param
from .http_history import why_of

log = logging.getLogger("vision_server")

BUILD_INTEGRATOR_ROUTES = frozenset({"/api/inspections/{name}", "/api/inspections/{name}/template"})
"""The paths of this module that change the configuration: the integrator's."""
MAX_SAVE_BYTES = 64 * 1024
"""The largest body of a whole save (the mapping and the reason)."""
MAX_TEMPLATE_BODY = 64 * 1024
"""The largest body of a template's training (JSON: a rectangle, maybe a draft's mapping)."""
READS_DEFAULT = 20
READS_MAX = 50
"""How many of the inspection's last production results ``/reads`` reads at most."""
READS_PAGES = 4
"""Pages of the log read at most to find them among tries (each ``last`` rows, by index)."""
MAX_READS = 200
"""The most texts one answer lists (a job reads one per code step)."""


def check_draft_name(name: str) -> None:
    """A name that no inspection has: it may be a draft's, if it is a name at all."""
    if not NAME.fullmatch(name):
        raise HttpError(
            400,
            "BAD_REQUEST",
            f"{name[:80]!r} is not an inspection's name (letters, digits, '_', '-' and '.', at "
            "most 64)",
        )


class BuildRoutes:
    """The building API of the console ``console`` over ``service``."""

    def __init__(self, console: Console, service: InspectionService) -> None:
        self.console = console
        self.service = service

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_get("/api/schema", self.schema)
        router.add_put("/api/inspections/{name}", self.save_whole)
        router.add_post("/api/inspections/{name}/template", self.template)
        router.add_get("/api/inspections/{name}/reads", self.reads)

    # ------------------------------------------------------------------ schema

    async def schema(self, request: web.Request) -> web.Response:
        """Every key of every inspection and job step type (vision_server/config/schema.py),
        ``camera`` listing the configured cameras."""
        cameras = list(self.service.catalog.cameras)
        return web.json_response(inspection_schema(cameras), headers={"Cache-Control": "no-store"})

    # ------------------------------------------------------------------ drafts

    def _tuner(self) -> Tuner:
        tune = self.service.catalog.tune
        if not isinstance(tune, Tuner):
            raise HttpError(
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
                raise HttpError(
                    404,
                    "UNKNOWN_INSPECTION",
                    f"no inspection named {name!r}: a try of a new inspection gives its whole "
                    "mapping as config",
                )
            return None
        if options:
            raise HttpError(400, "BAD_REQUEST", "give options or config, not both")
        if not isinstance(config, dict):
            raise HttpError(
                400, "BAD_REQUEST", "config must be the inspection's mapping (an object)"
            )
        if config.get("name") != name:
            raise HttpError(
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
            raise HttpError(400, "CONFIG_INVALID", str(exc)) from None

    # ------------------------------------------------------------------ save whole

    async def save_whole(self, request: web.Request) -> web.Response:
        """``PUT /api/inspections/{name}`` ``{"config": {...}, "why": "..."}``."""
        name = request.match_info["name"]
        check_draft_name(name)
        body = await bounded_json(request, MAX_SAVE_BYTES, self.console.settings.request_timeout_s)
        config = body.get("config")
        why = why_of(body)
        if not isinstance(config, dict):
            raise HttpError(
                400, "BAD_REQUEST", "config must be the inspection's mapping (an object)"
            )
        console = self.console
        path = console.writable_config()
        async with console.save_lock:
            served = console.all_written()
            try:
                # A request never makes the server open a path it chose (drafts.py).
                check_files(config, base_dir=path.resolve().parent, written=served.get(name))
            except ConfigError as exc:
                raise HttpError(
                    422, "CONFIG_REFUSED", f"{path.name}: inspection {name!r} -> {exc}"
                ) from None
            opened = http_save.opened_cameras(self.service.catalog)
            who = console.who(request)
            saved = await asyncio.to_thread(_save_whole, path, name, config, opened, who, why)
            catalog = await console.reload_or_undo(saved.saved)
        audit.info(
            "console: inspection %r %s in %s (why: %s)",
            name,
            "created" if saved.created else "saved whole",
            path.name,
            json.dumps(why),
        )
        return web.json_response(
            {
                "config_hash": catalog.config_hash,
                "version": saved.saved.version.number,
                "also_changed": console.others_changed(name, served),
                "notes": list(catalog.notes),
                "created": saved.created,
            }
        )

    # ------------------------------------------------------------------ templates

    async def template(self, request: web.Request) -> web.Response:
        """``POST /api/inspections/{name}/template``: cut ``rect`` from an image taken as a try
        takes it, keep it as a grey PNG in ``templates/`` (content-addressed), answer its path."""
        name = request.match_info["name"]
        check_draft_name(name)
        body = await bounded_json(
            request, MAX_TEMPLATE_BODY, self.console.settings.request_timeout_s
        )
        console = self.console
        path = console.writable_config()
        camera = self._camera_of(name, body.get("config"))
        rect = body.get("rect")
        try:
            template_files.check_rect(rect, 1 << 30, 1 << 30)  # its form, before any image
        except template_files.TemplateRefused as exc:
            raise HttpError(exc.status, "TEMPLATE_REFUSED", str(exc)) from None
        source = body.get("source")
        images: Images | Any
        if source == "camera":
            images = await console.camera_images(camera)
        elif source == "result":
            images = console.result_loader(body.get("result_id"))
        elif source == "recording":
            images = console.recording_loader(camera, body.get("frame"), 1)
        else:
            raise HttpError(400, "BAD_REQUEST", "source must be 'camera', 'result' or 'recording'")
        # One slot of the try lane while the image is decoded and cut: no more at once.
        key = self.service.request_key(InspectRequest(name, request_class="try"))
        admission = self.service.admit(key=key, request_class="try")
        try:
            needs = ImageNeeds(name, False, self.service.settings.max_image_pixels)
            kept = await asyncio.to_thread(_train, images, needs, rect, path.parent, name)
        finally:
            admission.release()
        audit.info("console: template %s trained for %r", kept.path, name)
        return web.json_response(
            {
                "path": kept.path,
                "width": kept.width,
                "height": kept.height,
                "image": "data:image/png;base64," + base64.b64encode(kept.png).decode("ascii"),
            }
        )

    def _camera_of(self, name: str, config: Any) -> str:
        """The camera of inspection ``name``; a draft's ``config`` names it."""
        catalog = self.service.catalog
        if config is not None:
            if not isinstance(config, dict) or not isinstance(config.get("camera"), str):
                raise HttpError(
                    400, "BAD_REQUEST", "config must be a mapping that names its camera"
                )
            catalog.camera(config["camera"])  # UNKNOWN_CAMERA
            return str(config["camera"])
        if name not in catalog.inspections:
            raise HttpError(
                404,
                "UNKNOWN_INSPECTION",
                f"no inspection named {name!r}: a new inspection's template needs its config "
                "(for its camera)",
            )
        return catalog.inspection(name).camera

    # ------------------------------------------------------------------ reads

    async def reads(self, request: web.Request) -> web.Response:
        """``GET /api/inspections/{name}/reads?last=N``: the texts the inspection's last N
        production results read, newest first, through the log's index by inspection."""
        name = request.match_info["name"]
        check_draft_name(name)
        last = int_param(request.query, "last", READS_DEFAULT, 1, READS_MAX)
        log_ = self.console.result_log()
        rows = await asyncio.to_thread(_production_rows, log_, name, last)
        out: list[dict[str, Any]] = []
        for row in rows:
            out.extend(_texts(row))
            if len(out) >= MAX_READS:
                break
        return web.json_response({"reads": out[:MAX_READS]}, headers={"Cache-Control": "no-store"})


def _train(
    images: Images | Any, needs: ImageNeeds, rect: Any, folder: Any, name: str
) -> template_files.Template:
    """Decode the image (in a thread), cut and keep the template: 400 naming ``rect``, 409
    naming the folder."""
    loaded = images if isinstance(images, Images) else images(needs)
    try:
        return template_files.keep(folder, name, template_files.cut(loaded.color, rect))
    except template_files.TemplateRefused as exc:
        raise HttpError(exc.status, "TEMPLATE_REFUSED", str(exc)) from None
    except OSError as exc:
        raise HttpError(500, "TEMPLATE_REFUSED", f"cannot write the template: {exc}") from None


def _production_rows(log_: Any, name: str, last: int) -> list[Any]:
    """The newest ``last`` production rows of ``name`` (tries skipped), by the log's index on
    inspection and time: at most :data:`READS_PAGES` pages of ``last`` rows are read."""
    rows = ProductionRows(log_, name, page_rows=last, max_examined=READS_PAGES * last)
    return list(itertools.islice(rows, last))


def _texts(row: Any) -> list[dict[str, Any]]:
    """What one stored result read: a code's or QR's ``text``, each code step's of a job."""
    data = row.data if isinstance(row.data, dict) else {}
    out = []
    if isinstance(data.get("text"), str):
        out.append({"result_id": row.id, "time": row.time, "text": data["text"], "step": None})
    steps = data.get("steps")
    if isinstance(steps, dict):
        for step, values in steps.items():
            if isinstance(values, dict) and isinstance(values.get("text"), str):
                out.append(
                    {"result_id": row.id, "time": row.time, "text": values["text"], "step": step}
                )
    return out


def _save_whole(
    path: Any, name: str, config: Any, opened: Any, who: str, why: str
) -> http_save_whole.SavedWhole:
    """Edit, validate and write the file (in a thread): CONFIG_REFUSED naming file,
    inspection and key, or why the file cannot be written."""
    try:
        return http_save_whole.save_whole(path, name, config, opened=opened, who=who, why=why)
    except (http_save.SaveRefused, ConfigError) as exc:
        raise HttpError(422, "CONFIG_REFUSED", str(exc)) from None
    except (OSError, UnicodeError) as exc:
        raise HttpError(500, "CONFIG_REFUSED", f"cannot save {path.name}: {exc}") from None


__all__ = ["BUILD_INTEGRATOR_ROUTES", "BuildRoutes", "check_draft_name"]
