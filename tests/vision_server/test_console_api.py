"""The web console's JSON API (docs/console.md) against the real server with the example cell:
real sockets on loopback, port 0, the configuration file's runtime (save and reload are real).
"""

from __future__ import annotations

import http.client
import struct
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import cv2
import numpy as np
import pytest
from console_server import (
    TOKEN,
    Browserless,
    RunningConsole,
    console_server,
    example_config,
    multipart,
)

from vision_server.frontends.http_auth import COOKIE
from vision_server.results import ResultEntry


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


@pytest.fixture
def client(server: RunningConsole) -> Browserless:
    c = Browserless(server.url)
    assert c.login().status == 200
    return c


def raw_get(server: RunningConsole, path: str) -> tuple[int, bytes]:
    """A GET of ``path`` exactly as written (no client-side normalisation of ``..``)."""
    parts = urlsplit(server.url)
    conn = http.client.HTTPConnection(parts.hostname or "", parts.port, timeout=30)
    try:
        conn.putrequest("GET", path, skip_accept_encoding=True)
        conn.endheaders()
        resp = conn.getresponse()
        return resp.status, resp.read()
    finally:
        conn.close()


# ----------------------------------------------------------------------------- auth


def test_without_a_session_only_the_page_answers(server: RunningConsole) -> None:
    anonymous = Browserless(server.url)
    assert anonymous.get("/").status == 200
    assert anonymous.get("/static/console.js").status == 200
    for path in ("/api/server", "/api/cameras", "/api/inspections", "/api/results", "/metrics"):
        reply = anonymous.get(path)
        assert reply.status == 401, path
        assert reply.json()["error"]["code"] == "UNAUTHORIZED"
    assert anonymous.get("/api/cameras/qc/frame.jpg").status == 401
    assert anonymous.get("/api/results/1/image.png").status == 401
    assert (
        anonymous.post_json("/api/inspections/magnet_check/save", {"options": {"min": 0.1}}).status
        == 401
    )
    assert anonymous.try_("magnet_check", {"source": "camera"}).status == 401


def test_wrong_token_is_refused_and_right_one_gives_a_strict_httponly_cookie(
    server: RunningConsole,
) -> None:
    c = Browserless(server.url)
    wrong = c.login("not-the-token")
    assert wrong.status == 401
    assert "Set-Cookie" not in wrong.headers
    assert c.post_json("/api/login", {"token": 5}).status == 401
    ok = c.login()
    assert ok.status == 200
    cookie = ok.headers["Set-Cookie"]
    assert cookie.startswith(COOKIE + "=")
    assert "HttpOnly" in cookie
    assert "SameSite=Strict" in cookie
    assert "Path=/" in cookie
    assert TOKEN not in cookie  # an HMAC of it, never the token
    assert c.get("/api/server").status == 200
    assert c.post_json("/api/logout", {}).status == 200
    assert c.get("/api/server").status == 401


def test_a_forged_cookie_is_refused(server: RunningConsole) -> None:
    c = Browserless(server.url)
    reply = c.request("GET", "/api/server", headers={"Cookie": f"{COOKIE}=abc.{'0' * 64}"})
    assert reply.status == 401


def test_metrics_take_a_bearer_token(server: RunningConsole) -> None:
    c = Browserless(server.url)
    assert c.request("GET", "/metrics", headers={"Authorization": "Bearer nope"}).status == 401
    reply = c.request("GET", "/metrics", headers={"Authorization": f"Bearer {TOKEN}"})
    assert reply.status == 200
    assert b"cellvision_busy_total" in reply.body


# ----------------------------------------------------------------------------- try


