"""The console's save (docs/console.md, ``POST /api/inspections/{name}/save``) cannot be used
to change the configuration beyond one inspection's tuned values: real HTTP on loopback, port 0,
the real server with the example cell and its configuration file's runtime.

- a key is a dotted name (a newline in it cannot add lines) and never one fixed by the
  configuration; a value that is YAML-significant text is refused or stored as that text;
- a save is validated as a try is, the running cameras' image sizes included;
- the history is bounded, and a save that fails while writing leaves neither a partial
  version nor a changed file.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from console_server import Browserless, RunningConsole, console_server

from vision_server.config import files, history

SAVE = "/api/inspections/{}/save"


@pytest.fixture
def running(tmp_path: Path) -> Iterator[RunningConsole]:
    with console_server(tmp_path) as server:
        yield server


@pytest.fixture
def client(running: RunningConsole) -> Browserless:
    c = Browserless(running.url)
    assert c.login().status == 200
    return c


def save(client: Browserless, options: dict[str, Any], name: str = "magnet_check") -> Any:
    return client.post_json(SAVE.format(name), {"options": options})


def backups(running: RunningConsole) -> list[Path]:
    """The history's version files (none before the first save)."""
    return sorted(running.config.parent.glob(f"{running.config.name}.history/*"))


def folder(running: RunningConsole) -> list[str]:
    """The configuration's folder (temporary files included), without the result log's."""
    return sorted(p.name for p in running.config.parent.iterdir() if "results" not in p.name)


def inspection(running: RunningConsole, name: str) -> dict[str, Any]:
    data = yaml.safe_load(running.config.read_text(encoding="utf-8"))
    found: dict[str, Any] = next(i for i in data["inspections"] if i["name"] == name)
    return found


def assert_refused(reply: Any, *words: str) -> str:
    assert reply.status == 422, reply.body
    error = reply.json()["error"]
    assert error["code"] == "CONFIG_REFUSED"
    for word in words:
        assert word in error["message"]
    message: str = error["message"]
    return message


# ----------------------------------------------------------------------------- keys and values


@pytest.mark.parametrize(
    "key",
    [
        "min\n  - name: x",
        "description: x\n    number",
        "x\n  - name: injected\n    type: presence\n    camera: qc\n    y",
        "threshold ",
        "min: 0.3 #",
        "circle..min_radius_px",
        "",
        "<<",
    ],
)
def test_a_key_that_is_not_a_plain_name_is_refused_and_the_file_is_unchanged(
    running: RunningConsole, client: Browserless, key: str
) -> None:
    before = running.config.read_bytes()
    assert_refused(save(client, {key: 1}), "cell.yaml", "magnet_check", "is not a key")
    assert running.config.read_bytes() == before
    assert not backups(running)


@pytest.mark.parametrize("key", ["number", "type", "camera", "name", "template", "output"])
def test_a_key_fixed_by_the_configuration_is_refused(
    running: RunningConsole, client: Browserless, key: str
) -> None:
    before = running.config.read_bytes()
    value = {"number": 7, "type": "locate", "camera": "tool"}.get(key, "x")
    assert_refused(save(client, {key: value}), key, "cannot be changed from the console")
    # Nested under a fixed key too (output.fields would be output's).
    assert_refused(save(client, {f"{key}.x": 1}), key, "cannot be changed from the console")
    assert running.config.read_bytes() == before
    assert not backups(running)


SIGNIFICANT = [
    "1\n- name: x",
    "1\n    number: 7",
    "{a: 1}",
    "[1, 2]",
    "&anchor",
    "*anchor",
    "!!python/object/apply:os.system ['true']",
    "# a comment",
    "- name: injected",
    "yes",
    "'\"\\",
    "\u2028\x85\x00 line breaks",
]


def test_yaml_significant_text_is_stored_as_that_text_never_as_structure(
    running: RunningConsole, client: Browserless
) -> None:
    names = [i["name"] for i in yaml.safe_load(running.config.read_text())["inspections"]]
    for text in SIGNIFICANT:
        saved = save(client, {"description": text})  # a key that takes any string
        assert saved.status == 200, (text, saved.body)
        data = yaml.safe_load(running.config.read_text())
        assert [i["name"] for i in data["inspections"]] == names
        written = inspection(running, "magnet_check")
        assert written["description"] == text
        assert "number" not in written
        # The server serves it as that text too.
        served = next(
            i
            for i in client.get("/api/inspections").json()["inspections"]
            if i["name"] == "magnet_check"
        )
        assert served["config"]["description"] == text


@pytest.mark.parametrize("text", SIGNIFICANT)
def test_yaml_significant_text_where_a_number_belongs_is_refused(
    running: RunningConsole, client: Browserless, text: str
) -> None:
    before = running.config.read_bytes()
    assert_refused(save(client, {"min": text}), "min", "expected a number")
    assert running.config.read_bytes() == before


@pytest.mark.parametrize(
    "value", [{"a": 1}, [[1, 2]], [{"a": 1}], None], ids=["mapping", "nested", "list", "null"]
)
def test_a_value_that_is_not_plain_is_refused(
    running: RunningConsole, client: Browserless, value: Any
) -> None:
    before = running.config.read_bytes()
    assert_refused(save(client, {"threshold": value}), "threshold", "expected a number")
    assert running.config.read_bytes() == before


def test_a_save_is_no_larger_than_a_tries_request_part(
    running: RunningConsole, client: Browserless
) -> None:
    before = running.config.read_bytes()
    reply = save(client, {"description": "x" * (64 * 1024)})
    assert reply.status == 413, reply.body
    assert reply.json()["error"]["code"] == "TOO_LARGE"
    assert running.config.read_bytes() == before


