"""Building inspections through the console's API (docs/console.md, "Building inspections: the
API"): a try of a whole edited or new mapping, and saving one whole, against the real server
with the example cell (real sockets on loopback, port 0, the configuration file's runtime).
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server

from robot_client import SyncVisionClient
from vision_server.config import load_config
from vision_server.results import ResultEntry

MAGNET = {"roi": [10, 10, 50, 60], "measure": "dark_fraction", "threshold": 90, "min": 0.25}
"""The example cell's magnet_check moved to a dark corner of the simulated QC camera's frame,
where it passes (where the example puts it, the rotor has no magnet yet: it fails)."""


def draft_job(name: str = "magnet_job", **changes: Any) -> dict[str, Any]:
    """A job made on the page: a presence step where the example's magnet is."""
    step = {"name": "magnet", "type": "presence", **MAGNET}
    config: dict[str, Any] = {
        "name": name,
        "type": "job",
        "camera": "qc",
        "steps": [step],
        "verdict": "magnet.value >= 0.25",
    }
    config.update(changes)
    return config


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


@pytest.fixture
def client(server: RunningConsole) -> Browserless:
    c = Browserless(server.url)
    assert c.login().status == 200
    return c


def put(client: Browserless, name: str, body: Any, **headers: str) -> Any:
    raw = body if isinstance(body, bytes) else json.dumps(body).encode()
    return client.request(
        "PUT",
        f"/api/inspections/{name}",
        raw,
        {"Content-Type": "application/json", **headers},
    )


# ----------------------------------------------------------------------------- try a draft


def test_a_draft_job_is_tried_on_the_camera_and_logged_as_a_try(client: Browserless) -> None:
    reply = client.try_("magnet_job", {"source": "camera", "config": draft_job()})
    assert reply.status == 200, reply.body
    body = reply.json()
    assert body["verdict"] == "pass"
    assert body["data"]["steps"]["magnet"]["passed"] is True
    assert body["overlay"].startswith("data:image/png;base64,")
    # The try is in the result log as a try, with the mapping it ran.
    rows = client.get("/api/results?inspection=magnet_job&limit=1").json()["results"]
    assert rows
    assert rows[0]["try"] is True
    stored = client.get(f"/api/results/{rows[0]['id']}").json()
    assert stored["data"]["try"]["config"] == draft_job()
    assert stored["peer"].startswith("console ")


def test_a_draft_that_fails_its_verdict_fails(client: Browserless) -> None:
    config = draft_job(verdict="magnet.value < 0.25")
    reply = client.try_("magnet_job", {"source": "camera", "config": config})
    assert reply.status == 200, reply.body
    assert reply.json()["verdict"] == "fail"


def test_an_edited_configured_inspection_is_tried_whole(client: Browserless) -> None:
    config = {"name": "magnet_check", "type": "presence", "camera": "qc", **MAGNET}
    passing = client.try_("magnet_check", {"source": "camera", "config": config})
    assert passing.json()["verdict"] == "pass", passing.body
    config["threshold"] = 1  # nothing is that dark
    failing = client.try_("magnet_check", {"source": "camera", "config": config})
    assert failing.json()["verdict"] == "fail", failing.body
    # options keep working as documented
    tuned = client.try_("magnet_check", {"source": "camera", "options": {"roi": MAGNET["roi"]}})
    assert tuned.json()["verdict"] == "pass"


def with_step(**changes: Any) -> dict[str, Any]:
    """The draft job with its presence step changed."""
    return draft_job(steps=[{"name": "magnet", "type": "presence", **MAGNET, **changes}])


