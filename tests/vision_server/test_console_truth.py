"""The web console tells the truth (docs/console.md): real HTTP on loopback, port 0, against
the real server with the example cell.

- a console try lands in the result log only as a try (its options in its row, marked in the
  API and the CLI) and counts in no production figure (/api/stats, Prometheus);
- viewing (or trying on) a folder camera takes none of its frames: the robot's next inspection
  gets the next file;
- a save says what else its reload changed (hand edits go live with it), and a refusal caused
  by another inspection's invalid hand edit says that the saved values are not at fault;
- an upload takes any format OpenCV reads (BMP, TIFF, ...), with the pixel limit checked from
  the header before decoding;
- the parameters the page offers to tune are only keys a try and a save both take (the Results
  page's plural rules are in test_console_results_browser.py).
"""

from __future__ import annotations

import contextlib
import io
import struct
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest
from console_server import Browserless, RunningConsole, console_server, running_cell
from rich.console import Console

from robot_client.client import SyncVisionClient
from vision_server.app import App
from vision_server.commands.results import results_command


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


@pytest.fixture
def client(server: RunningConsole) -> Browserless:
    c = Browserless(server.url)
    assert c.login().status == 200
    return c


def _metric(text: str, inspection: str, verdict: str) -> float:
    prefix = f'cellvision_inspections_total{{inspection="{inspection}",verdict="{verdict}"}} '
    for line in text.splitlines():
        if line.startswith(prefix):
            return float(line[len(prefix) :])
    return 0.0


def test_a_try_is_recorded_only_as_a_try(server: RunningConsole, client: Browserless) -> None:
    before = client.get("/api/stats?inspection=magnet_check&window_s=3600").json()
    metrics_before = client.get("/metrics").body.decode()
    # A wrong ROI (a dark corner of the frame) makes the failing part PASS.
    options = {"roi": [10, 10, 50, 60]}
    reply = client.try_("magnet_check", {"source": "camera", "options": options})
    assert reply.status == 200, reply.body
    assert reply.json()["verdict"] == "pass"

    rows = client.get("/api/results?inspection=magnet_check&limit=1").json()["results"]
    assert rows[0]["peer"].startswith("console ")
    assert rows[0]["try"] is True
    detail = client.get(f"/api/results/{rows[0]['id']}").json()
    assert detail["data"]["try"] == {"options": options}

    after = client.get("/api/stats?inspection=magnet_check&window_s=3600").json()
    assert after["inspections"][0]["count"] == before["inspections"][0]["count"]
    assert after["inspections"][0]["pass"] == before["inspections"][0]["pass"]
    metrics_after = client.get("/metrics").body.decode()
    for verdict in ("pass", "fail"):
        assert _metric(metrics_after, "magnet_check", verdict) == _metric(
            metrics_before, "magnet_check", verdict
        )

    # The CLI marks it too: a "try" column, and "try": true in its JSON lines.
    assert server.runtime is not None
    db = server.runtime.config.results.path
    assert db is not None
    out = io.StringIO()
    status = results_command(
        db,
        since=None,
        inspection="magnet_check",
        json_out=False,
        limit=1,
        failed_only=False,
        console=Console(file=out, width=200),
    )
    assert status == 0
    row_line = next(line for line in out.getvalue().splitlines() if "magnet_check" in line)
    assert " try " in row_line, out.getvalue()


# ----------------------------------------------------------------------------- folder cameras

REPLAY_CELL = """\
server: {port: 0, name: replay-cell}
console: {enabled: true, port: 0}
results: {path: results.sqlite3}
cameras:
  replay: {source: folder, path: frames, color: gray}
inspections:
  - {name: replay_job, type: presence, camera: replay, measure: mean_intensity, min: 0,
     number: 3}
"""


@contextlib.contextmanager
def replay_cell(folder: Path) -> Iterator[App]:
    """A cell with one folder camera over img1..img4 (grey levels 10, 20, 30, 40)."""
    (folder / "frames").mkdir()
    for index in range(1, 5):
        cv2.imwrite(
            str(folder / "frames" / f"img{index}.png"), np.full((8, 8), 10 * index, np.uint8)
        )
    config = folder / "cell.yaml"
    config.write_text(REPLAY_CELL, encoding="utf-8")
    with running_cell(config) as running:
        yield running.app