def test_a_save_changes_only_the_values_it_names(
    running: RunningConsole, client: Browserless
) -> None:
    before = running.config.read_text()
    assert save(client, {"threshold": 120}).status == 200
    assert running.config.read_text() == before.replace("threshold: 90", "threshold: 120", 1)
    middle = running.config.read_text()
    saved = save(client, {"circle.min_radius_px": 70}, name="cap_locate")
    assert saved.status == 200, saved.body
    assert running.config.read_text() == middle.replace("min_radius_px: 60", "min_radius_px: 70")


# ----------------------------------------------------------------------------- as a try


def test_an_roi_outside_the_declared_image_is_refused_as_a_try_refuses_it(
    running: RunningConsole, client: Browserless
) -> None:
    before = running.config.read_bytes()
    outside = [1000, 700, 100, 100]
    # A camera whose configuration declares its size (the tool camera's intrinsics): the
    # save gives the try's reason, naming the key in the file rather than in the options.
    tried = client.try_("cap_locate", {"source": "upload", "options": {"roi": outside}}, b"-")
    assert tried.status == 400, tried.body
    prefix = "inspection 'cap_locate': options -> roi: "
    message = tried.json()["error"]["message"]
    assert message.startswith(prefix)
    reason = message.removeprefix(prefix)
    assert "1024x768" in reason
    refused = assert_refused(save(client, {"roi": outside}, name="cap_locate"), "cap_locate")
    assert refused.endswith(f"-> roi: {reason}")
    # A camera that declares its size once open (the simulated QC camera: its scene's): the
    # try refuses the ROI, so does the save, and the robots' requests keep working.
    tried = client.try_("magnet_check", {"source": "camera", "options": {"roi": outside}})
    assert tried.status == 400, tried.body
    assert "1024x768" in tried.json()["error"]["message"]
    assert_refused(save(client, {"roi": outside}), "magnet_check", "-> roi: ", "1024x768")
    assert running.config.read_bytes() == before
    assert not backups(running)
    assert client.try_("magnet_check", {"source": "camera"}).status == 200
    # Inside the image it is saved.
    assert save(client, {"roi": [924, 668, 100, 100]}).status == 200


# ----------------------------------------------------------------------------- history


def test_the_history_is_bounded(running: RunningConsole, client: Browserless) -> None:
    """With the history's bounds at 20 versions, 30 saves keep the newest 20, each holding the
    text its save wrote; files beside the configuration are never touched."""
    history.set_bounds(running.config, history.Bounds(max_versions=20))
    mine = running.config.with_name(f"{running.config.name}.bak-mine")
    mine.write_text("a copy the integrator made\n")
    stray = running.config.with_name(f"{running.config.name}.history") / "notes.txt"
    texts = []
    numbers = []
    for i in range(30):
        saved = save(client, {"threshold": 100 + i})
        assert saved.status == 200, saved.body
        if i == 0:
            stray.write_text("mine\n")
        texts.append(running.config.read_text())
        numbers.append(saved.json()["version"])
        assert len(history.History(running.config).numbers()) <= 20
    kept = history.History(running.config)
    assert kept.numbers() == numbers[-20:] == list(range(12, 32))
    for number, text in zip(kept.numbers(), texts[-20:], strict=True):
        assert kept.text(number).decode() == text
    assert mine.read_text() == "a copy the integrator made\n"
    assert stray.read_text() == "mine\n"
    assert not [n for n in folder(running) if n.endswith(".tmp")]


class FailingOs:
    """``os`` for http_save, whose fsync of a temporary file that ``fails`` (by its name) first
    cuts the file to half its size (a disk that filled up mid-write) and then fails."""

    def __init__(self, fails: Callable[[str], bool]) -> None:
        self.fails = fails
        self.failed = 0

    def __getattr__(self, name: str) -> Any:
        return getattr(os, name)

    def fsync(self, fd: int) -> None:
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
        if name.endswith(".tmp") and self.fails(name):
            self.failed += 1
            os.ftruncate(fd, os.fstat(fd).st_size // 2)
            raise OSError(errno.ENOSPC, "No space left on device")
        os.fsync(fd)


@pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs /proc/self/fd")
@pytest.mark.parametrize("target", ["version", "configuration"])
def test_a_save_that_fails_while_writing_leaves_no_partial_version(
    running: RunningConsole,
    client: Browserless,
    monkeypatch: pytest.MonkeyPatch,
    target: str,
) -> None:
    assert save(client, {"threshold": 100}).status == 200  # two versions already there
    before = running.config.read_bytes()
    listed = folder(running)
    kept = [(b.name, b.read_bytes()) for b in backups(running)]
    # The temporary files are ".<random>.tmp" in the history's folder (the version, written
    # first) and ".cell.yaml.<random>.tmp" (the new configuration, written after it).
    config_tmp = f".{running.config.name}."
    failing = FailingOs(lambda name: name.startswith(config_tmp) == (target == "configuration"))
    monkeypatch.setattr(files, "os", failing)
    failed = save(client, {"threshold": 120})
    monkeypatch.undo()
    assert failing.failed == 1
    assert failed.status == 500, failed.body
    error = failed.json()["error"]
    assert error["code"] == "CONFIG_REFUSED"
    assert "No space left on device" in error["message"]
    assert running.config.read_bytes() == before
    assert folder(running) == listed  # no partial version, no temporary file
    assert [(b.name, b.read_bytes()) for b in backups(running)] == kept
    # The server still serves the old values, and the next save works.
    served = client.get("/api/inspections").json()["inspections"]
    assert next(i for i in served if i["name"] == "magnet_check")["config"]["threshold"] == 100
    assert save(client, {"threshold": 130}).status == 200
