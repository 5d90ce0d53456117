"""The ``calibration_board`` inspection: configured from YAML, run through a real server on
loopback on images of the simulated board, its data valid against the protocol's schema."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from loopback import client_for, run, server_in_thread

from protocol import schema
from simulation import SimCell, load_scene
from vision_server.config import ConfigError
from vision_server.inspections import RESULT_KINDS
from vision_server.service import CellRuntime

CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  tool: {source: request}
inspections:
  - name: charuco
    type: calibration_board
    camera: tool
    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}
  - name: chess
    type: calibration_board
    camera: tool
    board: {kind: chessboard, columns: 11, rows: 8, square_m: 0.03}
"""


@pytest.fixture
def runtime(tmp_path: Path) -> Iterator[CellRuntime]:
    path = tmp_path / "cell.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    cell = CellRuntime(path)
    try:
        yield cell
    finally:
        cell.close()


def _board_image(kind: str) -> np.ndarray:
    scene = load_scene("examples/scenes/intrinsics_cell.yaml")
    if kind == "chessboard":
        from dataclasses import replace

        board = replace(scene.calibration_boards[0], kind="chessboard")
        scene = replace(scene, calibration_boards=(board,))
    return SimCell(scene).render("fixed_camera").color


@pytest.mark.parametrize(("inspection", "kind"), [("charuco", "charuco"), ("chess", "chessboard")])
def test_corners_come_back_over_the_wire(runtime: CellRuntime, inspection: str, kind: str) -> None:
    image = _board_image(kind)

    async def body() -> dict[str, object]:
        with server_in_thread(runtime.catalog) as server:
            async with client_for(server) as client:
                result = await client.inspect(inspection, image)
                assert result.passed
                return dict(result.data)

    data = run(body())
    schema.validate_data("calibration_board", data)
    assert data["count"] == 70
    assert data["of"] == 70
    assert data["ids"] == list(range(70))
    assert data["squares"] == [11, 8]
    corners = np.asarray(data["corners"])
    points = np.asarray(data["object_points"])
    assert corners.shape == (70, 2)
    assert points[1, 0] - points[0, 0] == pytest.approx(0.03)
    assert RESULT_KINDS["calibration_board"].summary(data) == {"count": 70.0}


def test_no_board_is_a_fail_with_a_reason(runtime: CellRuntime) -> None:
    blank = np.full((480, 640), 128, np.uint8)

    async def body() -> tuple[bool, dict[str, object]]:
        with server_in_thread(runtime.catalog) as server:
            async with client_for(server) as client:
                result = await client.inspect("charuco", blank)
                return result.passed, dict(result.data)

    passed, data = run(body())
    assert not passed
    schema.validate_data("calibration_board", data)
    assert data["found"] is False
    assert "0 of the 70 corners" in str(data["reason"])


@pytest.mark.parametrize(
    ("board", "message"),
    [
        ("{kind: charuco, columns: 5, rows: 5, square_m: 0.03, marker_m: 0.03}", "marker_m"),
        ("{kind: charuco, columns: 20, rows: 20, square_m: 0.03, marker_m: 0.02}", "needs 200"),
        ("{kind: chessboard, columns: 2, rows: 5, square_m: 0.03}", "at least 3 x 3"),
        ("{kind: dots, columns: 5, rows: 5, square_m: 0.03}", "kind"),
        (
            "{kind: charuco, columns: 5, rows: 5, square_m: 0.03, marker_m: 0.02, dictionary: X}",
            "dictionary",
        ),
    ],
)
def test_a_bad_board_is_a_config_error_naming_it(tmp_path: Path, board: str, message: str) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(
        "cameras:\n  tool: {source: request}\ninspections:\n"
        f"  - {{name: b, type: calibration_board, camera: tool, board: {board}}}\n",
        encoding="utf-8",
    )
    with pytest.raises(ConfigError, match=message) as caught:
        CellRuntime(path)
    assert "cell.yaml" in str(caught.value)


def test_the_inspection_travels_pickled_after_it_ran(runtime: CellRuntime) -> None:
    """``server: process_inspections`` sends the inspection to a worker process pickled with
    every run: what a run leaves behind (the ChArUco detector's board) must not stop that."""
    import pickle

    from vision_server import InspectionInput

    inspection = runtime.catalog.inspections["charuco"]
    first = inspection.run(InspectionInput(_board_image("charuco")), overlay=False)
    copy = pickle.loads(pickle.dumps(inspection))
    again = copy.run(InspectionInput(_board_image("charuco")), overlay=False)
    assert first.data["corners"] == again.data["corners"]
