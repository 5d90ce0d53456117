"""Training an anomaly inspection from the console's API (docs/console.md, "Training an
anomaly inspection"): the real server with its console on port 0, a real result log whose rows
and stored images come from robot INSPECTs over the protocol, the real training and reload.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
import yaml
from console_server import Browserless, RunningConsole
from console_users import ANNA_PIN, CARLA_PIN
from train_cell import inspect, part_image, send_parts, train_server

from protocol import CameraUnavailable, CellvisionError
from vision_server.config import history

TRAIN = "/api/inspections/surface_check/train"


def carla(server: RunningConsole) -> Browserless:
    client = Browserless(server.url)
    assert client.post_json("/api/login", {"user": "Carla", "pin": CARLA_PIN}).status == 200
    return client


def anna(server: RunningConsole) -> Browserless:
    client = Browserless(server.url)
    assert client.post_json("/api/login", {"user": "anna", "pin": ANNA_PIN}).status == 200
    return client


def error_of(reply: Any) -> tuple[int, str, str]:
    body = reply.json()
    return reply.status, body["error"]["code"], body["error"]["message"]


def model_key(config: Path, name: str) -> Any:
    data = yaml.safe_load(config.read_text(encoding="utf-8"))
    return next(i for i in data["inspections"] if i["name"] == name).get("model")


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Any:
    folder = tmp_path_factory.mktemp("train")
    with train_server(folder) as server:
        ids = send_parts(server, 10)
        yield server, ids


def test_stored_results_are_listed_with_their_images(cell: Any) -> None:
    server, ids = cell
    client = anna(server)  # viewing is the operator's
    reply = client.get("/api/inspections/surface_check/train/images?limit=4")
    assert reply.status == 200, reply.body
    body = reply.json()
    assert [r["id"] for r in body["results"]] == ids[::-1][:4]
    assert body["store_images"] == "all"
    first = body["results"][0]
    # Before any training the inspection cannot judge: each row is an error, its image kept.
    assert first["passed"] is False
    assert "no trained model" in first["error"]
    assert body["next_before_id"] == ids[-4]
    rest = client.get(f"/api/inspections/surface_check/train/images?before_id={ids[-4]}").json()
    assert [r["id"] for r in rest["results"]] == ids[::-1][4:]
    assert rest["next_before_id"] is None
    assert client.get("/api/inspections/nope/train/images").status == 404
    assert client.get("/api/inspections/surface_check/train/images?limit=0").status == 400


def test_model_before_training(cell: Any) -> None:
    server, _ = cell
    client = anna(server)
    body = client.get("/api/inspections/surface_check/model").json()
    assert body["camera"] == "tool"
    assert body["camera_grabs"] is False
    (model,) = body["models"]
    assert model["trained"] is False
    assert model["file"] is None
    assert model["method"] == "variation"
    qc = client.get("/api/inspections/qc_surface/model").json()
    assert qc["camera_grabs"] is True
    status, code, message = error_of(client.get("/api/inspections/magnet_check/model"))
    assert (status, code) == (400, "NOT_TRAINABLE")
    assert "presence" in message


def test_roles_and_the_front_door(cell: Any) -> None:
    server, ids = cell
    body = {"source": "results", "ids": ids}
    assert Browserless(server.url).post_json(TRAIN, body).status == 401
    status, code, message = error_of(anna(server).post_json(TRAIN, body))
    assert (status, code) == (403, "FORBIDDEN")
    assert "integrator" in message
    client = carla(server)
    # Another site's page: its Origin is refused, as is a body that is neither JSON nor sent
    # with the console's header.
    reply = client.request(
        "POST",
        TRAIN,
        json.dumps(body).encode(),
        {"Content-Type": "application/json", "Origin": "http://evil.example"},
    )
    assert error_of(reply)[:2] == (403, "CROSS_SITE")
    reply = client.request(
        "POST",
        TRAIN,
        json.dumps(body).encode(),
        {"Content-Type": "text/plain", "X-Cellvision": "no"},
    )
    assert error_of(reply)[:2] == (403, "CROSS_SITE")


@pytest.mark.parametrize(
    ("path", "body", "status", "code", "words"),
    [
        ("/api/inspections/nope/train", {"source": "results", "ids": [1]}, 404, None, "nope"),
        (
            "/api/inspections/magnet_check/train",
            {"source": "results", "ids": [1]},
            400,
            "NOT_TRAINABLE",
            "presence",
        ),
        (TRAIN, {"source": "disk"}, 400, "BAD_REQUEST", "source"),
        (TRAIN, {"source": "results", "ids": []}, 400, "BAD_REQUEST", "ids"),
        (TRAIN, {"source": "results", "ids": [1, "2"]}, 400, "BAD_REQUEST", '"2"'),
        (TRAIN, {"source": "results", "ids": [1], "colour": 1}, 400, "BAD_REQUEST", "colour"),
        (
            TRAIN,
            {"source": "results", "ids": list(range(1, 1002))},
            400,
            "TOO_MANY_IMAGES",
            "1001",
        ),
        (TRAIN, {"source": "results", "ids": [1], "method": "x"}, 400, "BAD_REQUEST", "method"),
        (
            TRAIN,
            {"source": "results", "ids": [1], "false_reject": 0.7},
            400,
            "BAD_REQUEST",
            "false_reject",
        ),
        (TRAIN, {"source": "results", "ids": [1], "step": "s"}, 400, "NOT_TRAINABLE", "step"),
        (TRAIN, {"source": "camera", "frames": 3}, 400, "TOO_FEW_IMAGES", "at least 8"),
        (TRAIN, {"source": "camera", "frames": 20}, 400, "NO_CAMERA_FRAMES", "robots"),
        (
            "/api/inspections/qc_surface/train",
            {"source": "camera", "frames": 100, "interval_ms": 5000},
            400,
            "BAD_REQUEST",
            "500 s",
        ),
    ],
)
def test_requests_that_cannot_train_are_refused_by_name(
    cell: Any, path: str, body: dict[str, Any], status: int, code: str | None, words: str
) -> None:
    server, _ = cell
    before = server.config.read_bytes()
    reply = carla(server).post_json(path, body)
    got_status, got_code, message = error_of(reply)
    assert got_status == status, reply.body
    if code is not None:
        assert got_code == code
    assert words in message
    assert server.config.read_bytes() == before
    assert not (server.config.parent / "models").exists()


def test_too_few_and_missing_images_are_named(cell: Any) -> None:
    server, ids = cell
    client = carla(server)
    status, code, message = error_of(client.post_json(TRAIN, {"source": "results", "ids": ids[:5]}))
    assert (status, code) == (400, "TOO_FEW_IMAGES")
    assert "5 usable images" in message
    assert "at least 8" in message
    # An id that names no row and one whose row kept no image (a request that never ran).
    reply = client.post_json(TRAIN, {"source": "results", "ids": [*ids, 999_999]})
    status, code, message = error_of(reply)
    assert (status, code) == (400, "NO_STORED_IMAGE")
    assert "999999" in message
    assert reply.json()["error"]["result_ids"] == [999_999]
    # A stored image of another camera (station_qr's rgbd camera): refused before any is read.
    inspect(server, "station_qr", part_image(3)[:480, :640])
    other = server.app.service.results.query(inspection="station_qr", limit=1)[0].id
    reply = client.post_json(TRAIN, {"source": "results", "ids": [*ids[:9], other]})
    status, code, message = error_of(reply)
    assert (status, code) == (400, "OTHER_CAMERA")
    assert str(other) in message
    assert reply.json()["error"]["result_ids"] == [other]
    assert not (server.config.parent / "models").exists()


def test_one_training_at_a_time(cell: Any) -> None:
    """A camera training grabbing 8 frames 800 ms apart holds the one training slot: a
    second training is 503 BUSY with Retry-After, /api/training shows the first; then the
    first finishes and qc_surface answers with its model."""
    server, ids = cell
    client = carla(server)
    answers: list[Any] = []
    worker = threading.Thread(
        target=lambda: answers.append(
            client.post_json(
                "/api/inspections/qc_surface/train",
                {"source": "camera", "frames": 8, "interval_ms": 800},
            )
        )
    )
    worker.start()
    try:
        status: dict[str, Any] = {}
        for _ in range(200):
            status = client.get("/api/training").json()
            if status["running"]:
                break
            time.sleep(0.02)
        assert status["running"]
        assert status["inspection"] == "qc_surface"
        assert status["source"] == "camera"
        assert status["wanted"] == 8
        second = carla(server).post_json(TRAIN, {"source": "results", "ids": ids})
        got_status, code, message = error_of(second)
        assert (got_status, code) == (503, "BUSY")
        assert "qc_surface" in message
        assert int(second.headers["Retry-After"]) > 0
    finally:
        worker.join(120)
    (reply,) = answers
    assert reply.status == 200, reply.body
    report = reply.json()
    assert report["images"] == 8
    assert report["model"] == "models/qc_surface.v1.npz"
    assert model_key(server.config, "qc_surface") == "models/qc_surface.v1.npz"
    assert client.get("/api/training").json() == {"running": False}


def test_train_from_stored_results_then_the_inspection_answers_with_the_model(cell: Any) -> None:
    server, ids = cell
    client = carla(server)
    old_hash = server.app.service.catalog.config_hash
    reply = client.post_json(TRAIN, {"source": "results", "ids": ids, "false_reject": 0.05})
    assert reply.status == 200, reply.body
    report = reply.json()
    assert report["model"] == "models/surface_check.v1.npz"
    assert report["version"] == 1
    assert report["method"] == "variation"
    assert report["images"] == 10
    assert report["skipped"] == []
    assert report["false_reject"] == 0.05
    assert report["threshold"] > 0
    assert 0.0 <= report["held_out_rejected"] <= 1.0
    assert report["config_hash"] != old_hash
    assert report["config_hash"] == server.app.service.catalog.config_hash
    assert (server.config.parent / report["model"]).is_file()
    assert model_key(server.config, "surface_check") == report["model"]
    # Recorded in the file's history as Carla's.
    newest = history.history_of(server.config).versions(limit=1)[0]
    assert newest.number == report["config_version"]
    assert newest.who == "Carla"
    assert "surface_check.v1.npz" in newest.why
    # The inspection now answers with the model, under the new configuration hash.
    good = inspect(server, "surface_check", part_image(100))
    assert not isinstance(good, CellvisionError), good
    assert good.passed
    assert good.data["model_version"] == 1
    assert good.config_hash == report["config_hash"]  # type: ignore[attr-defined]
    bad = inspect(server, "surface_check", part_image(101, scratch=True))
    assert not isinstance(bad, CellvisionError), bad
    assert not bad.passed  # type: ignore[attr-defined]
    model = client.get("/api/inspections/surface_check/model").json()["models"][0]
    assert model["trained"]
    assert model["version"] == 1
    assert model["images"] == 10
    assert model["file"] == report["model"]
    assert model["threshold"] == report["threshold"]
    assert len(model["held_out_scores"]) == len(report["held_out_scores"])
    # Trained again: a new file beside the first, version 2.
    again = client.post_json(TRAIN, {"source": "results", "ids": ids})
    assert again.status == 200, again.body
    assert again.json()["model"] == "models/surface_check.v2.npz"
    assert again.json()["version"] == 2


def test_a_training_whose_browser_goes_away_stops_and_writes_nothing(cell: Any) -> None:
    """The request's connection closes while the frames are grabbed: the training stops, the
    slot is freed, no model file is written and the configuration is unchanged."""
    server, _ = cell
    client = carla(server)
    before = server.config.read_bytes()
    models = set((server.config.parent / "models").glob("*.npz"))
    cookie = "; ".join(f"{c.name}={c.value}" for c in client.jar)
    body = json.dumps({"source": "camera", "frames": 8, "interval_ms": 1000}).encode()
    address = urlsplit(server.url)
    host, port = address.hostname or "127.0.0.1", address.port or 80
    head = (
        f"POST /api/inspections/qc_surface/train HTTP/1.1\r\nHost: {host}:{port}\r\n"
        f"Content-Type: application/json\r\nX-Cellvision: console\r\nCookie: {cookie}\r\n"
        f"Content-Length: {len(body)}\r\n\r\n"
    )
    with socket.create_connection((host, port)) as sock:
        sock.sendall(head.encode() + body)
        for _ in range(250):
            if client.get("/api/training").json()["running"]:
                break
            time.sleep(0.02)
        assert client.get("/api/training").json()["running"]
    for _ in range(500):
        if not client.get("/api/training").json()["running"]:
            break
        time.sleep(0.02)
    assert client.get("/api/training").json() == {"running": False}
    assert server.config.read_bytes() == before
    assert set((server.config.parent / "models").glob("*.npz")) == models


def test_a_job_step_is_trained_by_name_with_patches(cell: Any) -> None:
    """A job with two anomaly steps: without ``step`` the request names both; ``right`` is
    trained (the default ``patches`` method, learned features) on the stored images of
    surface_check's results (the same camera), and only its ``model:`` is set."""
    server, ids = cell
    client = carla(server)
    path = "/api/inspections/surface_job/train"
    status, code, message = error_of(client.post_json(path, {"source": "results", "ids": ids}))
    assert (status, code) == (400, "NOT_TRAINABLE")
    assert "left" in message
    assert "right" in message
    reply = client.post_json(path, {"source": "results", "ids": ids[:8], "step": "right"})
    assert reply.status == 200, reply.body
    report = reply.json()
    assert report["model"] == "models/surface_job.right.v1.npz"
    assert report["step"] == "right"
    assert report["method"] == "patches"
    assert report["images"] == 8
    steps = {
        s["name"]: s
        for s in next(
            i
            for i in yaml.safe_load(server.config.read_text(encoding="utf-8"))["inspections"]
            if i["name"] == "surface_job"
        )["steps"]
    }
    assert steps["right"]["model"] == report["model"]
    assert "model" not in steps["left"]
    models = {
        m["step"]: m for m in client.get("/api/inspections/surface_job/model").json()["models"]
    }
    assert models["right"]["trained"]
    assert models["right"]["version"] == 1
    assert not models["left"]["trained"]


def test_a_reload_that_refuses_the_model_puts_everything_back(cell: Any) -> None:
    """The server cannot take the new text (here its reloader reports a camera that does not
    open): 422 CONFIG_REFUSED naming the model, the file's old text back, the History without
    the version, and the model file removed."""
    server, ids = cell
    service = server.app.service
    before = server.config.read_bytes()
    versions = [v.number for v in history.history_of(server.config).versions()]
    models = set((server.config.parent / "models").glob("*.npz"))

    def refuse() -> Any:
        raise CameraUnavailable("camera 'qc' does not open")

    reloader = service.reloader
    service.reloader = refuse
    try:
        reply = carla(server).post_json(TRAIN, {"source": "results", "ids": ids})
    finally:
        service.reloader = reloader
    status, code, message = error_of(reply)
    assert (status, code) == (422, "CONFIG_REFUSED")
    assert "surface_check.v" in message
    assert "does not open" in message
    assert server.config.read_bytes() == before
    assert [v.number for v in history.history_of(server.config).versions()] == versions
    assert set((server.config.parent / "models").glob("*.npz")) == models
