"""The online board and its API (vision_server/frontends/online_board.py, http_online.py)
against the real server with the example cell: production results through the robot's
protocol are counted, console tries are not; the strip is bounded and carries the log's ids;
an unchanged board answers 304; a reset needs the integrator; the board never reads the log."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import cv2
import numpy as np
import pytest
from console_server import TOKEN, Browserless, RunningConsole, example_config, running_cell

from robot_client import SyncVisionClient
from vision_server.frontends.online_board import STRIP_LENGTH

OPERATOR, INTEGRATOR = "online-operator-token-1", "online-integrator-token-2"


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    folder = tmp_path_factory.mktemp("online")
    config = example_config(
        folder, extra_server=f"  operator_token: {OPERATOR}\n  integrator_token: {INTEGRATOR}\n"
    )
    with running_cell(config) as running:
        yield running


@pytest.fixture
def robot(cell: RunningConsole) -> Iterator[SyncVisionClient]:
    client = SyncVisionClient("127.0.0.1", cell.app.port, auth_token=TOKEN, request_timeout_s=60)
    try:
        yield client
    finally:
        client.close()


def _client(cell: RunningConsole, token: str = TOKEN) -> Browserless:
    client = Browserless(cell.url)
    assert client.login(token).status == 200
    return client


@pytest.fixture
def admin(cell: RunningConsole) -> Browserless:
    client = _client(cell)
    assert client.post_json("/api/online/reset", {}).status == 200  # each test from zero
    return client


def _caps() -> np.ndarray:
    """A tool-camera image with two bright caps (cap_locate passes)."""
    image = np.full((768, 1024), 40, np.uint8)
    cv2.circle(image, (300, 300), 80, 230, -1)
    cv2.circle(image, (700, 420), 70, 230, -1)
    return image


def _entry(board: dict[str, Any], name: str) -> dict[str, Any]:
    for camera in board["cameras"]:
        for inspection in camera["inspections"]:
            if inspection["name"] == name:
                return {**inspection, "camera": camera["name"]}
    raise AssertionError(f"{name} is not on the board")


def test_production_results_are_counted_and_console_tries_are_not(
    cell: RunningConsole, admin: Browserless, robot: SyncVisionClient
) -> None:
    verdicts = [robot.inspect("magnet_check").passed for _ in range(3)]
    assert verdicts == [False, False, False]  # the example cell's empty slot
    tried = _client(cell, INTEGRATOR).try_(
        "magnet_check", {"source": "camera", "options": {"min": 0.0}}
    )
    assert tried.status == 200
    assert tried.json()["verdict"] == "pass"  # a try that passes must not count

    board = admin.get("/api/online").json()
    entry = _entry(board, "magnet_check")
    assert entry["camera"] == "qc"
    assert (entry["pass"], entry["fail"], entry["total"], entry["yield"]) == (0, 3, 3, 0.0)
    # the strip: the three production rows of the log, oldest first (newest at the right)
    rows = admin.get("/api/results?inspection=magnet_check&limit=10").json()["results"]
    production = [r["id"] for r in rows if not r["try"]][:3]
    assert [v["result_id"] for v in entry["strip"]] == sorted(production)
    assert [v["passed"] for v in entry["strip"]] == [False, False, False]
    last = entry["last"]
    assert last["passed"] is False
    assert last["result_id"] == max(production)
    assert last["image_size"] == [1024, 768]
    assert last["summary"] == "dark_fraction = 0.000"
    assert {"kind": "rect", "role": "fail", "x": 486, "y": 236, "w": 50, "h": 60} in last["shapes"]
    # every configured inspection is listed under its camera, with or without results
    cameras = {c["name"]: [i["name"] for i in c["inspections"]] for c in board["cameras"]}
    assert cameras == {
        "tool": ["cap_locate"],
        "rgbd": ["station_qr", "station_pose"],
        "qc": ["magnet_check"],
    }
    assert _entry(board, "station_qr")["last"] is None


def test_a_located_part_carries_its_features_as_shapes(
    admin: Browserless, robot: SyncVisionClient
) -> None:
    result = robot.inspect("cap_locate", _caps())
    assert result.passed
    entry = _entry(admin.get("/api/online").json(), "cap_locate")
    assert (entry["pass"], entry["fail"], entry["yield"]) == (1, 0, 1.0)
    circles = [s for s in entry["last"]["shapes"] if s["kind"] == "circle"]
    assert len(circles) == 2
    centres = sorted((round(c["u"]), round(c["v"])) for c in circles)
    assert centres == [(300, 300), (700, 420)]
    assert entry["last"]["image_size"] == [1024, 768]


def test_an_unchanged_board_answers_304_until_a_result_changes_it(
    admin: Browserless, robot: SyncVisionClient
) -> None:
    first = admin.get("/api/online")
    tag = first.headers["ETag"]
    again = admin.request("GET", "/api/online", headers={"If-None-Match": tag})
    assert again.status == 304
    assert again.body == b""
    robot.inspect("magnet_check")
    changed = admin.request("GET", "/api/online", headers={"If-None-Match": tag})
    assert changed.status == 200
    assert changed.headers["ETag"] != tag
    assert changed.json()["sequence"] > first.json()["sequence"]


def test_the_strip_keeps_the_last_verdicts_only(
    admin: Browserless, robot: SyncVisionClient
) -> None:
    runs = STRIP_LENGTH + 3
    dark = np.full((768, 1024), 40, np.uint8)  # no cap: fails
    for i in range(runs):
        robot.inspect("cap_locate", _caps() if i % 2 == 0 else dark)
    entry = _entry(admin.get("/api/online").json(), "cap_locate")
    assert entry["total"] == runs
    assert (entry["pass"], entry["fail"]) == ((runs + 1) // 2, runs // 2)
    strip = entry["strip"]
    assert len(strip) == STRIP_LENGTH
    # the newest at the right: the last run (an even index: the caps image) passed
    assert strip[-1]["passed"] is ((runs - 1) % 2 == 0)
    ids = [v["result_id"] for v in strip]
    assert ids == sorted(ids)
    assert entry["last"]["result_id"] == ids[-1]


def test_a_reset_needs_the_integrator_and_zeroes_one_inspection_or_all(
    cell: RunningConsole, admin: Browserless, robot: SyncVisionClient
) -> None:
    robot.inspect("magnet_check")
    robot.inspect("cap_locate", _caps())
    operator = _client(cell, OPERATOR)
    assert operator.get("/api/online").status == 200  # viewing: the operator's
    refused = operator.post_json("/api/online/reset", {})
    assert refused.status == 403
    assert refused.json()["error"]["code"] == "FORBIDDEN"
    assert "integrator" in refused.json()["error"]["message"]
    assert Browserless(cell.url).get("/api/online").status == 401

    integrator = _client(cell, INTEGRATOR)
    reply = integrator.post_json("/api/online/reset", {"inspection": "magnet_check"})
    assert reply.status == 200
    assert reply.json()["reset"] == ["magnet_check"]
    board = admin.get("/api/online").json()
    magnet, caps = _entry(board, "magnet_check"), _entry(board, "cap_locate")
    assert (magnet["total"], magnet["strip"]) == (0, [])
    assert magnet["last"] is not None  # the last graphics stay on the image
    assert caps["total"] == 1
    # an empty body (the page's "Reset all counts") resets every inspection
    everything = integrator.request("POST", "/api/online/reset", b"")
    assert everything.status == 200
    assert _entry(admin.get("/api/online").json(), "cap_locate")["total"] == 0


@pytest.mark.parametrize(
    ("body", "status", "code"),
    [
        (b'{"inspection": "no_such"}', 404, "UNKNOWN_INSPECTION"),
        (b'{"inspection": 7}', 400, "INVALID_ARGUMENT"),
        (b'{"inspection": "cap_locate", "all": true}', 400, "INVALID_ARGUMENT"),
        (b"[1, 2]", 400, "INVALID_ARGUMENT"),
        (b"{not json", 400, "INVALID_ARGUMENT"),
        (b"[" * 5000 + b"]" * 5000, 413, "TOO_LARGE"),
    ],
)
def test_a_bad_reset_is_refused_with_its_reason(
    admin: Browserless, body: bytes, status: int, code: str
) -> None:
    reply = admin.request("POST", "/api/online/reset", body, {"Content-Type": "application/json"})
    assert reply.status == status, reply.body
    error = reply.json()["error"]
    assert error["code"] == code
    assert error["message"]


def test_the_board_never_reads_the_result_log(
    cell: RunningConsole, admin: Browserless, robot: SyncVisionClient
) -> None:
    """The page polls /api/online: with 100,000 stored results it must cost what it costs
    with none, so it reads memory only."""
    service = cell.app.service
    real = service.results
    touched: list[str] = []

    class Spy:
        def __getattr__(self, name: str) -> Any:
            touched.append(name)
            return getattr(real, name)

    robot.inspect("magnet_check")
    service.results = Spy()  # type: ignore[assignment]
    try:
        for _ in range(3):
            assert admin.get("/api/online").status == 200
        assert admin.post_json("/api/online/reset", {}).status == 200
    finally:
        service.results = real
    assert touched == []


# ----------------------------------------------------------------------------- the board alone


class _Catalog:
    def __init__(self, inspections: dict[str, Any], config_hash: str) -> None:
        self.inspections = inspections
        self.cameras = {"qc": object()}
        self.config_hash = config_hash

    def tuned(self, inspection: Any, options: Any) -> Any:
        return inspection


class _Service:
    """What the board uses of the service: its catalog and its observers."""

    def __init__(self, names: list[str]) -> None:
        self.catalog = _Catalog({n: _inspection(n) for n in names}, "hash-1")
        self.observers: list[Any] = []

    def subscribe(self, observer: Any) -> Any:
        self.observers.append(observer)
        return lambda: self.observers.remove(observer)

    def answer(self, name: str, passed: bool, peer: str = "10.0.0.7:4000") -> None:
        from vision_server.service import InspectionRecord, InspectReply, InspectRequest

        reply = InspectReply(name, "qc", passed, {"value": 0.5}, 1.0, 2.0, "h", True)
        for observer in self.observers:
            observer(InspectionRecord(InspectRequest(name, peer=peer), reply))


def _inspection(name: str) -> Any:
    from types import SimpleNamespace

    return SimpleNamespace(name=name, type="presence", camera="qc")


def test_the_board_forgets_inspections_a_reload_removed_and_its_tag_follows_the_reload() -> None:
    from vision_server.frontends.online_board import OnlineBoard

    service = _Service(["a", "b"])
    board = OnlineBoard(service, strip_length=4)  # type: ignore[arg-type]
    for i in range(10):
        service.answer("a", i % 3 != 0)
        service.answer("b", True)
    service.answer("a", True, peer="console 127.0.0.1:5000")  # a try: not counted
    tag, snapshot = board.snapshot()
    (camera,) = snapshot["cameras"]
    a = camera["inspections"][0]
    assert (a["pass"], a["fail"], len(a["strip"])) == (6, 4, 4)
    assert board.snapshot()[1] is snapshot  # unchanged: the same answer, not built again
    # a reload that drops "b": its tally goes, the tag changes
    service.catalog = _Catalog({"a": _inspection("a")}, "hash-2")
    new_tag, after = board.snapshot()
    assert new_tag != tag
    assert [i["name"] for i in after["cameras"][0]["inspections"]] == ["a"]
    assert set(board._tallies) == {"a"}
    board.close()
    assert service.observers == []