def test_viewing_a_folder_camera_takes_none_of_its_frames(tmp_path: Path) -> None:
    with replay_cell(tmp_path) as app:
        assert app.http is not None
        console = Browserless(app.http.url)
        listing = console.get("/api/cameras").json()["cameras"]
        assert listing[0]["view"] == "last_taken"
        # Before any inspection there is nothing to show, and looking takes nothing.
        assert console.get("/api/cameras/replay/frame.jpg").status == 404
        robot = SyncVisionClient("127.0.0.1", app.port, request_timeout_s=10.0)
        try:
            first = robot.inspect("replay_job")
            assert first.data["source_files"] == ["img1.png"]
            for _ in range(3):
                view = console.get("/api/cameras/replay/frame.jpg")
                assert view.status == 200, view.body
            # A try on the camera's frame runs on the frame the robot's inspection took.
            tried = console.try_("replay_job", {"source": "camera", "options": {}})
            assert tried.status == 200, tried.body
            assert tried.json()["data"]["value"] == pytest.approx(10.0)
            second = robot.inspect("replay_job")
        finally:
            robot.close()
        assert second.data["source_files"] == ["img2.png"]


# ----------------------------------------------------------------------------- save


def test_a_save_says_what_else_its_reload_changed(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        assert c.login().status == 200
        # A hand edit of another inspection, not loaded yet.
        text = running.config.read_text(encoding="utf-8")
        running.config.write_text(
            text.replace("    min_count: 1\n", "    min_count: 2\n"), encoding="utf-8"
        )
        saved = c.post_json("/api/inspections/magnet_check/save", {"options": {"threshold": 100}})
        assert saved.status == 200, saved.body
        assert saved.json()["also_changed"] == ["cap_locate"]
        assert "2 inspections changed: cap_locate, magnet_check" in saved.json()["notes"]
        reload = c.get("/api/server").json()["reloads"][0]
        assert reload["message"] == "2 inspections changed: cap_locate, magnet_check"

        # Another inspection made invalid by hand: the refusal says the saved part is fine.
        text = running.config.read_text(encoding="utf-8")
        running.config.write_text(
            text.replace("    min_count: 2\n", "    min_count: -5\n"), encoding="utf-8"
        )
        refused = c.post_json("/api/inspections/magnet_check/save", {"options": {"min": 0.3}})
        assert refused.status == 422, refused.body
        message = refused.json()["error"]["message"]
        assert "already invalid" in message
        assert "'magnet_check''s values are not the invalid part" in message
        assert "min_count" in message


# ----------------------------------------------------------------------------- uploads


@pytest.mark.parametrize("suffix", [".bmp", ".tiff"])
def test_an_upload_takes_any_format_opencv_reads(client: Browserless, suffix: str) -> None:
    # The camera's own size (an image of another size is refused: its intrinsics would lie)
    image = np.full((768, 1024, 3), 255, np.uint8)
    image[:8, :8] = 0  # a dark square: dark_fraction 1.0 inside it, 0.0 outside
    ok, encoded = cv2.imencode(suffix, image)
    assert ok
    spec = {"source": "upload", "options": {"roi": [0, 0, 8, 8]}}
    dark = client.try_("magnet_check", spec, encoded.tobytes())
    assert dark.status == 200, dark.body
    assert dark.json()["data"]["value"] == pytest.approx(1.0)
    spec = {"source": "upload", "options": {"roi": [8, 8, 8, 8]}}
    bright = client.try_("magnet_check", spec, encoded.tobytes())
    assert bright.json()["data"]["value"] == pytest.approx(0.0)


def _bmp_header(width: int, height: int) -> bytes:
    info = struct.pack("<IiiHHIIiiII", 40, width, height, 1, 24, 0, 0, 2835, 2835, 0, 0)
    return b"BM" + struct.pack("<IHHI", 14 + len(info), 0, 0, 14 + len(info)) + info


def _tiff_header(width: int, height: int) -> bytes:
    entries = struct.pack("<HHII", 256, 4, 1, width) + struct.pack("<HHII", 257, 4, 1, height)
    return b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 2) + entries + b"\x00" * 4


@pytest.mark.parametrize("header", [_bmp_header, _tiff_header])
def test_an_upload_too_large_is_refused_from_its_header(
    client: Browserless, header: object
) -> None:
    assert callable(header)
    huge = client.try_("magnet_check", {"source": "upload"}, header(100_000, 100_000))
    assert huge.status == 413, huge.body
    assert huge.json()["error"]["code"] == "IMAGE_TOO_LARGE"
    assert "100000x100000" in huge.json()["error"]["message"]
    damaged = client.try_("magnet_check", {"source": "upload"}, b"BM" + b"\x00" * 10)
    assert damaged.status == 400
    assert damaged.json()["error"]["code"] == "BAD_IMAGE"


# ----------------------------------------------------------------------------- parameters


def test_only_keys_that_can_be_tried_and_saved_are_tunable(tmp_path: Path) -> None:
    with replay_cell(tmp_path) as app:
        assert app.http is not None
        console = Browserless(app.http.url)
        listed = console.get("/api/inspections").json()["inspections"][0]
        assert listed["config"]["number"] == 3  # configured, shown, but fixed
        keys = [p["key"] for p in listed["parameters"]]
        assert keys == ["min"]
        saved = console.post_json("/api/inspections/replay_job/save", {"options": {"min": 1}})
        assert saved.status == 200, saved.body
