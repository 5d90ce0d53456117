"""A test double of the console's JSON API, for the console's own browser tests.

It serves the real static files (``vision_server.console.static_dir()``) and answers every
``/api/*`` route of docs/console.md ("API") from fixed sample data defined below, recording each
request so that a test can check what the page sent. It is NOT the vision server: no inspection
service, no cameras, no result log. The tests against the real server come with the server's
HTTP front-end; this stub only lets the page be tested (and photographed) before that exists.

Sample data (all fixed, built at start-up, deterministic):

- cameras ``qc`` (source sim, 1024x768, the simulated cell's QC camera image with a dark magnet
  drawn at ``MAGNET``, a frame counter written on each frame so the live view visibly changes)
  and ``tool`` (source request, no image yet: frame.jpg answers 404), plus any ``extra_cameras``
  a test passes (a hostile name, for instance).
- inspections ``magnet_check`` (presence, ROI ``[486, 236, 50, 60]``, threshold 90, min 0.25) and
  ``cap_locate`` (locate, no ROI). A try computes the dark fraction and the 256-bin histogram of
  the QC image inside the requested ROI, so that moving the ROI changes the numbers; it stands in
  for the presence inspection only as far as the page can tell.
- 120 results (ids 1..120, two inspections, every seventh a failure, peers ``10.0.0.7:…`` and
  ``10.0.0.8:…``), newest has the highest id and time ``NOW``.
- save refuses a ``threshold`` above 255 with a validator-style message naming file, line and
  key path; other edits answer a fixed hash and version number.

Importable as ``console_stub`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import secrets
import threading
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from aiohttp import web

from vision_server.console import static_dir

REPO_ROOT = Path(__file__).resolve().parents[2]
NOW = 1_760_000_000.0  # the newest sample result's time, Unix seconds
MAGNET = (496, 246, 30, 40)  # x, y, w, h of the dark magnet drawn into the QC image
COOKIE = "cellvision_session"
JsonDict = dict[str, Any]


@dataclass(frozen=True)
class Recorded:
    """One API request the stub answered: method, path, query and the JSON it carried (the
    body, or the ``request`` part of a multipart try)."""

    method: str
    path: str
    query: dict[str, str]
    body: Any


@dataclass
class ConsoleStub:
    """The running stub: its base ``url`` and the requests it has recorded."""

    url: str = ""
    token: str | None = None
    extra_cameras: list[JsonDict] = field(default_factory=list)
    requests: list[Recorded] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def recorded(self, path: str, method: str | None = None) -> list[Recorded]:
        """The requests to ``path`` (exact), oldest first."""
        with self._lock:
            return [
                r
                for r in self.requests
                if r.path == path and (method is None or r.method == method)
            ]

    def record(self, entry: Recorded) -> None:
        with self._lock:
            self.requests.append(entry)


# -- sample data -----------------------------------------------------------------------------


def _qc_image() -> np.ndarray:
    """The simulated cell's QC camera view (grey, 768x1024) with a magnet in its slot."""
    from simulation.cell import SimCell

    cell = SimCell.from_yaml(REPO_ROOT / "examples" / "scenes" / "grundfos_cell.yaml")
    color = cell.render("qc_camera").color
    grey = color if color.ndim == 2 else cv2.cvtColor(color, cv2.COLOR_BGR2GRAY)
    grey = grey.copy()
    x, y, w, h = MAGNET
    grey[y : y + h, x : x + w] = 38
    return grey


INSPECTIONS: list[JsonDict] = [
    {
        "name": "magnet_check",
        "type": "presence",
        "camera": "qc",
        "camera_source": "sim",
        "depth": False,
        "config": {
            "name": "magnet_check",
            "type": "presence",
            "camera": "qc",
            "roi": [486, 236, 50, 60],
            "measure": "dark_fraction",
            "threshold": 90,
            "min": 0.25,
        },
        "parameters": [
            {"key": "threshold", "value": 90, "min": 0, "max": 255, "step": 1},
            {"key": "min", "value": 0.25, "min": 0, "max": 1, "step": 0.01},
        ],
        "roi": [486, 236, 50, 60],
    },
    {
        "name": "cap_locate",
        "type": "locate",
        "camera": "tool",
        "camera_source": "request",
        "depth": False,
        "config": {
            "name": "cap_locate",
            "type": "locate",
            "camera": "tool",
            "method": "circle",
            "circle": {"min_radius_px": 60, "max_radius_px": 100, "polarity": "bright"},
            "min_count": 1,
            "max_count": 10,
        },
        "parameters": [
            {"key": "circle.min_radius_px", "value": 60, "min": 1, "max": 400, "step": 1},
            {"key": "circle.max_radius_px", "value": 100, "min": 1, "max": 400, "step": 1},
        ],
        "roi": None,
    },
]


