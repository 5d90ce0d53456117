"""The web console's HTTP front-end: the page, its JSON API (docs/console.md) and ``/metrics``.

An aiohttp application in the server's own event loop over the one inspection service, like
the TCP front-end: parse the request, call the service (every try through
:meth:`InspectionService.inspect`: admission, deadlines, the result log), render its records as
JSON, and map the service's ``ErrorCode`` to an HTTP status in one table
(:data:`HTTP_STATUS`). Every error is a JSON body; a malformed request is a 4xx, never a
traceback.

Security: with an ``auth_token`` every ``/api/*`` path but ``/api/login`` (and ``/metrics``)
answers 401 without a session (:mod:`.http_auth`); the page and its files answer so that the
sign-in page can show. Files are served from the console's static folder only (aiohttp refuses
paths that leave it); result images by result id only; the configuration file is the one the
server was started with.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from aiohttp import BodyPartReader, web
from aiohttp.http_exceptions import HttpProcessingError

from protocol import (
    CellvisionError,
    ImageTooLarge,
    InvalidArgument,
)

from ..cameras import RecordingCamera, RecordingError
from ..config import FIXED_BY_THE_CONFIGURATION, SERVER_VERSION, ConsoleSettings, history
from ..console import static_dir
from ..results import TRY_PEER_PREFIX, ResultLogError, TimingsCache, is_row_id
from ..service import (
    CaptureRequest,
    ImageNeeds,
    Images,
    InspectionService,
    InspectRequest,
    OperatorDesk,
    check_images,
    stored_image_loader,
)
from . import http_export, http_save
from .http_auth import COOKIE, RANK, Role, Sessions
from .http_build import BUILD_INTEGRATOR_ROUTES, BuildRoutes, check_draft_name
from .http_common import (
    HTTP_STATUS,
    HttpError,
    audit,
    bounded_json,
    dumps,
    error_response,
    float_param,
    http_error_response,
    int_param,
    json_object,
    nested_options,
    peer_of,
    read_at_most,
    service_error,
)
from .http_door import cross_site_reason, host_allowed
from .http_export import ExportRoutes
from .http_history import HistoryRoutes, why_of
from .http_impact import IMPACT_PATH, ImpactRoutes
from .http_live import LiveView
from .http_metrics import CONTENT_TYPE, Metrics
from .http_online import OnlineRoutes
from .http_operator import OperatorRoutes
from .http_train import TRAIN_PATH, TrainRoutes
from .http_users import SignIn, SignInError, TooManyTries
from .listener import Listener, Policy, quiet_logger
from .mqtt import mqtt_check
from .online_board import OnlineBoard
from .uploads import upload_loader

log = logging.getLogger("vision_server")
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


MAX_JSON_PART = 64 * 1024
"""The largest ``request`` part of a try, bytes."""
FORM_OVERHEAD = 64 * 1024
"""Bytes of a try's form besides the image (boundaries, the request part)."""
FRAME_TIMESTAMP_HEADER = "X-Frame-Timestamp"
_DEVICE_KEYS = ("serial", "model", "vendor", "device_id", "address", "protocol")
"""What ``/api/cameras`` shows of a device camera's identity, from its ``status()``."""
LOGIN_MAX_BYTES = 4096
"""The largest sign-in body: a token, not an upload."""

"""The live view's frame.jpg header: the frame's capture time, Unix seconds."""
SECURITY_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Content-Security-Policy": (
        "default-src 'self'; img-src 'self' data: blob:; style-src 'self' 'unsafe-inline'; "
        "frame-ancestors 'none'; base-uri 'none'; form-action 'self'"
    ),
}
PARAMETER_RANGES: dict[str, tuple[float | None, float | None, float | None]] = {
    "threshold": (0, 255, 1),
}


ServerInfo = Callable[[], dict[str, Any]]
"""What the app knows that the service does not: ``listen`` and ``connections``."""