def test_try_on_the_camera_frame_and_an_roi_that_changes_the_verdict(client: Browserless) -> None:
    configured = client.try_("magnet_check", {"source": "camera", "options": {}, "overlay": True})
    assert configured.status == 200, configured.body
    body = configured.json()
    assert body["verdict"] == "fail"  # the example scene's rotor has no magnet yet
    assert body["overlay"].startswith("data:image/png;base64,")
    assert len(body["histogram"]["bins"]) == 256
    assert sum(body["histogram"]["bins"]) == 50 * 60
    assert body["histogram"]["threshold"] == 90
    # The same inspection on a dark part of the scene: the ROI option changes the verdict.
    moved = client.try_("magnet_check", {"source": "camera", "options": {"roi": [10, 10, 50, 60]}})
    assert moved.status == 200, moved.body
    assert moved.json()["verdict"] == "pass"


def test_try_on_an_uploaded_png_matches_the_camera(client: Browserless) -> None:
    frame = client.get("/api/cameras/qc/frame.jpg")
    assert frame.status == 200
    assert frame.headers["Content-Type"] == "image/jpeg"
    image = cv2.imdecode(np.frombuffer(frame.body, np.uint8), cv2.IMREAD_COLOR)
    png = cv2.imencode(".png", image)[1].tobytes()
    dark = client.try_(
        "magnet_check", {"source": "upload", "options": {"roi": [10, 10, 50, 60]}}, png
    )
    assert dark.status == 200, dark.body
    assert dark.json()["verdict"] == "pass"
    assert client.try_("magnet_check", {"source": "upload"}, png).json()["verdict"] == "fail"


def test_try_options_are_validated_like_the_configuration(client: Browserless) -> None:
    reply = client.try_("magnet_check", {"source": "camera", "options": {"threshold": "high"}})
    assert reply.status == 400
    error = reply.json()["error"]
    assert error["code"] == "INVALID_ARGUMENT"
    assert "threshold" in error["message"]
    unknown = client.try_("no_such", {"source": "camera"})
    assert unknown.status == 404
    assert unknown.json()["error"]["code"] == "UNKNOWN_INSPECTION"


# ----------------------------------------------------------------------------- results


def test_results_list_detail_and_image(client: Browserless) -> None:
    window = "/api/stats?inspection=magnet_check&window_s=3600"
    counted = client.get(window).json()["inspections"][0]["count"]
    assert client.try_("magnet_check", {"source": "camera"}).json()["verdict"] == "fail"
    listed = client.get("/api/results?inspection=magnet_check&verdict=fail&limit=1")
    assert listed.status == 200
    rows = listed.json()["results"]
    assert len(rows) == 1
    assert rows[0]["inspection"] == "magnet_check"
    assert not rows[0]["passed"]
    assert rows[0]["peer"].startswith("console 127.0.0.1:")
    newest = rows[0]["id"]
    older = client.get(f"/api/results?before_id={newest}&limit=500").json()["results"]
    assert all(r["id"] < newest for r in older)
    detail = client.get(f"/api/results/{newest}").json()
    assert detail["data"]["measure"] == "dark_fraction"
    assert rows[0]["has_image"]  # store_images: failures
    image = client.get(f"/api/results/{newest}/image.png?overlay=1")
    assert image.status == 200
    assert image.body.startswith(b"\x89PNG")
    assert client.get("/api/results/999999").status == 404
    assert client.get("/api/results?verdict=maybe").status == 400
    assert client.get("/api/results?limit=x").status == 400
    # The try is listed (marked as one) but no statistic counts it (docs/console.md).
    assert rows[0]["try"] is True
    assert client.get(window).json()["inspections"][0]["count"] == counted


