"""The console's history API (docs/console.md, "History") through the real server with the
example cell, real HTTP on loopback: saves become versions with who and why, the list pages
newest first, a version shows its text and diff, a revert writes an old text as a new version
and reloads, and what the loader or the reload refuses leaves the file and the history as they
were. Also the ``vision-server history`` command on the same files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server

from protocol import ConfigInvalid
from vision_server.config import history

INTEGRATOR = "integrator-test-token-0123456789"
OPERATOR = "operator-test-token-0123456789"


@pytest.fixture
def running(tmp_path: Path) -> Iterator[RunningConsole]:
    with console_server(tmp_path, integrator_token=INTEGRATOR, operator_token=OPERATOR) as server:
        yield server


def signed_in(running: RunningConsole, token: str) -> Browserless:
    client = Browserless(running.url)
    assert client.login(token).status == 200
    return client


@pytest.fixture
def integrator(running: RunningConsole) -> Browserless:
    return signed_in(running, INTEGRATOR)


def save(client: Browserless, options: dict[str, Any], why: Any = None) -> Any:
    body: dict[str, Any] = {"options": options}
    if why is not None:
        body["why"] = why
    return client.post_json("/api/inspections/magnet_check/save", body)


def revert(client: Browserless, version: int, why: str = "back") -> Any:
    return client.post_json(f"/api/history/{version}/revert", {"why": why})


def assert_shown_without_secrets(shown: str, text: str) -> None:
    """``shown`` is ``text`` line for line, but the tokens' values are hidden."""
    assert TOKEN not in shown
    assert INTEGRATOR not in shown
    assert OPERATOR not in shown
    pairs = list(zip(shown.splitlines(), text.splitlines(), strict=True))
    for seen, line in pairs:
        if "_token:" in line:
            assert seen.split(":")[0] == line.split(":")[0]
            assert "<hidden " in seen
        else:
            assert seen == line
    assert sum("<hidden " in seen for seen, _ in pairs) == 3


def served_threshold(client: Browserless) -> Any:
    inspections = client.get("/api/inspections").json()["inspections"]
    return next(i for i in inspections if i["name"] == "magnet_check")["config"]["threshold"]


def test_two_saves_list_show_diff_and_revert(
    running: RunningConsole, integrator: Browserless
) -> None:
    original = running.config.read_text()
    first = save(integrator, {"threshold": 100}, "darker magnets")
    assert first.status == 200, first.body
    assert first.json()["version"] == 2
    admin = signed_in(running, TOKEN)
    second = save(admin, {"threshold": 110})  # no why: recorded empty
    assert second.json()["version"] == 3

    listed = integrator.get("/api/history").json()
    rows = [(v["version"], v["kind"], v["who"], v["why"]) for v in listed["versions"]]
    assert rows == [
        (3, "save", "admin", ""),
        (2, "save", "integrator", "darker magnets"),
        (1, "original", "unknown", ""),
    ]
    assert listed["versions"][0]["inspections"] == ["magnet_check"]
    assert listed["versions"][0]["config_hash"] == second.json()["config_hash"]
    assert listed["file_config_hash"] == listed["served_config_hash"]
    assert listed["next_before"] is None
    assert listed["limits"] == {"max_versions": 200, "max_bytes": 50 * 1024 * 1024}

    shown = integrator.get("/api/history/2").json()
    assert shown["why"] == "darker magnets"
    assert shown["previous"] == 1
    assert shown["is_file"] is False
    assert "threshold: 100" in shown["text"]
    assert "-    threshold: 90\n" in shown["diff"]
    assert "+    threshold: 100\n" in shown["diff"]
    assert_shown_without_secrets(integrator.get("/api/history/1").json()["text"], original)

    reverted = revert(integrator, 1, "back to the configured threshold")
    assert reverted.status == 200, reverted.body
    body = reverted.json()
    assert body["changed"] is True
    assert body["version"] == 4
    assert body["reverted_to"] == 1
    assert running.config.read_text() == original
    assert body["config_hash"] == running.app.service.catalog.config_hash
    assert served_threshold(integrator) == 90
    newest = integrator.get("/api/history?limit=1").json()
    assert newest["next_before"] == 4
    version = newest["versions"][0]
    assert (version["kind"], version["reverted_to"], version["who"]) == ("revert", 1, "integrator")
    assert version["why"] == "back to the configured threshold"
    assert integrator.get("/api/history/4").json()["is_file"] is True
    # Paging: before=4 goes on below it.
    older = integrator.get("/api/history?before=4&limit=2").json()
    assert [v["version"] for v in older["versions"]] == [3, 2]
    assert older["next_before"] == 2

    # Reverting to the text the file has: nothing written, said so.
    again = revert(integrator, 4)
    assert again.status == 200
    assert again.json()["changed"] is False
    assert "already holds version 4" in again.json()["message"]
    assert history.History(running.config).numbers() == [1, 2, 3, 4]