class HttpFrontend:
    """Serves the console for ``service``; ``config_path`` is the file saves write (None: no
    saving); ``server_info`` adds the app's listening address and connections."""

    def __init__(
        self,
        service: InspectionService,
        settings: ConsoleSettings,
        *,
        config_path: Path | None = None,
        server_info: ServerInfo | None = None,
        operator_desk: OperatorDesk | None = None,
    ) -> None:
        self.service = service
        self.operator_desk = operator_desk or OperatorDesk()
        """The operator calls this console shows and answers (the TCP front-end posts them)."""
        self.settings = settings
        self.config_path = config_path
        self.server_info = server_info or (lambda: {})
        self.sessions = Sessions(
            {
                "admin": settings.auth_token,
                "operator": settings.operator_token,
                "integrator": settings.integrator_token,
            },
            settings.users,
        )
        self.sign_in = SignIn(self.sessions)
        self.started_at = time.time()
        self._runner: web.AppRunner | None = None
        self._listener: Listener | None = None
        self.save_lock = asyncio.Lock()
        if config_path is not None:
            history.set_bounds(
                config_path,
                history.Bounds(settings.history_max_versions, settings.history_max_bytes),
            )
        self.live: LiveView | None = None
        self.metrics: Metrics | None = None
        self._builder = BuildRoutes(self, service)
        self._trainer = TrainRoutes(self, service)
        self._timings: TimingsCache | None = None
        """The statistics' columns of the result log, read incrementally (GET /api/stats)."""
        self.online: OnlineBoard | None = None
        """The online view's counts and last graphics (made with the application)."""

    # ------------------------------------------------------------------ lifecycle

    @property
    def address(self) -> tuple[str, int]:
        """The address and port actually bound (useful with port 0)."""
        if self._listener is None:
            raise RuntimeError("the console is not started")
        return self._listener.address

    @property
    def port(self) -> int:
        return self.address[1]

    @property
    def url(self) -> str:
        scheme = "https" if self.settings.tls_cert else "http"
        host, port = self.address
        return f"{scheme}://{'[' + host + ']' if ':' in host else host}:{port}/"

    async def start(self) -> None:
        self.live = LiveView(self.service, self.settings.max_view_fps)
        self.metrics = Metrics(self.service, self.live)
        self._runner = web.AppRunner(
            self.build(),
            access_log=None,
            keepalive_timeout=self.settings.idle_timeout_s,
            # HTTP that does not parse (too many headers, a header line too long) is logged
            # a line at a time, not a traceback per connection (a flood filled 0.6 MB/s).
            logger=quiet_logger("vision_server.console.http"),
            # A browser that goes away takes its request with it (a try's answer is dropped
            # and its slot freed, as for a robot's dropped connection), and an unread body is
            # not waited for longer than a request may take.
            handler_cancellation=True,
            lingering_time=self.settings.request_timeout_s,
        )
        await self._runner.setup()
        server = self._runner.server
        assert server is not None
        # Connections come through the service's front door (counted before TLS) and close
        # when they stall, whatever they send (vision_server/frontends/listener.py).
        self._listener = Listener(
            self.service.door,
            Policy(
                name="console",
                max_connections=self.settings.max_connections,
                request_timeout_s=self.settings.request_timeout_s,
                idle_timeout_s=self.settings.idle_timeout_s,
                write_timeout_s=self.settings.write_timeout_s,
                tls_handshake_timeout_s=self.settings.request_timeout_s,
            ),
            server,
            ssl_context=self.settings.ssl_context(),
        )
        try:
            await self._listener.start(self.settings.host, self.settings.port)
        except BaseException:  # a port that is taken: leave nothing set up behind
            await self.stop()
            raise

    async def stop(self) -> None:
        if self._listener is not None:
            await self._listener.stop_accepting()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._listener is not None:
            await self._listener.close_connections()
            self._listener = None
        if self.metrics is not None:
            self.metrics.close()
        if self.online is not None:
            self.online.close()
            self.online = None
        if self.live is not None:
            self.live.close()
        self._trainer.close()

    def build(self) -> web.Application:
        app = web.Application(
            middlewares=[self._errors, self._door, self._guard],
            client_max_size=self.settings.max_upload_bytes + FORM_OVERHEAD,
        )
        routes = app.router
        routes.add_get("/", self.index)
        routes.add_static("/static/", static_dir(), follow_symlinks=False)
        routes.add_post("/api/login", self.login)
        routes.add_post("/api/logout", self.logout)
        routes.add_get("/api/server", self.server)
        routes.add_get("/api/cameras", self.cameras)
        routes.add_get("/api/cameras/{name}/frame.jpg", self.frame)
        routes.add_get("/api/inspections", self.inspections)
        routes.add_post("/api/inspections/{name}/try", self.try_)
        routes.add_post("/api/inspections/{name}/save", self.save)
        routes.add_get("/api/results", self.results_list)
        routes.add_get(r"/api/results/{id:\d{1,18}}", self.result)
        routes.add_get(r"/api/results/{id:\d{1,18}}/image.png", self.result_image)
        routes.add_get("/api/stats", self.stats)
        routes.add_get("/metrics", self.metrics_text)
        OperatorRoutes(self.operator_desk, self.who, self.settings, self.service).add_to(routes)
        ExportRoutes(self.result_log, self.user_name, SECURITY_HEADERS).add_to(routes)
        self._builder.add_to(routes)
        HistoryRoutes(self, self.service).add_to(routes)
        ImpactRoutes(self.service, self.settings, self.written).add_to(routes)
        self._trainer.add_to(routes)
        if self.online is None:
            self.online = OnlineBoard(self.service)
        OnlineRoutes(self.online, timeout_s=self.settings.request_timeout_s).add_to(routes)
        return app

    # ------------------------------------------------------------------ middlewares

    @web.middleware
    async def _errors(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Every error as JSON; nothing escapes as a traceback."""
        try:
            response = await handler(request)
        except CellvisionError as exc:
            response = service_error(exc)
        except HttpError as exc:
            response = http_error_response(exc)
        except web.HTTPException as exc:  # routing (404, 405), body too large (413)
            if exc.status < 400:
                raise
            code = {401: "UNAUTHORIZED", 404: "NOT_FOUND", 413: "TOO_LARGE"}.get(
                exc.status, "BAD_REQUEST"
            )
            response = error_response(exc.status, code, exc.reason)
        except HttpProcessingError as exc:  # a body aiohttp could not parse
            response = error_response(400, "BAD_REQUEST", f"malformed request: {exc.message}")
        except ResultLogError as exc:  # e.g. a PostgreSQL log whose database is down
            response = error_response(503, "RESULT_LOG_UNAVAILABLE", str(exc))
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("console: %s %s failed", request.method, request.path)
            response = error_response(500, "INTERNAL_ERROR", "the server failed; see its log")
        for key, value in SECURITY_HEADERS.items():
            response.headers.setdefault(key, value)
        return response

    @web.middleware
    async def _door(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """The Host and same-origin rules (vision_server/frontends/http_door.py), and the
        connection's clock: no deadline while a request is answered, a fresh one after."""
        if not host_allowed(request.host, self.settings.allowed_hosts):
            raise HttpError(
                421,
                "MISDIRECTED",
                f"this console does not answer for the host {request.host!r} (add the name to "
                "console: allowed_hosts if it is this machine's)",
            )
        why = cross_site_reason(request)
        if why is not None:
            raise HttpError(403, "CROSS_SITE", why)
        listener = self._listener
        clock = listener.clock_of(request.transport) if listener is not None else None
        if listener is None or clock is None:
            return await handler(request)
        clock.begin()
        try:
            response = await handler(request)
            if self._role(request) is not None:
                clock.signed_in = True
            return response
        finally:
            clock.end(listener.policy, time.monotonic())

    @web.middleware
    async def _guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Without a session only the page (its sign-in form) and /api/login answer."""
        path = request.path
        protected = (path.startswith("/api/") and path != "/api/login") or path == "/metrics"
        if not protected:
            return await handler(request)
        role = self._role(request)
        if role is None:
            if path == "/metrics" and request.headers.get("Authorization"):
                raise await self._refuse_token(request, "wrong bearer token")
            raise HttpError(401, "UNAUTHORIZED", "sign in with the server's token first")
        needed = required_role(request)
        if RANK[role] < RANK[needed]:
            raise HttpError(
                403,
                "FORBIDDEN",
                f"signed in as {role}: this needs the {needed}'s rights (sign in as a user "
                f"with that role, or with the "
                f"{'integrator_token' if needed == 'integrator' else 'auth_token'})",
            )
        return await handler(request)

    def _role(self, request: web.Request) -> Role | None:
        """The role of the request's session (or, for /metrics, of its bearer token)."""
        role = self.sessions.role(request.cookies.get(COOKIE))
        if role is None and request.path == "/metrics":  # a scraper sends a bearer token
            auth = request.headers.get("Authorization", "")
            if auth.startswith("Bearer "):
                return self.sessions.role_of(auth[7:].strip())
        return role

    def _user(self, request: web.Request) -> str | None:
        """The signed-in named user's name, else None."""
        session = self.sessions.session(request.cookies.get(COOKIE))
        return None if session is None else session.user

    def who(self, request: web.Request) -> str:
        """Who makes ``request``, for logs and records: the signed-in user's name, else the
        role of the token the session was opened with, else "console" (no sign-in)."""
        if not self.sessions.required:
            return "console"
        session = self.sessions.session(request.cookies.get(COOKIE))
        if session is None:
            return "console"
        return session.user or session.role

    async def _refuse_token(self, request: web.Request, message: str) -> HttpError:
        """A wrong token, answered after the front door's delay for its host."""
        await asyncio.sleep(self.service.door.auth_failed(peer_of(request)))
        return HttpError(401, "UNAUTHORIZED", message)

    # ------------------------------------------------------------------ page, sign-in

    async def index(self, request: web.Request) -> web.StreamResponse:
        response = web.FileResponse(static_dir() / "index.html")
        response.headers["Cache-Control"] = "no-store"
        return response

    async def login(self, request: web.Request) -> web.Response:
        raw = await read_at_most(request, LOGIN_MAX_BYTES, self.settings.request_timeout_s)
        body = json_object(raw, "the body")
        response = web.json_response({"ok": True})
        if not self.sessions.required:
            return response
        try:
            session = await self.sign_in.check(body)
        except SignInError as exc:
            raise HttpError(400, "BAD_REQUEST", str(exc)) from None
        except TooManyTries as exc:
            raise HttpError(
                429, "TOO_MANY_TRIES", str(exc), retry_after=max(1, math.ceil(exc.wait_s))
            ) from None
        if session is None:
            wrong = "wrong name or PIN" if "user" in body or "pin" in body else "wrong token"
            raise await self._refuse_token(request, wrong)
        if session.user is not None:
            audit.info(
                "console: %s signed in (%s) from %s", session.user, session.role, peer_of(request)
            )
        response = web.json_response({"ok": True, "role": session.role, "user": session.user})
        response.set_cookie(
            COOKIE,
            self.sessions.open(session.role, session.user),
            httponly=True,
            samesite="Strict",
            path="/",
            secure=bool(self.settings.tls_cert),
        )
        return response

    async def logout(self, request: web.Request) -> web.Response:
        self.sessions.close(request.cookies.get(COOKIE))
        response = web.json_response({"ok": True})
        response.del_cookie(COOKIE, path="/")
        return response

    # ------------------------------------------------------------------ server, cameras

    async def server(self, request: web.Request) -> web.Response:
        service = self.service
        health = service.health()
        log_ok = bool(health["result_log"]["ok"]) if "result_log" in health else True
        checks = [{"name": "result log", "ok": log_ok, "message": ""}]
        if "result_log" in health and not log_ok:
            checks[0]["message"] = str(health["result_log"].get("last_error") or "rows lost")
        if "mqtt" in health:  # the MQTT publisher (docs/mqtt.md)
            checks.append(mqtt_check(health["mqtt"]))
        info = self.server_info()
        reloads = [
            {"time": r.time, "ok": r.ok, "config_hash": r.config_hash, "message": r.message}
            for r in reversed(service.reloads)
        ]
        return web.json_response(
            {
                "name": self.settings.name,
                "version": SERVER_VERSION,
                "protocol": info.get("protocol", "1.0"),
                "config_file": None if self.config_path is None else str(self.config_path),
                "config_hash": service.catalog.config_hash,
                "started_at": self.started_at,
                "uptime_s": round(time.time() - self.started_at, 1),
                "listen": info.get("listen"),
                "auth_required": self.sessions.required,
                "role": self._role(request),
                "user": self._user(request),
                "health": {"status": "ok" if health["ok"] else "degraded", "checks": checks},
                "pool": {
                    "workers": service.settings.workers,
                    "in_flight": service.pool.admitted,
                    "max_in_flight": service.pool.capacity,
                    "queued": max(
                        service.pool.admitted
                        - service.settings.workers
                        - service.settings.fast_workers,
                        0,
                    ),
                    "queue_depth": service.settings.queue_depth,
                    "waiting_unread": service.pool.waiting,
                    "lanes": [
                        {
                            "lane": lane.name,
                            "threads": lane.threads,
                            "admitted": lane.admitted,
                            "capacity": lane.capacity,
                            "expected_wait_ms": round(lane.expected_wait_ms(0.0), 1),
                            "waiting": len(lane.waiters),
                        }
                        for lane in service.pool.lanes
                    ],
                    "costs_ms": {
                        name: round(ms, 2) for name, ms in service.pool.costs.snapshot().items()
                    },
                    "busy_count": service.busy_count,
                    "answered": None if self.metrics is None else self.metrics.answered,
                },
                "connections": info.get("connections", []),
                "reloads": reloads,
            }
        )

    async def cameras(self, request: web.Request) -> web.Response:
        assert self.live is not None
        out = []
        for name, camera in self.service.catalog.cameras.items():
            request_camera = camera.source == "request"
            newest = self.live.newest(name)
            width = newest.width if newest else None
            height = newest.height if newest else None
            if width is None and camera.intrinsics is not None:
                width, height = camera.intrinsics.width, camera.intrinsics.height
            frames = None
            status: dict[str, Any] = {}
            if not request_camera:
                try:
                    status = camera.status()
                    frames = int(status.get("frames", 0))
                except Exception:  # a camera's status is best effort here
                    frames = None
            out.append(
                {
                    "name": name,
                    "source": camera.source,
                    "depth": camera.has_depth,
                    "width": width,
                    "height": height,
                    "fps": None if request_camera else self.live.measured_fps(name, frames),
                    "view_fps": None if request_camera else self.settings.max_view_fps,
                    # What the live image is: the camera's own frames, or (a camera whose
                    # frames the console must not take) the last one the cell took or sent.
                    "view": "live"
                    if camera.view_takes_frames and not request_camera
                    else "last_sent"
                    if request_camera
                    else "last_taken",
                    "frame_age_s": None
                    if newest is None
                    else round(max(time.time() - newest.timestamp, 0.0), 3),
                    "state": status.get("state"),
                    "last_error": camera.public_text(str(status["last_error"]))
                    if status.get("last_error")
                    else None,
                    "reconnects": status.get("reconnects"),
                    # A device camera's identity (serial, model, address ...) and a
                    # streaming device's statistics (frames and packets), when it has them.
                    "device": {k: status[k] for k in _DEVICE_KEYS if k in status} or None,
                    "stream": status.get("stream"),
                }
            )
        return web.json_response({"cameras": out})

    async def frame(self, request: web.Request) -> web.Response:
        assert self.live is not None
        name = request.match_info["name"]
        frame = await self.live.frame(name)
        if frame is None:
            raise HttpError(404, "NOT_FOUND", f"camera {name!r} has had no image yet")
        headers = {
            "Cache-Control": "no-store",
            # When the camera took it (Unix seconds): a viewer can tell a new frame from the
            # cached one and measure how old it is on arrival (bench/console.py does).
            FRAME_TIMESTAMP_HEADER: f"{frame.timestamp:.6f}",
        }
        return web.Response(body=frame.jpeg, content_type="image/jpeg", headers=headers)

    # ------------------------------------------------------------------ inspections

    def written(self, name: str) -> dict[str, Any]:
        """Inspection ``name`` as written in the configuration (empty when unknown)."""
        written = getattr(self.service.catalog.tune, "written", None)
        if not isinstance(written, Mapping) or name not in written:
            return {}
        return dict(written[name])

    async def inspections(self, request: web.Request) -> web.Response:
        catalog = self.service.catalog
        out = []
        for descriptor in catalog.inspection_descriptors():
            config = self.written(descriptor["name"]) or {
                k: descriptor[k] for k in ("name", "type", "camera")
            }
            roi = config.get("roi")
            out.append(
                {
                    **descriptor,
                    "config": config,
                    "parameters": parameters(config),
                    "roi": roi if isinstance(roi, list) else None,
                }
            )
        return web.json_response({"inspections": out}, dumps=dumps)

    async def try_(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name not in self.service.catalog.inspections:
            check_draft_name(name)  # a try of a draft: its config comes in the body
        arrived = time.monotonic()
        declared = request.content_length
        limit = self.settings.max_upload_bytes + FORM_OVERHEAD
        if declared is not None and declared > limit:
            raise HttpError(413, "TOO_LARGE", f"the request has {declared} bytes, limit {limit}")
        # The body's bytes are reserved before it is read (BUSY when the server's memory for
        # request bodies is taken), as the protocol does for a frame.
        admission = self.service.admit(
            work=False, body_bytes=declared or limit, request_class="try"
        )
        try:
            # A stalled upload must not hold the bytes it reserved: the body must arrive
            # within the request timeout, plus a second per MiB.
            upload_s = self.settings.request_timeout_s + (declared or limit) / (1 << 20)
            try:
                async with asyncio.timeout(upload_s):
                    spec, upload = await self._try_form(request)
            except TimeoutError:
                raise HttpError(
                    408, "TIMEOUT", f"the try's body did not arrive within {upload_s:.0f} s"
                ) from None
            options = spec.get("options") or {}
            if not isinstance(options, dict):
                raise HttpError(400, "BAD_REQUEST", "options must be a JSON object")
            # A whole edited or new mapping (http_build), else the configured inspection
            # with the options laid over it.
            draft = await self._builder.draft(name, spec, options)
            inspection = self.service.catalog.inspection(name) if draft is None else draft
            written = self.written(name) if draft is None else {}
            tuned = nested_options(written, options)
            merged = {**written, **tuned} if draft is None else dict(spec["config"])
            source = spec.get("source")
            images: Images | Callable[[ImageNeeds], Images]
            if source == "camera":
                images = await self.camera_images(inspection.camera)
            elif source == "upload":
                if upload is None:
                    raise HttpError(400, "BAD_REQUEST", "source 'upload' needs an 'image' part")
                images = upload_loader(upload)
            elif source == "result":
                images = self.result_loader(spec.get("result_id"))
            elif source == "recording":
                images = self.recording_loader(
                    inspection.camera, spec.get("frame"), inspection.frames
                )
            else:
                raise HttpError(
                    400,
                    "BAD_REQUEST",
                    "source must be 'camera', 'upload', 'result' or 'recording'",
                )
            extras: dict[str, Any] = {}
            loader = _with_extras(images, merged, extras)
            # The row this try leaves in the result log is marked as a try by its peer, with
            # its options (vision_server.results.tries): never a production result.
            reply = await self.service.inspect(
                InspectRequest(
                    name,
                    images=loader,
                    overlay=".png" if spec.get("overlay", True) else None,
                    options=tuned,
                    arrived=arrived,
                    deadline=arrived + self.settings.try_deadline_s,
                    peer=TRY_PEER_PREFIX + peer_of(request),
                    request_class="try",
                    prepared=draft,
                    config=None if draft is None else merged,
                    # A named user's try keeps their name (GET /api/results?operator=NAME).
                    operator=self._user(request) or "",
                ),
                admission=admission,
            )
        finally:
            admission.release()
        overlay = None
        if reply.overlay is not None and reply.overlay.encoded is not None:
            overlay = _data_url("image/png", reply.overlay.encoded)
        body = {
            "verdict": "pass" if reply.passed else "fail",
            "data": reply.data,
            "timing": {
                "inspect": round(reply.compute_ms, 3),
                "total": round(reply.total_ms, 3),
            },
            "overlay": overlay,
            "histogram": extras.get("histogram"),
            "source_image": None if overlay else extras.get("source_image"),
            "config_hash": reply.config_hash,
        }
        return web.json_response(body, dumps=dumps)

    async def _try_form(self, request: web.Request) -> tuple[dict[str, Any], bytes | None]:
        """The ``request`` JSON part and the ``image`` part of a try's multipart form."""
        if not request.content_type.startswith("multipart/"):
            raise HttpError(400, "BAD_REQUEST", "a try is multipart/form-data")
        try:
            reader = await request.multipart()
        except (ValueError, AssertionError) as exc:
            raise HttpError(400, "BAD_REQUEST", f"malformed multipart body: {exc}") from None
        spec: dict[str, Any] | None = None
        upload: bytes | None = None
        try:
            while True:
                part = await reader.next()
                if part is None:
                    break
                if not isinstance(part, BodyPartReader):
                    raise HttpError(400, "BAD_REQUEST", "nested multipart is not accepted")
                if part.name == "request":
                    raw = await _read_part(part, MAX_JSON_PART, "the request part")
                    spec = json_object(raw, "request")
                elif part.name == "image":
                    upload = await _read_part(part, self.settings.max_upload_bytes, "the image")
                else:
                    await part.release()
        except (ValueError, AssertionError, HttpProcessingError) as exc:
            # aiohttp's parser raises these on a malformed part (headers, boundary).
            raise HttpError(400, "BAD_REQUEST", f"malformed multipart body: {exc}") from None
        if spec is None:
            raise HttpError(400, "BAD_REQUEST", "the form has no 'request' part")
        return spec, upload

    async def camera_images(self, camera: str) -> Images | Callable[[ImageNeeds], Images]:
        """The camera's current frame through the service's capture; for a triggered camera
        or a sequence (a folder replay), the frame the last inspection took: a try must not
        take a frame the cell's next inspection would then miss."""
        assert self.live is not None
        catalog = self.service.catalog
        source = catalog.camera(camera)
        if source.source == "request":
            raise HttpError(
                404, "NOT_FOUND", f"camera {camera!r} gets its images from robots; upload one"
            )
        if not source.view_takes_frames:
            taken = self.live.last_taken(camera)
            if taken is None:
                raise HttpError(
                    404,
                    "NOT_FOUND",
                    f"camera {camera!r} ({source.source}): the console takes no frame of it and "
                    "no inspection has taken one yet; upload an image",
                )
            return taken
        reply = await self.service.capture(CaptureRequest(camera))
        return Images(reply.frames[0].color)

    def recording_loader(
        self, camera: str, frame: Any, count: int
    ) -> Callable[[ImageNeeds], Images]:
        """Frame ``frame`` of a recording camera's recording (and the next ones, up to the
        ``count`` frames the inspection takes, as from the camera), read in the worker without
        moving the camera's position: the cell's next inspection still gets its next frame.
        The pixel count comes from the recording's manifest and is checked before decoding."""
        if isinstance(frame, bool) or not isinstance(frame, int) or frame < 0:
            raise HttpError(400, "BAD_REQUEST", "frame must be an integer >= 0")
        source = self.service.catalog.camera(camera)
        if not isinstance(source, RecordingCamera):
            raise HttpError(
                400,
                "BAD_REQUEST",
                f"camera {camera!r} ({source.source}) is not a recording: source 'recording' "
                "tries a frame of a camera with source: recording",
            )
        recording = source.recording  # CAMERA_UNAVAILABLE when it cannot be read
        total = len(recording)
        if frame >= total:
            raise HttpError(
                400,
                "BAD_REQUEST",
                f"camera {camera!r}: its recording has {total} frames (0..{total - 1}), "
                f"no frame {frame}",
            )
        indices = range(frame, min(frame + max(1, count), total))

        def load(needs: ImageNeeds) -> Images:
            entry = recording.entries[frame]
            if entry.width * entry.height > needs.max_pixels:
                raise ImageTooLarge(
                    f"frame {frame} is {entry.width}x{entry.height}, more than "
                    f"{needs.max_pixels} pixels"
                )
            try:
                frames = [source.frame_at(i) for i in indices]
            except RecordingError as exc:
                raise InvalidArgument(str(exc)) from None
            depth = tuple(f.depth for f in frames if f.depth is not None)
            return Images(frames[0].color, depth if needs.depth else ())

        return load

    def result_loader(self, result_id: Any) -> Callable[[ImageNeeds], Images]:
        if not is_row_id(result_id):
            raise HttpError(400, "BAD_REQUEST", "result_id must be a result's id, an integer >= 1")
        row = self._row(result_id)
        path = row.image_path
        if path is None or not path.is_file():
            raise HttpError(404, "NOT_FOUND", f"result {result_id} has no stored image")
        return stored_image_loader(path)  # as an impact preview reads it

    async def save(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        self.service.catalog.inspection(name)
        # A save's options are a try's: no larger than a try's request part.
        body = await bounded_json(request, MAX_JSON_PART, self.settings.request_timeout_s)
        options = body.get("options")
        if not isinstance(options, dict) or not options:
            raise HttpError(400, "BAD_REQUEST", "options must be a non-empty JSON object")
        why = why_of(body)
        path = self.writable_config()
        async with self.save_lock:
            served = self.all_written()
            # The image size each running camera declares, which the saved ROI must fit as a
            # try's must (a simulated camera's size is its scene's, known once it is open).
            opened = http_save.opened_cameras(self.service.catalog)
            who = self.who(request)
            saved = await asyncio.to_thread(_save_file, path, name, options, opened, who, why)
            catalog = await self.reload_or_undo(saved)
        audit.info(
            "console: %s saved %s of %r as version %d (why: %s)",
            who,
            ", ".join(sorted(options)),
            name,
            saved.version.number,
            json.dumps(why),
        )
        return web.json_response(
            {
                "config_hash": catalog.config_hash,
                "version": saved.version.number,
                "also_changed": self.others_changed(name, served),
                "notes": list(catalog.notes),
            }
        )

    def user_name(self, given: str) -> str:
        """A configured user's name as the configuration writes it (and the result log keeps
        it) when ``given`` is that name in any case (names are unique ignoring case), else
        ``given``."""
        folded = given.casefold()
        return next((u.name for u in self.sessions.users if u.name.casefold() == folded), given)

    def writable_config(self) -> Path:
        """The configuration file the console may write (403 ``CONFIG_REFUSED`` when the
        server runs without one, or saving is off)."""
        if self.config_path is None:
            raise HttpError(403, "CONFIG_REFUSED", "this server runs without a configuration file")
        if not self.settings.allow_save:
            raise HttpError(403, "CONFIG_REFUSED", "saving is off (server.allow_reload: false)")
        return self.config_path

    async def reload_or_undo(self, saved: http_save.Saved, *, what: str = "") -> Any:
        """The server reloaded after the console wrote its configuration file: the new catalog.
        When the server cannot take the text though it validated (a camera that does not
        open), the old text goes back (so that file and server agree) and the write is
        refused: 422 ``CONFIG_REFUSED``, ``what`` before the cause."""
        try:
            return await self.service.reload()
        except CellvisionError as exc:
            await asyncio.to_thread(http_save.undo, saved)
            raise HttpError(422, "CONFIG_REFUSED", what + exc.message) from None

    def others_changed(self, name: str, served: Mapping[str, Any]) -> list[str]:
        """The inspections other than ``name`` whose configuration differs from ``served``
        (as written before a save): the reload applies the whole file, so hand edits made
        since the last reload go live with the save, and whoever saves is told which."""
        now = self.all_written()
        return [
            other
            for other in sorted(set(served) | set(now))
            if other != name and served.get(other) != now.get(other)
        ]

    def all_written(self) -> dict[str, Any]:
        """Every inspection as written in the configuration served (empty when unknown)."""
        written = getattr(self.service.catalog.tune, "written", None)
        return dict(written) if isinstance(written, Mapping) else {}

    # ------------------------------------------------------------------ results

    def result_log(self) -> Any:
        if self.service.results is None:
            raise HttpError(404, "NOT_FOUND", "this server keeps no result log")
        return self.service.results

    def _row(self, result_id: int) -> Any:
        row = self.result_log().get(result_id)
        if row is None:
            raise HttpError(404, "NOT_FOUND", f"no result {result_id}")
        return row

    async def results_list(self, request: web.Request) -> web.Response:
        query = request.query
        limit = int_param(query, "limit", 50, 1, 500)
        before = int_param(query, "before_id", None, 1, None)
        wanted = http_export.filters(query, self.user_name)
        rows = await asyncio.to_thread(
            self.result_log().query, limit=limit + 1, before_id=before, **wanted
        )
        more = len(rows) > limit
        rows = rows[:limit]
        return web.json_response(
            {
                "results": [_row_json(r) for r in rows],
                "next_before_id": rows[-1].id if more and rows else None,
            },
            dumps=dumps,
        )

    async def result(self, request: web.Request) -> web.Response:
        row = self._row(int(request.match_info["id"]))
        body = {
            **_row_json(row),
            "data": row.data,
            # The log keeps the inspection's own run (after the image was read, before the
            # reply), the figure the try panel calls "inspect".
            "timing": {"inspect": row.duration_ms},
            "error": row.error,
        }
        return web.json_response(body, dumps=dumps)

    async def result_image(self, request: web.Request) -> web.Response:
        """The stored input, or with ``overlay=1`` the stored overlay; 404 naming which is
        missing (the row's ``has_image`` / ``has_overlay`` say so beforehand)."""
        row = self._row(int(request.match_info["id"]))
        flag = request.query.get("overlay", "0")
        if flag not in ("0", "1"):
            raise HttpError(400, "BAD_REQUEST", f"overlay must be 0 or 1, got {flag!r}")
        if flag == "1":
            path = row.overlay_path
            if path is None or not path.is_file():
                raise HttpError(404, "NOT_FOUND", f"result {row.id} has no stored overlay")
        else:
            path = row.image_path
            if path is None or not path.is_file():
                raise HttpError(404, "NOT_FOUND", f"result {row.id} has no stored image")
        data = await asyncio.to_thread(path.read_bytes)
        return web.Response(body=data, content_type="image/png")

    async def stats(self, request: web.Request) -> web.Response:
        window = float_param(request.query, "window_s") or 86400.0
        if not 60 <= window <= 366 * 86400:
            raise HttpError(400, "BAD_REQUEST", "window_s must be in 60..31622400")
        wanted = request.query.get("inspection") or None
        names = [wanted] if wanted else sorted(self.service.catalog.inspections)
        log_ = self.result_log()
        cache: Any = log_
        if getattr(log_, "ids_in_commit_order", False):
            # Read once, then only the rows written since (results/timings_cache.py).
            if self._timings is None or self._timings.log is not log_:
                self._timings = TimingsCache(log_)
            cache = self._timings
        now = time.time()
        out = await asyncio.to_thread(lambda: [stats_of(cache, n, now, window) for n in names])
        return web.json_response({"window_s": window, "inspections": out}, dumps=dumps)

    async def metrics_text(self, request: web.Request) -> web.Response:
        assert self.metrics is not None
        return web.Response(body=self.metrics.render(), headers={"Content-Type": CONTENT_TYPE})


# ----------------------------------------------------------------------------- helpers


INTEGRATOR_ROUTES = (
    frozenset(
        {
            "/api/inspections/{name}/try",
            "/api/inspections/{name}/save",
            "/api/history/{version}/revert",
            IMPACT_PATH,
            TRAIN_PATH,
            "/api/online/reset",
        }
    )
    | BUILD_INTEGRATOR_ROUTES
)
"""What changes an inspection or runs one with other options: the integrator's and the
admin's, not the operator's (who views, and answers operator calls)."""


def required_role(request: web.Request) -> Role:
    """The least role that may make ``request``."""
    route = request.match_info.route.resource
    canonical = route.canonical if route is not None else request.path
    return "integrator" if canonical in INTEGRATOR_ROUTES else "operator"


def parameters(config: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The numeric keys of an inspection's configuration the page may tune (nested: dotted):
    only keys a try's options and a save both take, never one fixed by the configuration
    (``number``, ``output``, ...: a request cannot change them, the save refuses them)."""
    out: list[dict[str, Any]] = []
    measure = config.get("measure")
    for key, value in config.items():
        # roi has its own editor; frames changes what is acquired, not what is measured.
        if key in ("roi", "frames") or key in FIXED_BY_THE_CONFIGURATION:
            continue
        if isinstance(value, dict):
            for sub, inner in value.items():
                if _number(inner):
                    out.append(_parameter(f"{key}.{sub}", inner, None, None))
        elif _number(value):
            low, high = _range(key, measure)
            out.append(_parameter(key, value, low, high))
    return out


def _parameter(key: str, value: Any, low: float | None, high: float | None) -> dict[str, Any]:
    step: float | None = 1 if isinstance(value, int) else None
    if key in PARAMETER_RANGES:
        low, high, step = PARAMETER_RANGES[key]
    elif high is not None and low is not None and high - low <= 2:
        step = 0.01
    return {"key": key, "value": value, "min": low, "max": high, "step": step}


def _range(key: str, measure: Any) -> tuple[float | None, float | None]:
    if key in ("min", "max") and isinstance(measure, str):
        from ..inspections import MEASURE_RANGES

        if measure in MEASURE_RANGES:
            low, high, _ = MEASURE_RANGES[measure]
            return low, (None if math.isinf(high) else high)
    return None, None


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _save_file(
    path: Path,
    name: str,
    options: Mapping[str, Any],
    opened: Mapping[str, Any],
    who: str,
    why: str,
) -> http_save.Saved:
    """Edit, validate and write the configuration file, recorded as ``who``'s version for
    ``why`` (in a thread). HttpError CONFIG_REFUSED naming file, line and key path, or why the
    file cannot be written."""
    try:
        return http_save.save(path, name, options, opened=opened, who=who, why=why)
    except (http_save.SaveRefused, http_save.ConfigError) as exc:
        raise HttpError(422, "CONFIG_REFUSED", str(exc)) from None
    except (OSError, UnicodeError) as exc:
        raise HttpError(500, "CONFIG_REFUSED", f"cannot save {path.name}: {exc}") from None


def _with_extras(
    images: Images | Callable[[ImageNeeds], Images],
    config: Mapping[str, Any],
    extras: dict[str, Any],
) -> Callable[[ImageNeeds], Images]:
    """A loader that also computes, in the worker, what the try panel shows besides the
    service's reply: the ROI's grey-level histogram and the source image."""

    def load(needs: ImageNeeds) -> Images:
        loaded = images if isinstance(images, Images) else images(needs)
        check_images(loaded, needs)
        color = loaded.color
        grey = color if color.ndim == 2 else cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
        if config.get("type") == "presence":
            extras["histogram"] = _histogram(grey, config.get("roi"), config.get("threshold"))
        ok, jpeg = cv2.imencode(".jpg", color, [cv2.IMWRITE_JPEG_QUALITY, 85])
        if ok:
            extras["source_image"] = _data_url("image/jpeg", bytes(jpeg.tobytes()))
        return loaded

    return load


def _histogram(grey: Any, roi: Any, threshold: Any) -> dict[str, Any]:
    height, width = grey.shape[:2]
    x, y, w, h = 0, 0, width, height
    if isinstance(roi, list) and len(roi) == 4 and all(_number(v) for v in roi):
        x, y, w, h = (int(v) for v in roi)
    patch = grey[max(y, 0) : max(y + h, 0), max(x, 0) : max(x + w, 0)]
    bins = np.bincount(patch.ravel(), minlength=256)[:256] if patch.size else np.zeros(256)
    return {
        "bins": [int(b) for b in bins],
        "threshold": threshold if _number(threshold) else None,
    }


STATS_BUCKETS = 24


def stats_of(log_: Any, name: str, now: float, window: float) -> dict[str, Any]:
    """One inspection's statistics over the ``window`` seconds before ``now`` (Unix seconds):
    count, pass rate, duration p50/p99 in ms, and the same per bucket of the window."""
    times, passed, durations = log_.timings(inspection=name, since=now - window)
    start = now - window
    bucket_s = window / STATS_BUCKETS
    # The rows come oldest first: each bucket is one slice, found by bisection.
    edges = np.searchsorted(times, start + bucket_s * np.arange(STATS_BUCKETS + 1), side="left")
    edges[-1] = len(times)
    series = [
        {"t": start + index * bucket_s, **_summary(passed[lo:hi], durations[lo:hi])}
        for index, (lo, hi) in enumerate(zip(edges[:-1], edges[1:], strict=True))
    ]
    summary = _summary(passed, durations)
    passes = int(np.count_nonzero(passed))
    return {
        "name": name,
        "count": summary["count"],
        "pass": passes,
        "fail": len(passed) - passes,
        "pass_rate": summary["pass_rate"],
        "p50_ms": summary["p50_ms"],
        "p99_ms": summary["p99_ms"],
        "bucket_s": bucket_s,
        "series": series,
    }


def _summary(passed: np.ndarray, durations: np.ndarray) -> dict[str, Any]:
    if len(passed) == 0:
        return {"count": 0, "pass_rate": None, "p50_ms": None, "p99_ms": None}
    p50, p99 = np.percentile(durations, [50, 99])
    return {
        "count": len(passed),
        "pass_rate": round(float(np.count_nonzero(passed)) / len(passed), 4),
        "p50_ms": round(float(p50), 3),
        "p99_ms": round(float(p99), 3),
    }


def _row_json(row: Any) -> dict[str, Any]:
    return {
        "id": row.id,
        "time": row.time,
        "inspection": row.inspection,
        "camera": row.camera,
        "passed": row.passed,
        "duration_ms": row.duration_ms,
        "peer": row.peer,
        "try": row.is_try,
        "request_id": row.request_id,
        "config_hash": row.config_hash,
        "has_image": row.image_path is not None and row.image_path.is_file(),
        "has_overlay": row.overlay_path is not None and row.overlay_path.is_file(),
        "operator": None if row.operator is None else row.operator.to_json(),
    }


async def _read_part(part: BodyPartReader, limit: int, what: str) -> bytes:
    chunks: list[bytes] = []
    size = 0
    while True:
        chunk = await part.read_chunk(256 * 1024)
        if not chunk:
            return b"".join(chunks)
        size += len(chunk)
        if size > limit:
            raise ImageTooLarge(f"{what} has more than {limit} bytes")
        chunks.append(chunk)


def _data_url(mime: str, data: bytes) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


__all__ = ["HTTP_STATUS", "HttpError", "HttpFrontend", "nested_options", "parameters"]