@pytest.mark.parametrize(
    ("config", "where"),
    [
        (with_step(roi=[0, 0, 0, 4]), "steps[0] (name='magnet') -> roi"),
        (draft_job(verdict="magnet.count >= 1"), "verdict"),
        (draft_job(camera="nowhere"), "camera"),
        (draft_job(bogus=1), "bogus"),
        (with_step(roi=[2000, 0, 8, 8]), "steps[0] (name='magnet') -> roi"),
        (draft_job(steps=[{"name": "m", "type": "locate", "method": "template",
                           "template": {"image": "/etc/passwd"}}]),
         "steps[0] -> template -> image"),
        (draft_job(steps=[{"name": "m", "type": "locate", "method": "template",
                           "template": {"image": "../x.png"}}]),
         "steps[0] -> template -> image"),
    ],
)  # fmt: skip
def test_a_draft_is_validated_as_the_loader_does_naming_the_key_path(
    client: Browserless, config: dict[str, Any], where: str
) -> None:
    reply = client.try_("magnet_job", {"source": "camera", "config": config})
    assert reply.status == 400, reply.body
    error = reply.json()["error"]
    assert error["code"] == "CONFIG_INVALID"
    assert error["message"].startswith(where), error["message"]


def test_a_verdict_error_names_its_column(client: Browserless) -> None:
    reply = client.try_(
        "magnet_job", {"source": "camera", "config": draft_job(verdict="magnet.count >= 1")}
    )
    assert "column" in reply.json()["error"]["message"]


def test_a_draft_needs_its_config_and_its_own_name(client: Browserless) -> None:
    missing = client.try_("magnet_job", {"source": "camera"})
    assert missing.status == 404
    assert missing.json()["error"]["code"] == "UNKNOWN_INSPECTION"
    wrong = client.try_("magnet_job", {"source": "camera", "config": draft_job("other")})
    assert wrong.status == 400
    message = wrong.json()["error"]["message"]
    assert "'other'" in message
    assert "'magnet_job'" in message
    both = client.try_("magnet_check", {"source": "camera", "options": {"min": 0.1}, "config": {}})
    assert both.status == 400
    bad_name = client.try_("bad%20name!", {"source": "camera", "config": draft_job("bad%20name!")})
    assert bad_name.status in (400, 404)


def test_an_operator_may_not_try_or_save(tmp_path: Path) -> None:
    with console_server(tmp_path, operator_token="operator-token-0123456789") as running:
        person = Browserless(running.url)
        assert person.login("operator-token-0123456789").status == 200
        tried = person.try_("magnet_job", {"source": "camera", "config": draft_job()})
        assert tried.status == 403
        saved = put(person, "magnet_job", {"config": draft_job()})
        assert saved.status == 403
        assert saved.json()["error"]["code"] == "FORBIDDEN"
        template = {"source": "camera", "rect": [0, 0, 8, 8], "config": {"camera": "qc"}}
        assert train(person, "magnet_job", template).status == 403
        assert not (tmp_path / "templates").exists()
        # viewing is the operator's
        assert person.get("/api/schema").status == 200
        assert person.get("/api/inspections/magnet_check/reads").status == 200
        anonymous = Browserless(running.url)
        assert anonymous.get("/api/schema").status == 401
        assert anonymous.get("/api/inspections/magnet_check/reads").status == 401


# ----------------------------------------------------------------------------- save whole


