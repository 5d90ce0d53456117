"""Collecting hand-eye views: for a camera on the tool (eye-in-hand) the robot moves the camera
through the poses of :func:`~robot_client.commissioning.hand_eye.plan_views` around a board it
sees from where it starts; for a fixed camera (eye-to-hand) the robot holds the board (bolted to
its flange) and shows it to the camera at the poses of
:func:`~robot_client.commissioning.hand_eye.plan_fixed_views`. At each pose the server's
``calibration_board`` inspection finds the corners; each view keeps the pose the robot reports
there. Poses where the board would be mostly outside the image (predicted from the first view
and the camera's nominal mount) are skipped with the reason, as are unreachable ones.

Frames: OpenCV's board frame (origin at the squares' top-left corner, x right, y down the
print, z into it) for the corners; the robot's active base frame for the tool poses; metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, invert_transform, make_transform

from ..devices import Devices
from .collect import BoardResult, board_result, move_to_view
from .hand_eye import MIN_CORNERS, HandEyeView, Setup, plan_fixed_views, plan_views

__all__ = ["HandEyeCollected", "collect_hand_eye_views"]

FloatArray = NDArray[np.float64]
ProgressFn = Callable[[str, float], None]


@dataclass
class HandEyeCollected:
    """The views taken (with their labels), the views not taken (label, why), the board and
    the setup (``eye_in_hand`` for a tool camera, ``eye_to_hand`` for a fixed one)."""

    setup: Setup = "eye_in_hand"
    views: list[HandEyeView] = field(default_factory=list)
    labels: list[str] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    board: str = ""


def _camera_from_board(seen: BoardResult, intrinsics: CameraIntrinsics) -> FloatArray:
    assert seen.view is not None
    ok, rvec, tvec = cv2.solvePnP(
        seen.view.object_points, seen.view.uv, intrinsics.matrix, np.asarray(intrinsics.dist)
    )
    if not ok:
        raise ValueError("the board's pose could not be solved from the first view")
    return make_transform(cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3))


def _facing_centre(board_size_m: tuple[float, float]) -> FloatArray:
    """``board_from_centre``: the board's centre with z out of the print (towards a camera
    that sees it), the frame :func:`plan_views` aims at."""
    width, height = board_size_m
    return np.array(
        [
            [1.0, 0.0, 0.0, width / 2],
            [0.0, -1.0, 0.0, height / 2],
            [0.0, 0.0, -1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


MIN_VISIBLE = 0.5
"""A planned pose is skipped when less than this fraction of the board's area (sampled on a
grid) is predicted inside the image: the corners found would not fix the board's pose."""


def _visible_fraction(
    camera_from_board: FloatArray, board_size_m: tuple[float, float], intrinsics: CameraIntrinsics
) -> float:
    """The fraction of a 9 x 9 grid over the board's squares (OpenCV board frame) that lands
    inside the image in front of the camera at ``camera_from_board``."""
    width, height = board_size_m
    u, v = np.meshgrid(np.linspace(0.0, width, 9), np.linspace(0.0, height, 9))
    grid = np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])
    p = grid @ camera_from_board[:3, :3].T + camera_from_board[:3, 3]
    front = p[:, 2] > 0.05
    if not np.any(front):
        return 0.0
    uv = intrinsics.project(p[front])
    inside = (
        (uv[:, 0] >= 0)
        & (uv[:, 0] <= intrinsics.width - 1)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= intrinsics.height - 1)
    )
    return float(np.count_nonzero(inside)) / len(grid)


STILL_PX = 2.0
"""Below this median shift of the corners between the start and the first pose the board did
not move with the tool (each planned pose moves it by tens of pixels)."""


def _check_board_moves(start: BoardResult, first: BoardResult, camera: str) -> None:
    """Raise ``ValueError`` when the board ``camera`` sees stood still while the tool moved:
    a board in the cell, not on the flange, which eye-to-hand cannot use."""
    assert start.view is not None
    assert first.view is not None
    before = {tuple(p): uv for p, uv in zip(start.view.object_points, start.view.uv, strict=True)}
    shifts = [
        float(np.linalg.norm(uv - before[tuple(p)]))
        for p, uv in zip(first.view.object_points, first.view.uv, strict=True)
        if tuple(p) in before
    ]
    if shifts and float(np.median(shifts)) < STILL_PX:
        raise ValueError(
            f"the board camera {camera!r} sees did not move with the tool (corners "
            f"{float(np.median(shifts)):.1f} px from where they were): eye-to-hand needs the "
            "board bolted to the flange"
        )