def _sample_results() -> list[JsonDict]:
    rows = []
    for i in range(1, 121):
        inspection = "magnet_check" if i % 3 else "cap_locate"
        passed = i % 7 != 0
        rows.append(
            {
                "id": i,
                "time": NOW - (120 - i) * 37.0,
                "inspection": inspection,
                "camera": "qc" if inspection == "magnet_check" else "tool",
                "passed": passed,
                "duration_ms": round(3.1 + (i % 5) * 0.45 + (0 if passed else 1.2), 2),
                "peer": f"10.0.0.{7 + i % 2}:{41000 + i % 2}",
                "request_id": 1000 + i,
                "config_hash": "5f1c9e0a7b3d" + "0" * 52,
                "has_image": not passed or i % 10 == 0,
                "has_overlay": not passed or i % 10 == 0,
                "data": {"measure": "dark_fraction", "value": 0.41 if passed else 0.02, "min": 0.25}
                if inspection == "magnet_check"
                else {"count": 1 if passed else 0},
                "timing": {"queue": 0.08, "decode": 0.9, "inspect": 1.7, "total": 3.4},
            }
        )
    return rows


SERVER_INFO: JsonDict = {
    "name": "grundfos-cell",
    "version": "0.1.0",
    "protocol": "1.0",
    "config_file": "/etc/cellvision/cell.yaml",
    "config_hash": "5f1c9e0a7b3d" + "0" * 52,
    "started_at": NOW - 3 * 3600 - 754,
    "uptime_s": 3 * 3600 + 754.0,
    "listen": "127.0.0.1:7878",
    "health": {
        "status": "ok",
        "checks": [
            {"name": "result log", "ok": True, "message": ""},
            {"name": "camera qc", "ok": True, "message": ""},
        ],
    },
    "pool": {
        "workers": 2,
        "in_flight": 1,
        "max_in_flight": 32,
        "queued": 0,
        "queue_depth": 16,
        "busy_count": 0,
        "answered": 4812,
    },
    "connections": [
        {"peer": "10.0.0.7:41000", "requests": 3120, "in_flight": 1, "since": NOW - 9000},
        {"peer": "10.0.0.8:41001", "requests": 1692, "in_flight": 0, "since": NOW - 5400},
    ],
    "reloads": [
        {"time": NOW - 5000, "ok": True, "config_hash": "5f1c9e0a7b3d", "message": "3 changed"},
        {
            "time": NOW - 5200,
            "ok": False,
            "config_hash": None,
            "message": "cell.yaml:52: inspections[1].min: expected a number, got 'high'",
        },
    ],
}


# -- the app ---------------------------------------------------------------------------------


def _error(status: int, code: str, message: str) -> web.Response:
    return web.json_response({"error": {"code": code, "message": message}}, status=status)


def _data_url(mime: str, data: bytes) -> str:
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