def test_a_draft_saved_whole_is_served_and_a_robot_inspects_it(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        original = running.config.read_text()
        config = draft_job()
        assert c.try_("magnet_job", {"source": "camera", "config": config}).json()["verdict"] == (
            "pass"
        )
        saved = put(c, "magnet_job", {"config": config, "why": "a job for the magnet"})
        assert saved.status == 200, saved.body
        body = saved.json()
        assert body["created"] is True
        # The history holds the file as it was and the new text, with who and why.
        version = c.get(f"/api/history/{body['version']}").json()
        assert version["kind"] == "created_inspection", version
        assert version["why"] == "a job for the magnet"
        before = c.get(f"/api/history/{version['previous']}").json()["text"]
        # (the API hides the token's value: the rest is the file as it was)
        assert [ln for ln in before.splitlines() if "<hidden " not in ln] == [
            ln for ln in original.splitlines() if "token: " not in ln
        ]
        text = running.config.read_text()
        # Everything before the new entry is byte for byte what it was.
        assert text.startswith(original.rstrip("\n"))
        assert '  - name: "magnet_job"\n    type: "job"\n' in text
        assert load_config(running.config).inspections[-1].name == "magnet_job"
        listed = {i["name"]: i for i in c.get("/api/inspections").json()["inspections"]}
        assert listed["magnet_job"]["config"] == config
        with SyncVisionClient("127.0.0.1", running.app.port, auth_token=TOKEN) as robot:
            result = robot.inspect("magnet_job")
        assert result.passed
        assert result.data["steps"]["magnet"]["passed"] is True

        # Saved again with a change: replaced in place, not appended.
        changed = draft_job(verdict="magnet.value < 0.25")
        again = put(c, "magnet_job", {"config": changed, "why": "stricter"})
        assert again.status == 200, again.body
        assert again.json()["created"] is False
        assert running.config.read_text().count('name: "magnet_job"') == 1
        with SyncVisionClient("127.0.0.1", running.app.port, auth_token=TOKEN) as robot:
            assert not robot.inspect("magnet_job").passed


def test_a_whole_replace_keeps_the_rest_of_the_file_byte_identical(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        original = running.config.read_text()
        config = {
            "name": "magnet_check",
            "type": "presence",
            "camera": "qc",
            **MAGNET,
            "description": 'the magnet: "in its slot"\n# not a comment',
        }
        saved = put(c, "magnet_check", {"config": config})
        assert saved.status == 200, saved.body
        text = running.config.read_text()
        head = original[: original.index("  - name: magnet_check")]
        tail = original[original.index("  # Fast calibration") :]
        assert text.startswith(head)
        assert text.endswith(tail)
        assert "# Quality control (paper, Table 2)" in text
        written = load_config(running.config)
        spec = next(i for i in written.inspections if i.name == "magnet_check")
        assert spec.common.description == config["description"]


def test_a_save_whole_is_refused_naming_the_cause(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        original = running.config.read_text()
        bad_roi = draft_job(steps=[{"name": "magnet", "type": "presence", **MAGNET,
                                    "roi": [2000, 0, 8, 8]}])  # fmt: skip
        refused = put(c, "magnet_job", {"config": bad_roi})
        assert refused.status == 422
        error = refused.json()["error"]
        assert error["code"] == "CONFIG_REFUSED"
        for part in ("cell.yaml", "magnet_job", "steps[0]", "roi"):
            assert part in error["message"], error["message"]
        outside = draft_job(
            steps=[{"name": "m", "type": "locate", "method": "template",
                    "template": {"image": "/etc/hostname"}}]
        )  # fmt: skip
        refused = put(c, "magnet_job", {"config": outside})
        assert refused.status == 422
        assert "steps[0] -> template -> image" in refused.json()["error"]["message"]
        wrong_name = put(c, "magnet_job", {"config": draft_job("other")})
        assert wrong_name.status == 422
        assert "'other'" in wrong_name.json()["error"]["message"]
        assert put(c, "magnet_job", {"config": draft_job(), "why": "x" * 501}).status == 400
        big = put(c, "magnet_job", {"config": draft_job(description="x" * 70_000)})
        assert big.status == 413
        not_json = put(c, "magnet_job", b"{")
        assert not_json.status == 400
        # Another site's page: its Origin, or a body a form could send (no JSON type, no
        # X-Cellvision header).
        cross = put(c, "magnet_job", {"config": draft_job()}, Origin="http://evil.example")
        assert cross.status == 403
        assert cross.json()["error"]["code"] == "CROSS_SITE"
        form = c.request(
            "PUT",
            "/api/inspections/magnet_job",
            json.dumps({"config": draft_job()}).encode(),
            {"Content-Type": "text/plain", "X-Cellvision": ""},
        )
        assert form.status == 403
        assert running.config.read_text() == original
        assert not list(tmp_path.glob("cell.yaml.bak-*"))


def test_an_entry_with_anchors_is_not_replaced_whole(tmp_path: Path) -> None:
    with console_server(tmp_path) as running:
        text = running.config.read_text()
        text = text.replace(
            "    measure: dark_fraction\n    threshold: 90\n",
            "    measure: &how dark_fraction\n    threshold: 90\n",
        )
        running.config.write_text(text)
        c = Browserless(running.url)
        c.login()
        config = {"name": "magnet_check", "type": "presence", "camera": "qc", **MAGNET}
        refused = put(c, "magnet_check", {"config": config})
        assert refused.status == 422
        assert "anchor" in refused.json()["error"]["message"]
        assert running.config.read_text() == text


# ----------------------------------------------------------------------------- schema


def test_the_schema_gives_every_type_and_step_with_the_cameras(client: Browserless) -> None:
    reply = client.get("/api/schema")
    assert reply.status == 200
    schema = reply.json()
    assert set(schema["types"]) == {
        "presence", "locate", "qr", "code", "qr_pose", "caliper", "calibration_board", "job",
        "anomaly",
    }  # fmt: skip
    assert set(schema["steps"]) == {"locate", "fixture", "presence", "code", "caliper", "anomaly"}
    camera = next(k for k in schema["common"] if k["key"] == "camera")
    assert camera["kind"] == "enum"
    assert set(camera["values"]) == {"tool", "rgbd", "qc"}
    radius = next(
        k for k in schema["types"]["locate"]["keys"] if k["key"] == "circle.min_radius_px"
    )
    assert radius["kind"] == "number"
    assert radius["unit"] == "px"
    assert radius["when"] == {"method": "circle"}
    assert radius["required"] is True


# ----------------------------------------------------------------------------- templates


def train(client: Browserless, name: str, body: dict[str, Any]) -> Any:
    return client.post_json(f"/api/inspections/{name}/template", body)


def test_a_template_trained_from_the_camera_locates_the_part_in_a_try(
    server: RunningConsole, client: Browserless
) -> None:
    rect = [440, 190, 140, 150]  # the rotor on the QC table
    trained = train(client, "rotor_find", {"source": "camera", "rect": rect,
                                           "config": {"camera": "qc"}})  # fmt: skip
    assert trained.status == 200, trained.body
    body = trained.json()
    assert re.fullmatch(r"templates/rotor_find-[0-9a-f]{12}\.png", body["path"])
    assert (body["width"], body["height"]) == (140, 150)
    assert body["image"].startswith("data:image/png;base64,")
    written = cv2.imread(str(server.config.parent / body["path"]), cv2.IMREAD_UNCHANGED)
    assert written.shape == (150, 140)  # grey
    config = {
        "name": "rotor_find",
        "type": "locate",
        "camera": "qc",
        "roi": [300, 100, 450, 400],
        "method": "template",
        "template": {"image": body["path"]},
    }
    tried = client.try_("rotor_find", {"source": "camera", "config": config})
    assert tried.status == 200, tried.body
    found = tried.json()
    assert found["verdict"] == "pass"
    feature = found["data"]["features"][0]
    # the template's centre, where it was cut (pixel centres: x + (w - 1) / 2)
    assert abs(feature["u"] - (440 + 69.5)) < 1.0
    assert abs(feature["v"] - (190 + 74.5)) < 1.0


def test_the_same_crop_twice_is_the_same_file_and_bad_rects_are_refused(
    server: RunningConsole, client: Browserless
) -> None:
    tried = client.try_("magnet_check", {"source": "camera"})
    assert tried.status == 200
    row = client.get("/api/results?inspection=magnet_check&limit=1").json()["results"][0]
    assert row["has_image"], row  # a failure: its image is stored
    body = {"source": "result", "result_id": row["id"], "rect": [440, 190, 64, 64]}
    first = train(client, "magnet_check", body)
    second = train(client, "magnet_check", body)
    assert first.status == 200, first.body
    assert first.json()["path"] == second.json()["path"]
    folder = server.config.parent / "templates"
    assert len(list(folder.glob("magnet_check-*.png"))) == 1
    for rect, word in (
        ([440, 190, 4, 64], "8..1024"),
        ([440, 190, 2000, 64], "8..1024"),
        ([1000, 700, 64, 64], "not inside"),
        ([0, 0, 64], "rect"),
        ("x", "rect"),
    ):
        refused = train(client, "magnet_check", {**body, "rect": rect})
        assert refused.status == 400, (rect, refused.body)
        assert word in refused.json()["error"]["message"]
    assert train(client, "magnet_check", {**body, "source": "upload"}).status == 400
    assert train(client, "no_such", {"source": "camera", "rect": [0, 0, 8, 8]}).status == 404


def test_the_template_folder_is_bounded_and_never_overwritten(tmp_path: Path) -> None:
    from vision_server.frontends import template_files

    texture = np.random.default_rng(5).integers(0, 255, (20, 20), dtype=np.uint8)
    kept = template_files.keep(tmp_path, "part", texture)
    assert (tmp_path / kept.path).read_bytes() == kept.png
    # another image under that name (by hand) is not overwritten
    other = np.flipud(texture).copy()
    cv2.imwrite(str(tmp_path / kept.path), other)
    with pytest.raises(template_files.TemplateRefused, match="not overwritten"):
        template_files.keep(tmp_path, "part", texture)
    for index in range(template_files.MAX_TEMPLATES):
        (tmp_path / "templates" / f"filler-{index}.png").write_bytes(b"")
    with pytest.raises(template_files.TemplateRefused, match="templates/") as full:
        template_files.keep(tmp_path, "part", np.fliplr(texture).copy())
    assert full.value.status == 409
    flat = np.full((20, 20), 128, np.uint8)
    with pytest.raises(template_files.TemplateRefused, match="flat"):
        template_files.cut(flat, [0, 0, 10, 10])


# ----------------------------------------------------------------------------- reads


def qr_image(text: str) -> np.ndarray:
    code = cv2.QRCodeEncoder.create().encode(text)
    code = cv2.resize(code, None, fx=8, fy=8, interpolation=cv2.INTER_NEAREST)
    canvas = np.full((480, 640), 255, np.uint8)
    h, w = code.shape
    canvas[40 : 40 + h, 40 : 40 + w] = code
    return canvas


def test_reads_are_the_last_production_texts_newest_first(
    server: RunningConsole, client: Browserless
) -> None:
    with SyncVisionClient("127.0.0.1", server.app.port, auth_token=TOKEN) as robot:
        # the example's station_qr expects this text exactly
        for _ in range(2):
            found = robot.inspect("station_qr", qr_image("cellvision:station-1"))
            assert found.data["text"] == "cellvision:station-1"
    png = cv2.imencode(".png", qr_image("cellvision:station-1"))[1].tobytes()
    assert client.try_("station_qr", {"source": "upload"}, png).status == 200
    reads = client.get("/api/inspections/station_qr/reads?last=5").json()["reads"]
    assert [r["text"] for r in reads] == ["cellvision:station-1"] * 2  # the try is not one
    assert reads[0]["result_id"] > reads[1]["result_id"]
    assert reads[0]["step"] is None
    assert client.get("/api/inspections/station_qr/reads?last=51").status == 400
    assert client.get("/api/inspections/station_qr/reads?last=0").status == 400
    # A job's code steps: each step's text, named.
    log = server.app.service.results
    assert log is not None
    log.record(
        ResultEntry(
            time=time.time(),
            inspection="label_job",
            camera="qc",
            passed=True,
            data={"steps": {"label": {"type": "code", "text": "P-4711"},
                            "hole": {"type": "locate", "count": 1}}},
            duration_ms=1.0,
            config_hash="x",
        )
    )  # fmt: skip
    job = client.get("/api/inspections/label_job/reads").json()["reads"]
    assert [(r["step"], r["text"]) for r in job] == [("label", "P-4711")]


def test_a_fixtured_job_built_through_the_api_alone_is_served(tmp_path: Path) -> None:
    """What the page does for an integrator: a template trained on the camera's frame, a
    locate on it, a fixture from the locate, a presence check in the part's frame whose ROI is
    an offset from the fixture's frame the try answered, the job saved whole and run by a
    robot."""
    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        trained = train(c, "rotor_job", {"source": "camera", "rect": [440, 190, 140, 150],
                                          "config": {"camera": "qc"}})  # fmt: skip
        assert trained.status == 200, trained.body
        image = trained.json()["path"]
        locate = {"name": "rotor", "type": "locate", "method": "template",
                  "roi": [300, 100, 450, 400], "template": {"image": image}}  # fmt: skip
        fixture = {"name": "part", "type": "fixture", "origin": "rotor", "angle_from": "rotor"}
        job = {"name": "rotor_job", "type": "job", "camera": "qc", "steps": [locate, fixture]}
        first = c.try_("rotor_job", {"source": "camera", "config": job})
        assert first.status == 200, first.body
        frame = first.json()["data"]["steps"]["part"]
        assert first.json()["data"]["features"][0]["u"] == pytest.approx(frame["u"])
        # the centre of the rotor, 20 x 20 px around the frame's origin
        centre = {"name": "hub", "type": "presence", "fixture": "part", "roi": [-10, -10, 20, 20],
                  "measure": "mean_intensity", "min": 0}  # fmt: skip
        job["steps"] = [locate, fixture, centre]
        job["verdict"] = "all(rotor, part, hub)"
        tried = c.try_("rotor_job", {"source": "camera", "config": job})
        assert tried.json()["verdict"] == "pass", tried.body
        saved = put(c, "rotor_job", {"config": job, "why": "built on the page"})
        assert saved.status == 200, saved.body
        with SyncVisionClient("127.0.0.1", running.app.port, auth_token=TOKEN) as robot:
            result = robot.inspect("rotor_job")
        assert result.passed
        assert result.data["steps"]["hub"]["passed"] is True


def test_a_reload_that_fails_puts_the_old_file_back(tmp_path: Path) -> None:
    from vision_server.config import ConfigError

    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        original = running.config.read_text()
        service = running.app.service
        reloader = service.reloader

        def refuse() -> Any:
            raise ConfigError("camera 'qc' does not open", source="cell.yaml")

        running.call(lambda: setattr(service, "reloader", refuse))
        try:
            refused = put(c, "magnet_job", {"config": draft_job()})
        finally:
            running.call(lambda: setattr(service, "reloader", reloader))
        assert refused.status == 422
        assert "does not open" in refused.json()["error"]["message"]
        assert running.config.read_text() == original
        assert not list(tmp_path.glob("cell.yaml.bak-*"))
        assert put(c, "magnet_job", {"config": draft_job()}).status == 200


def test_reads_read_a_bounded_number_of_pages_past_tries() -> None:
    """Among many tries the reads stop after a few pages of the index, never reading on."""
    from types import SimpleNamespace

    from vision_server.frontends import http_build

    calls: list[dict[str, Any]] = []

    class Log:
        def query(self, **filters: Any) -> list[Any]:
            calls.append(filters)
            start = filters["before_id"] or 10_000
            return [
                SimpleNamespace(id=i, peer="console 127.0.0.1:1", is_try=True)
                for i in range(start - 1, start - 1 - filters["limit"], -1)
            ]

    rows = http_build._production_rows(Log(), "station_qr", 20)
    assert rows == []
    assert len(calls) == http_build.READS_PAGES
    assert all(c["inspection"] == "station_qr" and c["limit"] == 20 for c in calls)


def test_a_save_may_not_grow_the_file_past_its_bounds(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A text over MAX_TEXT characters, or a save that would grow the file past
    MAX_CONFIG_BYTES (here lowered to the file's size and 10 KB, so that a few saves reach
    it), are refused naming why: the file stays as it was."""
    from vision_server.frontends import http_save

    with console_server(tmp_path) as running:
        c = Browserless(running.url)
        c.login()
        before = running.config.read_bytes()
        config = {**draft_job(), "description": "d" * (http_save.MAX_TEXT + 1)}
        refused = put(c, "magnet_job", {"config": config, "why": "long"})
        assert refused.status == 422, refused.body
        assert "at most 4096" in refused.json()["error"]["message"]
        assert running.config.read_bytes() == before
        bound = len(before) + 10_000
        monkeypatch.setattr(http_save, "MAX_CONFIG_BYTES", bound)
        statuses = []
        for index in range(5):
            config = {**draft_job(), "name": f"job{index}", "description": "d" * 4000}
            reply = put(c, f"job{index}", {"config": config, "why": "bulk"})
            statuses.append(reply.status)
            if reply.status != 200:
                assert f"at most {bound}" in reply.json()["error"]["message"]
                break
        assert statuses == [200, 200, 422], statuses
        assert running.config.stat().st_size <= bound