def collect_hand_eye_views(
    devices: Devices,
    *,
    camera: str,
    inspection: str,
    intrinsics: CameraIntrinsics,
    count: int = 15,
    fill: float = 0.8,
    progress: ProgressFn | None = None,
) -> HandEyeCollected:
    """Views for a hand-eye calibration of ``camera`` (a camera of ``devices``): eye-in-hand
    when it is on the tool (its ``tool_from_camera`` serves as the rough guess the plan
    needs), eye-to-hand when it is fixed (its nominal ``base_from_camera``, as its captures
    report it, is the guess; the board is on the tool).

    The robot must start where the camera sees the board; that view (with ``intrinsics``)
    places the board. ``count`` poses are planned at the distance where the board spans
    ``fill`` of the image width; poses out of the workspace, unreachable or with the board
    predicted mostly out of the image are skipped with the reason, as are views where the
    board is not found. The robot goes back to its start pose at the end. Raises
    ``ValueError`` when the camera does not see the board at the start.
    """
    device = devices.camera(camera)
    guess = device.tool_from_camera
    setup: Setup = "eye_in_hand" if guess is not None else "eye_to_hand"
    if devices.vision is None:
        raise ValueError("no vision server to run the calibration_board inspection on")
    start_pose = devices.robot.base_from_tool()
    first = device.capture()
    seen = board_result(devices.vision.inspect(inspection, first.color).data, "start")
    if seen.view is None or seen.board_size_m is None:
        where = (
            "move the robot so that the camera sees the board from about half a metre"
            if setup == "eye_in_hand"
            else "move the robot so that the board on its tool faces the camera, about half "
            "a metre from it"
        )
        raise ValueError(
            f"the board is not in view of camera {camera!r} at the start ({seen.reason}): " + where
        )
    camera_from_board = _camera_from_board(seen, intrinsics)
    distance_m = intrinsics.fx * seen.board_size_m[0] / (fill * intrinsics.width)
    spread: dict[str, Any] = {
        "count": count,
        "distance_m": distance_m,
        # Nearer than this the board overflows the image; farther, the corners shrink.
        "depth_spread": 0.15,
        "tilt_rad": math.radians(35.0),
    }
    centre = _facing_centre(seen.board_size_m)
    if guess is not None:
        base_from_board = start_pose @ guess @ camera_from_board
        poses = plan_views(base_from_board @ centre, guess, **spread)
        predicted = [invert_transform(pose @ guess) @ base_from_board for pose in poses]
    else:
        base_from_camera = first.base_from_camera
        tool_from_board = invert_transform(start_pose) @ base_from_camera @ camera_from_board
        poses = plan_fixed_views(base_from_camera, tool_from_board @ centre, **spread)
        predicted = [invert_transform(base_from_camera) @ pose @ tool_from_board for pose in poses]
    collected = HandEyeCollected(setup=setup, board=seen.board)
    try:
        for i, (pose, camera_from_planned) in enumerate(zip(poses, predicted, strict=True)):
            label = f"pose {i + 1}"
            if progress is not None:
                progress(f"{label} of {len(poses)}", i / len(poses))
            visible = _visible_fraction(camera_from_planned, seen.board_size_m, intrinsics)
            if visible < MIN_VISIBLE:
                why = (
                    f"the board would be mostly out of the image ({visible:.0%} of it inside, "
                    f"at least {MIN_VISIBLE:.0%} needed)"
                )
                collected.skipped.append((label, why))
                continue
            refused = move_to_view(devices, pose)
            if refused is not None:
                collected.skipped.append((label, refused))
                continue
            reported = devices.robot.base_from_tool()
            found = board_result(
                devices.vision.inspect(inspection, device.capture().color).data, label
            )
            if found.view is None:
                collected.skipped.append((label, found.reason or "board not found"))
                continue
            if len(found.view.uv) < MIN_CORNERS:
                why = f"{len(found.view.uv)} corners found, fewer than {MIN_CORNERS}"
                collected.skipped.append((label, why))
                continue
            if setup == "eye_to_hand" and not collected.views:
                _check_board_moves(seen, found, camera)
            collected.views.append(HandEyeView(reported, found.view.uv, found.view.object_points))
            collected.labels.append(label)
    finally:
        devices.robot.move_linear(start_pose)
    if progress is not None:
        progress(f"{len(collected.views)} views", 1.0)
    return collected