def test_a_revert_rescues_a_broken_hand_edit_and_a_broken_version_is_refused(
    running: RunningConsole, integrator: Browserless
) -> None:
    assert save(integrator, {"threshold": 100}, "darker").status == 200
    good = running.config.read_text()
    broken = good.replace("threshold: 100", "threshold: 300")
    running.config.write_text(broken)  # by hand, not loaded
    rescued = revert(integrator, 2, "undo the hand edit")
    assert rescued.status == 200, rescued.body
    assert rescued.json()["version"] == 4
    kept = history.History(running.config)
    outside = kept.get(3)
    assert (outside.kind, outside.who) == ("edited_outside", "unknown")
    assert kept.text(3).decode() == broken
    assert running.config.read_text() == good

    hash_before = running.app.service.catalog.config_hash
    refused = revert(integrator, 3, "try the hand edit")
    assert refused.status == 422, refused.body
    error = refused.json()["error"]
    assert error["code"] == "CONFIG_REFUSED"
    assert "version 3 cannot be loaded" in error["message"]
    assert "threshold" in error["message"]
    assert running.config.read_text() == good
    assert kept.numbers() == [1, 2, 3, 4]
    assert running.app.service.catalog.config_hash == hash_before


def test_a_revert_whose_reload_fails_puts_the_file_back(
    running: RunningConsole, integrator: Browserless, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert save(integrator, {"threshold": 100}, "darker").status == 200
    before = running.config.read_bytes()

    async def refuse() -> Any:
        raise ConfigInvalid("camera 'qc' does not open")

    monkeypatch.setattr(running.app.service, "reload", refuse)
    failed = revert(integrator, 1)
    assert failed.status == 422, failed.body
    assert "camera 'qc' does not open" in failed.json()["error"]["message"]
    assert "put back" in failed.json()["error"]["message"]
    assert running.config.read_bytes() == before
    assert history.History(running.config).numbers() == [1, 2]
    monkeypatch.undo()
    assert served_threshold(integrator) == 100


@pytest.mark.parametrize(
    ("why", "words"),
    [
        ("x" * 501, "501 characters, at most 500"),
        (42, "why must be a string"),
        (["a"], "why must be a string"),
    ],
)
def test_a_bad_why_is_refused_before_anything_is_written(
    running: RunningConsole, integrator: Browserless, why: Any, words: str
) -> None:
    before = running.config.read_bytes()
    for reply in (
        save(integrator, {"threshold": 100}, why),
        integrator.post_json("/api/history/1/revert", {"why": why}),
    ):
        assert reply.status == 400, reply.body
        assert reply.json()["error"]["code"] == "BAD_REQUEST"
        assert words in reply.json()["error"]["message"]
    assert running.config.read_bytes() == before
    assert not history.History(running.config).folder.exists()
    # 500 characters are kept whole.
    saved = save(integrator, {"threshold": 100}, "y" * 500)
    assert saved.status == 200
    assert integrator.get("/api/history/2").json()["why"] == "y" * 500


def test_an_operator_reads_no_token_in_the_history(
    running: RunningConsole, integrator: Browserless
) -> None:
    """The texts and diffs shown hide every token (an operator must not read the admin's);
    a changed token still shows as a changed line, without either value."""
    original = running.config.read_text()
    assert save(integrator, {"threshold": 100}, "darker").status == 200
    rotated = running.config.read_text().replace(TOKEN, "a-new-admin-token-9876543210")
    running.config.write_text(rotated)  # by hand
    assert revert(integrator, 1, "undo the hand edit").status == 200
    operator = signed_in(running, OPERATOR)
    for number in (1, 2, 3, 4):
        shown = operator.get(f"/api/history/{number}").json()
        for secret in (TOKEN, INTEGRATOR, OPERATOR, "a-new-admin-token-9876543210"):
            assert secret not in shown["text"]
            assert secret not in shown["diff"]
    assert_shown_without_secrets(operator.get("/api/history/1").json()["text"], original)
    outside = operator.get("/api/history/3").json()
    assert outside["kind"] == "edited_outside"
    changed = [line for line in outside["diff"].splitlines() if line[:1] in "+-"]
    assert [line.split(":")[0] for line in changed[2:]] == ["-  auth_token", "+  auth_token"]
    assert changed[2] != changed[3]  # different fingerprints
    # The command line on the cell PC reads the file itself: it shows the text as written.
    assert cli("--config", str(running.config), "show", "3").stdout == rotated


def test_roles_the_front_door_and_bad_requests(
    running: RunningConsole, integrator: Browserless
) -> None:
    assert save(integrator, {"threshold": 100}, "darker").status == 200
    anonymous = Browserless(running.url)
    assert anonymous.get("/api/history").status == 401
    assert anonymous.get("/api/history/1").status == 401
    operator = signed_in(running, OPERATOR)
    assert operator.get("/api/history").status == 200
    assert operator.get("/api/history/2").status == 200
    refused = revert(operator, 1)
    assert refused.status == 403
    assert refused.json()["error"]["code"] == "FORBIDDEN"
    # Without the page's header: another site's form.
    cross = integrator.request(
        "POST", "/api/history/1/revert", b'{"why": "x"}', {"X-Cellvision": ""}
    )
    assert cross.status == 403
    assert cross.json()["error"]["code"] == "CROSS_SITE"
    assert history.History(running.config).numbers() == [1, 2]

    assert integrator.get("/api/history/9").status == 404
    assert integrator.get("/api/history/9").json()["error"]["code"] == "NOT_FOUND"
    assert revert(integrator, 9).status == 404
    assert integrator.get("/api/history/0").status == 404
    assert integrator.get("/api/history/abc").status == 404
    for query in ("limit=0", "limit=201", "limit=x", "before=0", "before=-1"):
        reply = integrator.get(f"/api/history?{query}")
        assert reply.status == 400, query
        assert reply.json()["error"]["code"] == "BAD_REQUEST"
    big = integrator.request(
        "POST",
        "/api/history/1/revert",
        json.dumps({"why": "x" * 5000}).encode(),
        {"Content-Type": "application/json"},
    )
    assert big.status == 413
    for raw in (b"not json", b"[1]", b'"x"'):
        reply = integrator.request("POST", "/api/history/1/revert", raw)
        assert reply.status == 400, raw
    assert history.History(running.config).numbers() == [1, 2]


def test_revert_is_off_when_saving_is(tmp_path: Path) -> None:
    with console_server(tmp_path, allow_reload="false") as running:
        client = signed_in(running, TOKEN)
        assert client.get("/api/history").json()["versions"] == []
        refused = revert(client, 1)
        assert refused.status == 403
        assert refused.json()["error"]["code"] == "CONFIG_REFUSED"


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "CELLVISION_CONFIG"}
    return subprocess.run(
        [sys.executable, "-m", "vision_server", "history", *args],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
        env=env,
    )


