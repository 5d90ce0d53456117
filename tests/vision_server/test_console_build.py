"""Building inspections through the console's API (docs/console.md, "Building inspections: the
API"): a try of a whole edited or new mapping, and saving one whole, against the real server
with the example cell (real sockets on loopback, port 0, the configuration file's runtime).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server

from robot_client import SyncVisionClient
from vision_server.config import load_config

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
        assert body["backup"].startswith("cell.yaml.bak-")
        assert (tmp_path / body["backup"]).read_text() == original
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
