"""Hand-eye calibration against known truth: synthetic views of a board (corners projected
with the camera's distortion, pixel noise, and the robot's repeatability as noise on the poses
it reports), fixed seeds. Accuracy, not timing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from geometry import CameraIntrinsics, invert_transform, make_transform, rotation_angle
from geometry.transforms import rotation_from_axis_angle, rotation_from_rpy
from robot_client.commissioning.hand_eye import (
    HandEyeError,
    HandEyeView,
    plan_views,
    solve_hand_eye,
)

INTRINSICS = CameraIntrinsics(1024, 768, 900.0, 902.0, 515.0, 381.0, (-0.08, 0.05, 0.0, 0.0, 0.0))
TOOL_FROM_CAMERA = make_transform(rotation_from_rpy(0.02, -0.03, 1.57), [0.052, -0.011, 0.085])
BASE_FROM_BOARD = make_transform(rotation_from_rpy(0.0, 0.0, 0.4), [0.55, 0.12, 0.02])
BASE_FROM_CAMERA = make_transform(rotation_from_rpy(math.pi - 0.2, 0.1, 0.3), [0.5, -0.3, 0.9])
TOOL_FROM_BOARD = make_transform(rotation_from_rpy(math.pi, 0.0, 0.1), [0.0, 0.01, 0.07])
CORNERS = np.array(
    [[0.03 * i - 0.12, 0.03 * j - 0.075, 0.0] for j in range(6) for i in range(9)], np.float64
)
ROBOT_NOISE_M = 0.03e-3
ROBOT_NOISE_RAD = math.radians(0.01)
PIXEL_NOISE = 0.1


def jitter(pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The pose the robot reports: the true one off by its repeatability."""
    axis = rng.normal(size=3)
    turn = rotation_from_axis_angle(axis, rng.normal(0.0, ROBOT_NOISE_RAD))
    out = pose.copy()
    out[:3, :3] = turn @ pose[:3, :3]
    out[:3, 3] += rng.normal(0.0, ROBOT_NOISE_M, 3)
    return out


def observe(
    base_from_tool: np.ndarray, camera_from_board: np.ndarray, rng: np.random.Generator
) -> HandEyeView:
    """The view a detector gives: the corners inside the image, with pixel noise, and the
    pose the robot reports."""
    p = CORNERS @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
    uv = INTRINSICS.project(p) + rng.normal(0.0, PIXEL_NOISE, (len(CORNERS), 2))
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 1024) & (uv[:, 1] >= 0) & (uv[:, 1] < 768)
    return HandEyeView(jitter(base_from_tool, rng), uv[inside], CORNERS[inside])


def eye_in_hand_views(seed: int, count: int = 15) -> list[HandEyeView]:
    rng = np.random.default_rng(seed)
    views = []
    for base_from_tool in plan_views(BASE_FROM_BOARD, TOOL_FROM_CAMERA, count=count):
        camera_from_board = invert_transform(base_from_tool @ TOOL_FROM_CAMERA) @ BASE_FROM_BOARD
        views.append(observe(base_from_tool, camera_from_board, rng))
    return views