class _App:
    def __init__(self, stub: ConsoleStub) -> None:
        self.stub = stub
        self.sessions: set[str] = set()
        self.qc = _qc_image()
        self.frames = 0
        self.results = _sample_results()

    # requests and auth

    @web.middleware
    async def guard(self, request: web.Request, handler: Any) -> web.StreamResponse:
        path = request.path
        if path.startswith("/api/"):
            body: Any = None
            if request.content_type == "application/json" and request.can_read_body:
                try:
                    body = await request.json()
                except ValueError:
                    return _error(400, "BAD_REQUEST", "the body is not JSON")
            self.stub.record(Recorded(request.method, path, dict(request.query), body))
            if (
                self.stub.token is not None
                and path != "/api/login"
                and request.cookies.get(COOKIE) not in self.sessions
            ):
                return _error(401, "UNAUTHORIZED", "sign in with the server's token")
        return await handler(request)

    async def login(self, request: web.Request) -> web.Response:
        body = await request.json()
        if self.stub.token is None or body.get("token") != self.stub.token:
            return _error(401, "UNAUTHORIZED", "that token is not valid")
        session = secrets.token_urlsafe(16)
        self.sessions.add(session)
        response = web.json_response({"ok": True})
        response.set_cookie(COOKIE, session, httponly=True, samesite="Strict", path="/")
        return response

    async def logout(self, request: web.Request) -> web.Response:
        self.sessions.discard(request.cookies.get(COOKIE, ""))
        response = web.json_response({"ok": True})
        response.del_cookie(COOKIE, path="/")
        return response

    # pages

    async def index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(static_dir() / "index.html")

    async def server(self, request: web.Request) -> web.Response:
        return web.json_response({**SERVER_INFO, "auth_required": self.stub.token is not None})

    async def cameras(self, request: web.Request) -> web.Response:
        cameras = [
            {"name": "qc", "source": "sim", "depth": False, "width": 1024, "height": 768,
             "fps": 14.9, "view_fps": 10, "frame_age_s": 0.04},
            {"name": "tool", "source": "request", "depth": False, "width": 1024, "height": 768,
             "fps": None, "view_fps": None, "frame_age_s": None},
            *self.stub.extra_cameras,
        ]  # fmt: skip
        return web.json_response({"cameras": cameras})

    async def frame(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name != "qc":
            return _error(404, "NO_FRAME", f"camera {name!r} has no image yet")
        self.frames += 1
        image = cv2.cvtColor(self.qc, cv2.COLOR_GRAY2BGR)
        cv2.putText(image, f"frame {self.frames}", (20, 740), cv2.FONT_HERSHEY_SIMPLEX, 0.8,
                    (255, 255, 255), 2)  # fmt: skip
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 80])
        assert ok
        return web.Response(body=jpeg.tobytes(), content_type="image/jpeg")

    async def inspections(self, request: web.Request) -> web.Response:
        return web.json_response({"inspections": INSPECTIONS})

    async def try_(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        inspection = next((i for i in INSPECTIONS if i["name"] == name), None)
        if inspection is None:
            return _error(404, "UNKNOWN_INSPECTION", f"no inspection named {name!r}")
        reader = await request.multipart()
        spec: JsonDict | None = None
        upload: bytes | None = None
        async for part in reader:
            if part.name == "request":
                spec = json.loads(await part.read())  # type: ignore[union-attr]
            elif part.name == "image":
                upload = bytes(await part.read())  # type: ignore[union-attr]
        if spec is None:
            return _error(400, "BAD_REQUEST", "the multipart body has no 'request' part")
        self.stub.record(Recorded("POST", request.path, {}, spec))
        grey = self.qc
        if spec.get("source") == "upload":
            decoded = cv2.imdecode(np.frombuffer(upload or b"", np.uint8), cv2.IMREAD_GRAYSCALE)
            if decoded is None:
                return _error(400, "BAD_IMAGE", "the uploaded file is not an image")
            grey = decoded
        return web.json_response(_try_outcome(inspection, spec.get("options") or {}, grey))

    async def save(self, request: web.Request) -> web.Response:
        body = await request.json()
        options: Mapping[str, Any] = body.get("options") or {}
        threshold = options.get("threshold")
        if isinstance(threshold, int | float) and threshold > 255:
            return _error(
                422,
                "CONFIG_REFUSED",
                "/etc/cellvision/cell.yaml:53: inspections[1].threshold: "
                f"expected a grey level 0..255, got {threshold}",
            )
        return web.json_response({"config_hash": "a41b7c2d9e0f" + "1" * 52, "version": 2})

    async def results_list(self, request: web.Request) -> web.Response:
        q = request.query
        rows = [r for r in reversed(self.results)]
        if q.get("inspection"):
            rows = [r for r in rows if r["inspection"] == q["inspection"]]
        if q.get("verdict") in ("pass", "fail"):
            rows = [r for r in rows if r["passed"] == (q["verdict"] == "pass")]
        if q.get("since"):
            rows = [r for r in rows if r["time"] >= float(q["since"])]
        if q.get("peer"):
            rows = [r for r in rows if r["peer"].startswith(q["peer"])]
        if q.get("before_id"):
            rows = [r for r in rows if r["id"] < int(q["before_id"])]
        limit = int(q.get("limit", "50"))
        page = rows[:limit]
        next_before = page[-1]["id"] if len(rows) > limit else None
        listed = [{k: v for k, v in r.items() if k not in ("data", "timing")} for r in page]
        return web.json_response({"results": listed, "next_before_id": next_before})

    async def result(self, request: web.Request) -> web.Response:
        wanted = int(request.match_info["id"])
        row = next((r for r in self.results if r["id"] == wanted), None)
        if row is None:
            return _error(404, "NO_RESULT", f"no result {wanted}")
        return web.json_response(row)

    async def result_image(self, request: web.Request) -> web.Response:
        wanted = int(request.match_info["id"])
        row = next((r for r in self.results if r["id"] == wanted), None)
        if row is None or not row["has_image"]:
            return _error(404, "NO_IMAGE", f"result {wanted} has no stored image")
        outcome_png = _overlay(self.qc, [486, 236, 50, 60], passed=bool(row["passed"]))
        return web.Response(body=outcome_png, content_type="image/png")

    async def stats(self, request: web.Request) -> web.Response:
        window_s = float(request.query.get("window_s", "86400"))
        names = (
            [request.query["inspection"]]
            if request.query.get("inspection")
            else [i["name"] for i in INSPECTIONS]
        )
        out = []
        for k, name in enumerate(names):
            rows = [r for r in self.results if r["inspection"] == name]
            passed = sum(1 for r in rows if r["passed"])
            series = [
                {
                    "t": NOW - window_s + b * window_s / 24,
                    "count": 5,
                    "pass_rate": 1.0 if (b + k) % 6 else 0.8,
                    "p50_ms": 3.2 + 0.3 * ((b * 7 + k) % 4),
                    "p99_ms": 5.5 + 0.9 * ((b * 3 + k) % 5),
                }
                for b in range(24)
            ]
            out.append(
                {
                    "name": name,
                    "count": len(rows),
                    "pass": passed,
                    "fail": len(rows) - passed,
                    "pass_rate": passed / len(rows) if rows else None,
                    "p50_ms": 3.6,
                    "p99_ms": 8.9,
                    "bucket_s": window_s / 24,
                    "series": series,
                }
            )
        return web.json_response({"window_s": window_s, "inspections": out})

    def build(self) -> web.Application:
        app = web.Application(middlewares=[self.guard], client_max_size=8 * 1024 * 1024)
        app.router.add_get("/", self.index)
        app.router.add_static("/static/", static_dir())
        app.router.add_post("/api/login", self.login)
        app.router.add_post("/api/logout", self.logout)
        app.router.add_get("/api/server", self.server)
        app.router.add_get("/api/cameras", self.cameras)
        app.router.add_get("/api/cameras/{name}/frame.jpg", self.frame)
        app.router.add_get("/api/inspections", self.inspections)
        app.router.add_post("/api/inspections/{name}/try", self.try_)
        app.router.add_post("/api/inspections/{name}/save", self.save)
        app.router.add_get("/api/results", self.results_list)
        app.router.add_get("/api/results/{id:\\d+}", self.result)
        app.router.add_get("/api/results/{id:\\d+}/image.png", self.result_image)
        app.router.add_get("/api/stats", self.stats)
        return app


def _overlay(grey: np.ndarray, roi: list[int], *, passed: bool) -> bytes:
    """The QC image with the ROI outlined in the verdict's colour, as PNG bytes."""
    image = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    x, y, w, h = roi
    colour = (60, 170, 60) if passed else (40, 40, 220)
    cv2.rectangle(image, (x, y), (x + w, y + h), colour, 2)
    cv2.putText(image, "PASS" if passed else "FAIL", (x, max(20, y - 10)),
                cv2.FONT_HERSHEY_SIMPLEX, 0.8, colour, 2)  # fmt: skip
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


def _try_outcome(inspection: JsonDict, options: Mapping[str, Any], grey: np.ndarray) -> JsonDict:
    """What the stub answers to a try: the dark fraction and histogram in the requested ROI."""
    config = inspection["config"]
    roi = options.get("roi", inspection["roi"])
    threshold = float(options.get("threshold", config.get("threshold", 128)))
    low = float(options.get("min", config.get("min", 0.0)))
    ok, jpeg = cv2.imencode(".jpg", grey, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    if inspection["type"] != "presence" or roi is None:
        return {
            "verdict": "fail",
            "data": {"count": 0},
            "timing": {"decode": 1.1, "inspect": 4.2, "total": 5.6},
            "overlay": None,
            "histogram": None,
            "source_image": _data_url("image/jpeg", jpeg.tobytes()),
        }
    x, y, w, h = (int(v) for v in roi)
    patch = grey[y : y + h, x : x + w]
    value = float((patch < threshold).mean()) if patch.size else 0.0
    passed = value >= low
    bins = np.bincount(patch.ravel(), minlength=256)[:256] if patch.size else np.zeros(256)
    return {
        "verdict": "pass" if passed else "fail",
        "data": {"measure": "dark_fraction", "value": round(value, 4), "min": low, "max": None},
        "timing": {"decode": 0.9, "inspect": 0.6, "overlay": 0.8, "total": 2.4},
        "overlay": _data_url("image/png", _overlay(grey, [x, y, w, h], passed=passed)),
        "histogram": {"bins": [int(b) for b in bins], "threshold": threshold},
        "source_image": _data_url("image/jpeg", jpeg.tobytes()),
    }


@contextlib.contextmanager
def console_stub(
    *, token: str | None = None, extra_cameras: list[JsonDict] | None = None
) -> Iterator[ConsoleStub]:
    """The stub on 127.0.0.1, port 0, on its own event loop in a thread."""
    stub = ConsoleStub(token=token, extra_cameras=list(extra_cameras or []))
    app = _App(stub).build()
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="console-stub", daemon=True)
    thread.start()
    runner = web.AppRunner(app, access_log=None)

    async def start() -> str:
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        host, port = runner.addresses[0][:2]
        return f"http://{host}:{port}"

    try:
        stub.url = asyncio.run_coroutine_threadsafe(start(), loop).result(30.0)
        yield stub
    finally:
        asyncio.run_coroutine_threadsafe(runner.cleanup(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()
