"""The conformance suite validates what a live server sends against protocol/schema
(SPEC §6.3.1): a configured cell passes, a server whose RESULT data breaks its type's schema
fails the check that received it, and a run without jsonschema says so in a skip."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from loopback import server_in_thread

from protocol import schema
from protocol.conformance import Target, run_checks
from robot_client import SyncVisionClient
from robot_client.devices.vision import intrinsics_from_dict
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.service import CellRuntime

DISTORTION = [-0.1, 0.02, 0.001, -0.002, 0.003]
CELL = f"""\
server: {{port: 0}}
cameras:
  tool: {{source: request}}
  fixed:
    source: folder
    path: frames
    intrinsics: {{width: 32, height: 24, fx: 40.0, fy: 40.0, cx: 15.5, cy: 11.5,
                 distortion: {DISTORTION}}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}}
  - {{name: code, type: qr, camera: tool}}
  - {{name: dots, type: locate, camera: tool, method: blob, min_count: 1, blob: {{}}}}
  - {{name: fixed_bright, type: presence, camera: fixed, measure: mean_intensity, min: 0}}
"""


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    frames = tmp_path / "frames"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((24, 32), 60 * (i + 1), np.uint8))
    path = tmp_path / "cell.yaml"
    path.write_text(CELL, encoding="utf-8")
    return path


def test_a_configured_cell_passes_every_check_with_every_answer_validated(cell: Path) -> None:
    runtime = CellRuntime(cell)
    try:
        with server_in_thread(runtime.catalog) as server:
            results = run_checks(Target("127.0.0.1", server.port, 10.0))
            with SyncVisionClient("127.0.0.1", server.port) as client:
                frames = client.capture("fixed")
    finally:
        runtime.close()
    not_passed = [(r.name, r.status, r.detail) for r in results if r.status != "pass"]
    assert not_passed == []
    assert "metadata_schemas" in {r.name for r in results}
    # The camera's distortion reaches the client under the name SPEC §6.4 gives it (the
    # server sent it as "distortion", and the client read zeros for "dist").
    assert frames.intrinsics is not None
    assert list(intrinsics_from_dict(frames.intrinsics).dist) == DISTORTION


@dataclass(frozen=True)
class ThreeCornerQR:
    """A "qr" inspection whose data breaks data/qr.json: three corners."""

    name: str = "bad_qr"
    camera: str = "tool"
    type: str = "qr"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        return InspectionOutcome(True, {"text": "x", "corners": [[0, 0], [1, 0], [1, 1]]})


def test_a_result_whose_data_breaks_its_schema_fails_naming_the_field() -> None:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [ThreeCornerQR()])
    with server_in_thread(catalog) as server:
        (result,) = run_checks(Target("127.0.0.1", server.port, 10.0), select="metadata_schemas")
    assert result.status == "fail"
    assert "RESULT" in result.detail
    assert "protocol/schema/data/qr.json at corners" in result.detail


def test_without_jsonschema_the_schema_check_skips_naming_the_package(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    schema._validators.cache_clear()
    monkeypatch.setitem(sys.modules, "jsonschema", None)
    try:
        with server_in_thread() as server:
            results = run_checks(Target("127.0.0.1", server.port, 10.0), select="ping")
            results += run_checks(Target("127.0.0.1", server.port, 10.0), select="metadata_schemas")
    finally:
        monkeypatch.undo()
        schema._validators.cache_clear()
    statuses = {r.name: (r.status, r.detail) for r in results}
    assert statuses["ping_pong"] == ("pass", "")
    status, detail = statuses["metadata_schemas"]
    assert status == "skip"
    assert "jsonschema is not installed" in detail
    assert "cellvision[conformance]" in detail
