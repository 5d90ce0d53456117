"""Collecting hand-eye views of a camera on the tool: the robot moves through the poses of
:func:`~robot_client.commissioning.hand_eye.plan_views` around a board it sees from where it
starts, and at each the server's ``calibration_board`` inspection finds the corners; each view
keeps the pose the robot reports there.

Frames: OpenCV's board frame (origin at the squares' top-left corner, x right, y down the
print, z into it) for the corners; the robot's active base frame for the tool poses; metres.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics, make_transform

from ..devices import Devices
from .collect import BoardResult, board_result, move_to_view
from .hand_eye import MIN_CORNERS, HandEyeView, plan_views

__all__ = ["HandEyeCollected", "collect_hand_eye_views"]

FloatArray = NDArray[np.float64]
ProgressFn = Callable[[str, float], None]


@dataclass
class HandEyeCollected:
    """The views taken (with their labels), the views not taken (label, why) and the board."""

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
    """Views for an eye-in-hand calibration of ``camera`` (a camera of ``devices`` on the
    tool, whose ``tool_from_camera`` serves as the rough guess the plan needs).

    The robot must start where the camera sees the board; that view (with ``intrinsics``)
    places the board. ``count`` poses are planned at the distance where the board spans
    ``fill`` of the image width; poses out of the workspace or unreachable are skipped with
    the reason, as are views where the board is not found. The robot goes back to its start
    pose at the end. Raises ``ValueError`` when the camera is not on the tool or does not see
    the board at the start.
    """
    device = devices.camera(camera)
    guess = device.tool_from_camera
    if guess is None:
        raise ValueError(
            f"camera {camera!r} is not on the tool: eye-to-hand needs the board held by the "
            "tool, which this command does not do yet"
        )
    if devices.vision is None:
        raise ValueError("no vision server to run the calibration_board inspection on")
    start_pose = devices.robot.base_from_tool()
    seen = board_result(devices.vision.inspect(inspection, device.capture().color).data, "start")
    if seen.view is None or seen.board_size_m is None:
        raise ValueError(
            f"the board is not in view of camera {camera!r} at the start ({seen.reason}): "
            "move the robot so that the camera sees the board from about half a metre"
        )
    base_from_board = start_pose @ guess @ _camera_from_board(seen, intrinsics)
    distance_m = intrinsics.fx * seen.board_size_m[0] / (fill * intrinsics.width)
    poses = plan_views(
        base_from_board @ _facing_centre(seen.board_size_m),
        guess,
        count=count,
        distance_m=distance_m,
        # Nearer than this the board overflows the image; farther, the corners shrink.
        depth_spread=0.15,
        tilt_rad=math.radians(35.0),
    )
    collected = HandEyeCollected(board=seen.board)
    try:
        for i, pose in enumerate(poses):
            label = f"pose {i + 1}"
            if progress is not None:
                progress(f"{label} of {len(poses)}", i / len(poses))
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
            collected.views.append(HandEyeView(reported, found.view.uv, found.view.object_points))
            collected.labels.append(label)
    finally:
        devices.robot.move_linear(start_pose)
    if progress is not None:
        progress(f"{len(collected.views)} views", 1.0)
    return collected
