"""The simulated calibration board: drawn where the camera model puts it, also in part."""

from __future__ import annotations

import numpy as np

from geometry import invert_transform, transform_points
from robot_client.commissioning.views import plan_tool_views
from simulation import SimCell, load_scene
from simulation.calibration_board import spec_from_opencv
from vision_server.analysis import BoardSpec, detect_board

SCENE = "examples/scenes/intrinsics_cell.yaml"


def _corner_errors(pose_index: int, *, fill: float | None = None) -> tuple[int, float]:
    scene = load_scene(SCENE)
    cell = SimCell(scene)
    camera, board = scene.camera("tool_camera"), scene.calibration_boards[0]
    base_from_board = (
        invert_transform(scene.robot.world_from_base)
        @ board.world_from_board
        @ spec_from_opencv(board)
    )
    poses = plan_tool_views(
        base_from_board, camera.pose, board.size_m, fx_px=1400.0, image_width_px=1024
    )
    pose = poses[pose_index].copy()
    if fill is not None:  # closer to the board: it no longer fits in the image
        pose[:3, 3] += pose[:3, 2] * fill
    cell.robot.move_linear(pose)
    spec = BoardSpec("charuco", board.columns, board.rows, board.square_m, board.marker_m)
    found = detect_board(cell.render("tool_camera").color, spec)
    camera_from_board = (
        invert_transform(cell.world_from_camera("tool_camera"))
        @ board.world_from_board
        @ spec_from_opencv(board)
    )
    truth = camera.intrinsics.project(transform_points(camera_from_board, found.object_points))
    error = np.sqrt(np.mean(np.sum((found.uv - truth) ** 2, axis=1)))
    return len(found.ids), float(error)


def test_board_corners_sit_where_the_camera_model_puts_them() -> None:
    # With the board large in the image an edge must not be quantised by too few samples.
    count, error = _corner_errors(0)
    assert count == 70
    assert error < 0.15


def test_a_board_seen_in_part_is_drawn_in_part() -> None:
    # The camera 0.2 m closer: the board reaches past the image; the squares in view are drawn.
    count, error = _corner_errors(0, fill=0.2)
    assert 6 <= count < 70
    assert error < 0.3