def test_the_command_line_lists_shows_and_diffs_the_same_versions(
    running: RunningConsole, integrator: Browserless
) -> None:
    original = running.config.read_text()
    assert save(integrator, {"threshold": 100}, "darker magnets").status == 200
    config = str(running.config)
    listed = cli("--config", config)
    assert listed.returncode == 0, listed.stderr
    assert "darker magnets" in listed.stdout
    assert "integrator" in listed.stdout
    assert "the file as found" in listed.stdout
    as_json = cli("--config", config, "--json")
    rows = [json.loads(line) for line in as_json.stdout.splitlines()]
    assert [(r["version"], r["who"]) for r in rows] == [(2, "integrator"), (1, "unknown")]
    shown = cli("--config", config, "show", "1")
    assert shown.returncode == 0
    assert shown.stdout == original
    diff = cli("--config", config, "diff", "2")
    assert "+    threshold: 100" in diff.stdout
    assert diff.stdout.startswith("--- version 1\n+++ version 2\n")
    missing = cli("--config", config, "show", "7")
    assert missing.returncode == 2
    assert "no version 7" in missing.stderr
    assert cli("--config", config, "diff").returncode == 2
    shown_json = json.loads(cli("--config", config, "show", "1", "--json").stdout)
    assert (shown_json["version"], shown_json["kind"], shown_json["text"]) == (
        1,
        "original",
        original,
    )
    nowhere = cli("--config", str(running.config.with_name("nowhere.yaml")))
    assert nowhere.returncode == 2
    assert "no such file" in nowhere.stderr
    unconfigured = cli("show", "1")
    assert unconfigured.returncode == 2
    assert "give --config FILE" in unconfigured.stderr


def test_without_sign_in_the_console_is_who_saved(tmp_path: Path) -> None:
    with console_server(tmp_path, token=None) as running:
        client = Browserless(running.url)
        assert save(client, {"threshold": 100}, "open cell").status == 200
        newest = client.get("/api/history?limit=1").json()["versions"][0]
        assert (newest["who"], newest["why"]) == ("console", "open cell")


def test_a_revert_checks_the_roi_against_the_running_cameras(
    running: RunningConsole, integrator: Browserless
) -> None:
    """A version whose ROI lies outside the image the QC camera declares once open is refused
    as a save of that ROI is (the loader alone cannot know the simulated camera's size)."""
    good = running.config.read_text()
    outside = good.replace("roi: [486, 236, 50, 60]", "roi: [1000, 700, 100, 100]")
    assert outside != good
    running.config.write_text(outside)  # by hand
    assert save(integrator, {"threshold": 100}, "x").status == 422  # the save refuses it too
    running.config.write_text(good)
    assert save(integrator, {"threshold": 100}, "x").status == 200
    kept = history.History(running.config)
    # Put the hand edit's text in the history as a version of its own, as a catch-up would.
    running.config.write_text(outside)
    assert revert(integrator, 2, "undo the hand edit").status == 200
    assert kept.text(3).decode() == outside
    refused = revert(integrator, 3)
    assert refused.status == 422, refused.body
    assert "1024x768" in refused.json()["error"]["message"]
    assert running.config.read_text() == kept.text(4).decode()