def errors(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (
        float(np.linalg.norm(found[:3, 3] - truth[:3, 3])),
        math.degrees(rotation_angle(found[:3, :3].T @ truth[:3, :3])),
    )


def test_eye_in_hand_meets_the_goal_over_20_seeds() -> None:
    """Issue 18: tool_from_camera p95 <= 0.3 mm and <= 0.05 deg from <= 15 poses, with robot
    repeatability 0.03 mm / 0.01 deg."""
    found = [solve_hand_eye(eye_in_hand_views(seed), INTRINSICS) for seed in range(20)]
    translation = [errors(r.camera, TOOL_FROM_CAMERA)[0] for r in found]
    rotation = [errors(r.camera, TOOL_FROM_CAMERA)[1] for r in found]
    assert np.percentile(translation, 95) <= 0.3e-3, translation
    assert np.percentile(rotation, 95) <= 0.05, rotation
    assert all(r.verdict == "good" for r in found), [r.reasons for r in found]
    assert all(r.rms_px < 0.4 for r in found)  # 0.1 px per axis and the robot's noise
    # The reported uncertainty is of the size of the errors seen (not 0, not far off).
    sigma = np.median([r.sigma_translation_m for r in found])
    assert 0.1 * np.median(translation) < sigma < 10.0 * np.percentile(translation, 95)


def test_eye_to_hand_finds_the_fixed_camera() -> None:
    rng = np.random.default_rng(5)
    views = []
    for k in range(15):
        tilt = rotation_from_rpy(
            0.35 * math.sin(k), 0.35 * math.cos(1.7 * k), 0.6 * math.sin(0.9 * k)
        )
        # The board (on the tool) in front of the camera, 0.45 m away, turned a little.
        camera_from_board = make_transform(
            tilt, [0.05 * math.sin(2.1 * k), 0.04 * math.cos(1.3 * k), 0.45]
        )
        base_from_tool = BASE_FROM_CAMERA @ camera_from_board @ invert_transform(TOOL_FROM_BOARD)
        views.append(observe(base_from_tool, camera_from_board, rng))
    result = solve_hand_eye(views, INTRINSICS, "eye_to_hand")
    t, r = errors(result.camera, BASE_FROM_CAMERA)
    assert t < 0.3e-3
    assert r < 0.05
    t_board, _ = errors(result.board, TOOL_FROM_BOARD)
    assert t_board < 0.3e-3
    assert result.verdict == "good"


def test_a_view_taken_at_another_pose_is_named() -> None:
    views = eye_in_hand_views(3)
    moved = views[6].base_from_tool.copy()
    moved[:3, 3] += [0.004, 0.0, 0.0]  # the robot reported a pose 4 mm from where it was
    views[6] = HandEyeView(moved, views[6].corners_uv, views[6].corners_board)
    result = solve_hand_eye(views, INTRINSICS)
    assert result.verdict in ("check", "redo")
    assert "6 (" in " ".join(result.reasons) or result.verdict == "redo", result.reasons
    worst = max(result.views, key=lambda v: v.translation_m)
    assert worst.index == 6


def test_a_pose_a_millimetre_off_is_named() -> None:
    views = eye_in_hand_views(5)
    moved = views[9].base_from_tool.copy()
    moved[:3, 3] += [0.0, 0.001, 0.0]
    views[9] = HandEyeView(moved, views[9].corners_uv, views[9].corners_board)
    result = solve_hand_eye(views, INTRINSICS)
    assert result.verdict == "check"
    assert "views 9 (" in result.reasons[0], result.reasons


def test_poses_that_turn_about_one_axis_only_are_refused_with_the_reason() -> None:
    rng = np.random.default_rng(1)
    views = []
    for k in range(10):
        turn = make_transform(rotation_from_axis_angle([0, 0, 1], 0.3 * k), [0, 0, 0])
        base_from_tool = (
            BASE_FROM_BOARD
            @ turn
            @ make_transform(np.diag([1.0, -1.0, -1.0]), [0.01 * k, 0.0, 0.4])
            @ invert_transform(TOOL_FROM_CAMERA)
        )
        camera_from_board = invert_transform(base_from_tool @ TOOL_FROM_CAMERA) @ BASE_FROM_BOARD
        views.append(observe(base_from_tool, camera_from_board, rng))
    result = solve_hand_eye(views, INTRINSICS)
    assert result.verdict == "redo"
    assert "one axis" in result.reasons[0]


def test_too_few_views_is_an_error_naming_the_count() -> None:
    with pytest.raises(HandEyeError, match="2 view"):
        solve_hand_eye(eye_in_hand_views(0, count=2), INTRINSICS)


def test_intrinsics_a_little_off_are_not_called_good() -> None:
    """Integrator finding 1: with fx and fy 1.4 % off the reprojection RMS stays below 1 px
    while the mount is millimetres off; the AX=XB loop against what the noise explains shows
    it, and the verdict names the likely causes. The same views with the true intrinsics are
    good (their loop is what noise explains)."""
    views = eye_in_hand_views(1)
    right = solve_hand_eye(views, INTRINSICS)
    assert right.verdict == "good", right.reasons
    assert right.loop_translation_m < 2.0 * right.expected.loop_translation_m
    scaled = CameraIntrinsics(
        1024, 768, 900.0 * 0.986, 902.0 * 0.986, 515.0, 381.0, INTRINSICS.dist
    )
    wrong = solve_hand_eye(views, scaled)
    assert errors(wrong.camera, TOOL_FROM_CAMERA)[0] > 3e-3  # the case is real: 4 mm off
    assert wrong.rms_px < 1.0  # and the old rule (RMS > 1 px) let it through
    assert wrong.verdict in ("check", "redo")
    reason = " ".join(wrong.reasons)
    assert "intrinsics" in reason
    assert "robot's poses" in reason
    assert "AX=XB loop" in reason
