"""Collecting views of a calibration board through the server's ``calibration_board``
inspection: the robot moves a tool camera through planned poses, or the operator shows the
board to a fixed camera while the coverage says what is still missing.

Both work on :class:`~robot_client.devices.Devices` (blocking calls) and report progress
through a callback ``(message, fraction)``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics

from ..devices import DeviceError, Devices, Unreachable
from .board_view import BoardView
from .coverage import Coverage, board_coverage
from .views import plan_tool_views

__all__ = [
    "BoardResult",
    "Collected",
    "board_result",
    "collect_fixed_views",
    "collect_tool_views",
    "move_to_view",
]

FloatArray = NDArray[np.float64]


def move_to_view(devices: Devices, pose: FloatArray) -> str | None:
    """Move the tool to ``pose`` (``base_from_tool``) for a view; None when it got there,
    else why the view is skipped (outside the workspace, unreachable)."""
    if not devices.robot.in_workspace(pose[:3, 3]):
        return "the pose lies outside the robot's workspace"
    try:
        devices.robot.move_linear(pose)
    except Unreachable as exc:
        return f"unreachable: {exc}"
    return None


ProgressFn = Callable[[str, float], None]


@dataclass(frozen=True)
class BoardResult:
    """One ``calibration_board`` result: the view (None when the board was not found, with
    the server's ``reason``), the image size and the board's size (width, height of its
    squares' area, metres)."""

    view: BoardView | None
    image_size: tuple[int, int] | None
    board_size_m: tuple[float, float] | None
    reason: str | None
    board: str = ""
    """The board for people, e.g. ``charuco 11x8, 30 mm squares``."""


@dataclass
class Collected:
    """Views collected, the image size, and the views that could not be taken (label, why)."""

    views: list[BoardView] = field(default_factory=list)
    image_size: tuple[int, int] | None = None
    skipped: list[tuple[str, str]] = field(default_factory=list)
    board: str = ""


def board_result(data: Mapping[str, Any], label: str) -> BoardResult:
    """A ``calibration_board`` RESULT's ``data`` (SPEC §6.3) as a :class:`BoardResult`."""
    if not data.get("found"):
        return BoardResult(None, None, None, str(data.get("reason") or "board not found"))
    uv = np.asarray(data["corners"], dtype=np.float64).reshape(-1, 2)
    points = np.asarray(data["object_points"], dtype=np.float64).reshape(-1, 3)
    width, height = (int(n) for n in data["image_size"])
    columns, rows = (int(n) for n in data["squares"])
    square = float(data["square_m"])
    return BoardResult(
        BoardView(uv, points, label),
        (width, height),
        (columns * square, rows * square),
        None,
        f"{data.get('board', 'board')} {columns}x{rows}, {square * 1000:g} mm squares",
    )


def _inspect(devices: Devices, inspection: str, image: Any, label: str) -> BoardResult:
    if devices.vision is None:
        raise DeviceError("no vision server to run the calibration_board inspection on")
    result = devices.vision.inspect(inspection, image)
    return board_result(result.data, label)


def collect_tool_views(
    devices: Devices,
    *,
    camera: str,
    inspection: str,
    nominal: CameraIntrinsics | None = None,
    tilt_deg: float = 30.0,
    progress: ProgressFn | None = None,
) -> Collected:
    """Views of the board from a camera on the tool, at the poses of
    :func:`~robot_client.commissioning.views.plan_tool_views` around where the robot is.

    The robot must start where the camera sees the board (whole or in part): that first
    view, solved with ``nominal`` intrinsics (default: the camera's own), places the board.
    Poses out of the workspace or unreachable are skipped with the reason; the robot goes
    back to its start pose at the end. Raises ``ValueError`` when the camera is not on the
    tool or the board is not in the first view.
    """
    device = devices.camera(camera)
    tool_from_camera = device.tool_from_camera
    if tool_from_camera is None:
        raise ValueError(f"camera {camera!r} is not on the tool: calibrate it with --fixed")
    intrinsics = nominal or device.intrinsics
    start_pose = devices.robot.base_from_tool()
    first = device.capture()
    seen = _inspect(devices, inspection, first.color, "start")
    if seen.view is None or seen.board_size_m is None:
        raise ValueError(
            f"the board is not in view of camera {camera!r} at the start ({seen.reason}): "
            "move the robot so that the camera sees the board from about half a metre"
        )
    ok, rvec, tvec = cv2.solvePnP(
        seen.view.object_points, seen.view.uv, intrinsics.matrix, np.asarray(intrinsics.dist)
    )
    if not ok:
        raise ValueError("the board's pose could not be solved from the first view")
    camera_from_board = np.eye(4)
    camera_from_board[:3, :3] = cv2.Rodrigues(rvec)[0]
    camera_from_board[:3, 3] = np.asarray(tvec).reshape(3)
    base_from_board = first.base_from_camera @ camera_from_board
    poses = plan_tool_views(
        base_from_board,
        tool_from_camera,
        seen.board_size_m,
        fx_px=intrinsics.fx,
        image_width_px=intrinsics.width,
        tilt_deg=tilt_deg,
    )
    collected = Collected(image_size=seen.image_size, board=seen.board)
    try:
        for i, pose in enumerate(poses):
            label = f"view {i + 1}"
            if progress is not None:
                progress(f"{label} of {len(poses)}", i / len(poses))
            refused = move_to_view(devices, pose)
            if refused is not None:
                collected.skipped.append((label, refused))
                continue
            found = _inspect(devices, inspection, device.capture().color, label)
            if found.view is None:
                collected.skipped.append((label, found.reason or "board not found"))
                continue
            collected.views.append(found.view)
    finally:
        devices.robot.move_linear(start_pose)
    if progress is not None:
        progress(f"{len(collected.views)} views", 1.0)
    return collected


def collect_fixed_views(
    devices: Devices,
    *,
    inspection: str,
    count: int,
    next_view: Callable[[int, Coverage | None], bool],
    focal_px: float | None = None,
) -> Collected:
    """Views of the board from a fixed server camera (the inspection's camera, captured by
    the server). Before each of up to ``count`` views ``next_view(index, coverage)`` is asked
    (the operator moves the board and confirms; False ends the collection); ``coverage`` is
    that of the views so far (None before the first), the tilts judged with a pinhole of
    ``focal_px`` (default: 1.2 times the image width, a normal lens) centred in the image."""
    collected = Collected()
    coverage: Coverage | None = None
    for i in range(count):
        if not next_view(i, coverage):
            break
        label = f"view {i + 1}"
        found = _inspect(devices, inspection, None, label)
        if found.view is None or found.image_size is None:
            collected.skipped.append((label, found.reason or "board not found"))
            continue
        collected.views.append(found.view)
        collected.image_size, collected.board = found.image_size, found.board
        width, height = found.image_size
        f = focal_px or 1.2 * width
        nominal = CameraIntrinsics(width, height, f, f, (width - 1) / 2, (height - 1) / 2)
        coverage = board_coverage(collected.views, nominal)
    return collected
