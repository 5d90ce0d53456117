"""Intrinsics calibration in the simulated cell: the tool camera (with the DMK 31BF03 preset's
barrel distortion) moves through the planned views over the ChArUco board; the corners come
from the server's board detector; the solution is compared with the scene's true intrinsics."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from geometry import invert_transform
from robot_client.commissioning import (
    BoardView,
    CalibrationError,
    board_coverage,
    solve_intrinsics,
)
from robot_client.commissioning.views import plan_tool_views
from simulation import SimCell, load_scene
from simulation.calibration_board import spec_from_opencv
from vision_server.analysis import BoardSpec, detect_board

SCENE = "examples/scenes/intrinsics_cell.yaml"


def _views(seed: int) -> tuple[list[BoardView], object]:
    scene = load_scene(SCENE).with_seed(seed)
    cell = SimCell(scene)
    camera = scene.camera("tool_camera")
    board = scene.calibration_boards[0]
    base_from_board = (
        invert_transform(scene.robot.world_from_base)
        @ board.world_from_board
        @ spec_from_opencv(board)
    )
    spec = BoardSpec("charuco", board.columns, board.rows, board.square_m, board.marker_m)
    views = []
    poses = plan_tool_views(
        base_from_board, camera.pose, board.size_m, fx_px=1400.0, image_width_px=1024
    )
    for i, pose in enumerate(poses):
        cell.robot.move_linear(pose)
        found = detect_board(cell.render("tool_camera").color, spec)
        views.append(BoardView(found.uv, found.object_points, f"view {i}"))
    return views, camera.intrinsics


@pytest.mark.parametrize("seed", range(10))
def test_sim_intrinsics_meet_the_goal(seed: int) -> None:
    views, truth = _views(seed)
    solution = solve_intrinsics(views, (1024, 768))
    k = solution.intrinsics
    assert abs(k.fx / truth.fx - 1) < 0.001  # type: ignore[attr-defined]
    assert abs(k.fy / truth.fy - 1) < 0.001  # type: ignore[attr-defined]
    assert abs(k.cx - truth.cx) < 0.5  # type: ignore[attr-defined]
    assert abs(k.cy - truth.cy) < 0.5  # type: ignore[attr-defined]
    assert solution.rms_px < 0.2
    assert solution.used == len(views)
    assert solution.coverage.complete, solution.coverage.describe()
    assert 0 < solution.std["fx"] < 2.0


def test_a_view_that_moved_is_dropped_with_its_reason() -> None:
    views, truth = _views(11)
    bad = views[3]
    rng = np.random.default_rng(0)
    views[3] = replace(bad, uv=bad.uv + rng.normal(0.0, 2.0, bad.uv.shape))
    solution = solve_intrinsics(views, (1024, 768))
    dropped = [v for v in solution.views if not v.used]
    assert [v.label for v in dropped] == ["view 3"]
    assert dropped[0].reason is not None
    assert "above" in dropped[0].reason
    assert dropped[0].rms_px > 1.0
    assert abs(solution.intrinsics.fx / truth.fx - 1) < 0.001  # type: ignore[attr-defined]


def test_too_few_views_is_a_clear_error() -> None:
    views, _ = _views(12)
    with pytest.raises(CalibrationError, match="at least 4"):
        solve_intrinsics(views[:3], (1024, 768))


def test_coverage_names_what_is_missing() -> None:
    views, truth = _views(13)
    # The frontal view's corners in the middle third of the image only, shown twice.
    u, v = views[0].uv[:, 0], views[0].uv[:, 1]
    middle = (u > 1024 / 3) & (u < 2 * 1024 / 3) & (v > 768 / 3) & (v < 2 * 768 / 3)
    centre = replace(views[0], uv=views[0].uv[middle], object_points=views[0].object_points[middle])
    coverage = board_coverage([centre, centre], truth)  # type: ignore[arg-type]
    assert coverage.missing_regions == (
        "top left",
        "top",
        "top right",
        "left",
        "right",
        "bottom left",
        "bottom",
        "bottom right",
    )
    assert coverage.missing_tilts == ("tilted left", "tilted right", "tilted up", "tilted down")
    assert not coverage.complete
    assert "missing: top left" in coverage.describe()
    full = board_coverage(views, truth)  # type: ignore[arg-type]
    assert full.complete, full.describe()