def test_a_row_opens_its_stored_overlay_and_says_when_it_has_none(
    server: RunningConsole, client: Browserless
) -> None:
    # The page's try may not ask for an overlay: the log draws and keeps one all the same.
    reply = client.try_("magnet_check", {"source": "camera", "overlay": False})
    assert reply.json()["verdict"] == "fail"
    assert reply.json()["overlay"] is None
    row = client.get("/api/results?inspection=magnet_check&verdict=fail&limit=1").json()
    newest = row["results"][0]
    assert newest["has_image"]
    assert newest["has_overlay"]
    raw = client.get(f"/api/results/{newest['id']}/image.png")
    drawn = client.get(f"/api/results/{newest['id']}/image.png?overlay=1")
    assert raw.status == drawn.status == 200
    assert drawn.headers["Content-Type"] == "image/png"
    inp = cv2.imdecode(np.frombuffer(raw.body, np.uint8), cv2.IMREAD_COLOR)
    over = cv2.imdecode(np.frombuffer(drawn.body, np.uint8), cv2.IMREAD_COLOR)
    assert inp.shape == over.shape
    # The failing ROI [486, 236, 50, 60] is drawn in red on the overlay, not on the input.
    assert tuple(over[236, 500]) == (0, 0, 255)
    assert tuple(inp[236, 500]) != (0, 0, 255)
    assert client.get(f"/api/results/{newest['id']}/image.png?overlay=2").status == 400

    # A row stored without an overlay (a log written before overlays were kept).
    log = server.app.service.results
    assert log is not None
    bare = log.record(
        ResultEntry(
            time=time.time(),
            inspection="magnet_check",
            camera="qc",
            passed=False,
            data={},
            duration_ms=1.0,
            config_hash="old",
            image=inp,
        )
    )
    listed = client.get(f"/api/results?before_id={bare + 1}&limit=1").json()["results"]
    assert listed[0]["id"] == bare
    assert listed[0]["has_image"]
    assert not listed[0]["has_overlay"]
    missing = client.get(f"/api/results/{bare}/image.png?overlay=1")
    assert missing.status == 404
    assert missing.json()["error"]["message"] == f"result {bare} has no stored overlay"
    assert client.get(f"/api/results/{bare}/image.png").status == 200


def test_a_try_on_a_stored_result(client: Browserless) -> None:
    client.try_("magnet_check", {"source": "camera"})
    newest = client.get("/api/results?verdict=fail&limit=1").json()["results"][0]["id"]
    reply = client.try_("magnet_check", {"source": "result", "result_id": newest})
    assert reply.status == 200, reply.body
    assert reply.json()["verdict"] == "fail"
    assert client.try_("magnet_check", {"source": "result", "result_id": 10**9}).status == 404


# ----------------------------------------------------------------------------- bad requests


def png_header_only(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` pixels (and no image data)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 64)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def test_malformed_requests_get_4xx_json(client: Browserless) -> None:
    bad_json = client.request(
        "POST", "/api/login", b"{not json", {"Content-Type": "application/json"}
    )
    assert bad_json.status == 400
    assert bad_json.json()["error"]["code"] == "BAD_REQUEST"
    not_multipart = client.request(
        "POST", "/api/inspections/magnet_check/try", b"{}", {"Content-Type": "application/json"}
    )
    assert not_multipart.status == 400
    garbage = client.request(
        "POST",
        "/api/inspections/magnet_check/try",
        b"--zz\r\ngarbage",
        {"Content-Type": "multipart/form-data; boundary=zz"},
    )
    assert 400 <= garbage.status < 500
    assert "error" in garbage.json()
    body, ctype = multipart({"request": b"[1, 2"}, {})
    broken = client.request(
        "POST", "/api/inspections/magnet_check/try", body, {"Content-Type": ctype}
    )
    assert broken.status == 400
    no_image = client.try_("magnet_check", {"source": "upload"})
    assert no_image.status == 400
    not_image = client.try_("magnet_check", {"source": "upload"}, b"GIF89a....")
    assert not_image.status == 400
    assert not_image.json()["error"]["code"] == "BAD_IMAGE"
    huge = client.try_("magnet_check", {"source": "upload"}, png_header_only(100_000, 100_000))
    assert huge.status == 413
    assert huge.json()["error"]["code"] == "IMAGE_TOO_LARGE"
    assert client.request("DELETE", "/api/server").status == 405


def test_path_tricks_are_refused(server: RunningConsole, client: Browserless) -> None:
    secret = server.config.read_bytes()
    for path in (
        "/static/../cell.yaml",
        "/static/%2e%2e/cell.yaml",
        "/static/..%2fcell.yaml",
        "/api/results/../../x",
        "/api/results/1/../../../cell.yaml",
        "/cell.yaml",
        "/static//etc/passwd",
    ):
        status, body = raw_get(server, path)
        assert 400 <= status < 500, path
        assert b"auth_token" not in body, path
        assert secret[:200] not in body, path


def test_an_oversized_upload_is_refused_before_it_is_read(tmp_path: Path) -> None:
    limit = 300_000
    with console_server(tmp_path, max_frame_bytes=limit) as running:
        c = Browserless(running.url)
        c.login()
        big = b"\x89PNG\r\n\x1a\n" + bytes(limit + 100_000)
        reply = c.try_("magnet_check", {"source": "upload"}, big)
        assert reply.status == 413
        assert "error" in reply.json()


def test_busy_is_503_with_retry_after(tmp_path: Path) -> None:
    with console_server(tmp_path, workers=1, queue_depth=0) as running:
        c = Browserless(running.url)
        c.login()
        held = running.call(running.app.service.admit)  # the only slot
        try:
            reply = c.try_("magnet_check", {"source": "camera"})
            assert reply.status == 503
            assert reply.headers["Retry-After"] == "1"
            assert reply.json()["error"]["code"] == "BUSY"
            assert b"cellvision_busy_total 1.0" in c.get("/metrics").body
        finally:
            running.call(held.release)
        assert c.try_("magnet_check", {"source": "camera"}).status == 200


# ----------------------------------------------------------------------------- save


def test_save_records_a_version_validates_and_reloads(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        before = c.get("/api/server").json()["config_hash"]
        original = running.config.read_text()
        refused = c.post_json("/api/inspections/magnet_check/save", {"options": {"threshold": 300}})
        assert refused.status == 422
        error = refused.json()["error"]
        assert error["code"] == "CONFIG_REFUSED"
        assert "cell.yaml" in error["message"]
        assert "threshold" in error["message"]
        assert running.config.read_text() == original
        assert not (tmp_path / "cell.yaml.history").exists()

        saved = c.post_json(
            "/api/inspections/magnet_check/save",
            {"options": {"roi": [10, 10, 50, 60], "threshold": 100}},
        )
        assert saved.status == 200, saved.body
        new_hash = saved.json()["config_hash"]
        assert new_hash != before
        assert c.get("/api/server").json()["config_hash"] == new_hash
        # The history holds the file as it was (version 1) and this save (version 2).
        assert saved.json()["version"] == 2
        versions = c.get("/api/history").json()["versions"]
        assert [(v["version"], v["kind"]) for v in versions] == [(2, "save"), (1, "original")]
        shown = c.get("/api/history/1").json()["text"]  # its tokens hidden
        assert TOKEN not in shown
        assert shown.replace("<hidden", "").count("\n") == original.count("\n")
        text = running.config.read_text()
        assert "roi: [10, 10, 50, 60]" in text
        assert "threshold: 100" in text
        assert "# Quality control (paper, Table 2)" in text  # comments kept
        config = next(
            i
            for i in c.get("/api/inspections").json()["inspections"]
            if i["name"] == "magnet_check"
        )
        assert config["roi"] == [10, 10, 50, 60]
        # The reloaded server runs the saved inspection.
        assert c.try_("magnet_check", {"source": "camera"}).json()["verdict"] == "pass"
        state = c.get("/api/server").json()
        assert state["pool"]["answered"] >= 1
        reloads = state["reloads"]
        assert reloads[0]["ok"]
        assert reloads[0]["config_hash"] == new_hash
        fixed = c.post_json("/api/inspections/magnet_check/save", {"options": {"camera": "tool"}})
        assert fixed.status == 422


# ----------------------------------------------------------------------------- wiring


def test_the_console_is_off_unless_enabled(tmp_path: Path) -> None:
    from vision_server.config import load_config

    config = example_config(tmp_path)
    text = config.read_text().replace("console:\n  enabled: true\n", "console:\n")
    config.write_text(text)
    assert not load_config(config).console.enabled
