"""The demo's first step: the cell arrives uncommissioned and commissions its tool camera.

Before commissioning the robot program knows the tool camera only from paper: the lens's data
sheet (fx = fy = 1350 px, no distortion; the truth is 1400 px with barrel distortion) and the
mount's drawing (4 mm and 0.6 degrees off the true ``tool_from_camera``). A ChArUco board
stands in the cell (on a stand beside table L2, out of every other view); the robot moves its
tool camera over it, calibrates the intrinsics, then the hand-eye with them (both through the
server's ``calibration_board`` inspection), and stores the result in a copy of the taught
records, which the task then runs with. Metres, radians, pixels.
"""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from geometry import (
    CameraIntrinsics,
    invert_transform,
    make_transform,
    rotation_angle,
    rotation_from_rpy,
    transform_from_xyz_rpy,
)
from simulation import SimCell
from simulation.calibration_board import CalibrationBoardSpec
from simulation.scene import Scene

from ..commissioning import HandEyeResult, solve_hand_eye, solve_intrinsics
from ..commissioning.collect import collect_tool_views
from ..commissioning.hand_eye_collect import collect_hand_eye_views
from ..devices import Devices
from ..devices.sim import SimCamera
from ..skills.camera_mounts import hand_eye_record
from ..teach_store import TeachStore

__all__ = [
    "APPROXIMATE",
    "BOARD_INSPECTION",
    "NOMINAL_MOUNT",
    "Commissioned",
    "commission_tool_camera",
    "uncommissioned_camera",
    "with_board",
]

FloatArray = NDArray[np.float64]
CAMERA = "tool_camera"
APPROXIMATE = CameraIntrinsics(1024, 768, 1350.0, 1350.0, 512.0, 384.0)
NOMINAL_MOUNT = make_transform(rotation_from_rpy(0.01, 0.0, 0.0), [0.074, 0.0, -0.1])
BOARD = CalibrationBoardSpec(
    "commissioning_board",
    "charuco",
    11,
    8,
    0.03,
    0.015,
    transform_from_xyz_rpy([0.7, 0.7, 0.5], [0.0, 0.0, 0.0]),  # face up, on a 0.5 m stand
)
BOARD_INSPECTION: dict[str, Any] = {
    "name": "board_tool",
    "type": "calibration_board",
    "camera": "tool",
    "board": {"kind": "charuco", "columns": 11, "rows": 8, "square_m": 0.03, "marker_m": 0.0225},
}
VIEW_DISTANCE_M = 0.5  # the camera above the board where the robot starts


def with_board(scene: Scene) -> Scene:
    """``scene`` with the commissioning board standing in it."""
    return replace(scene, calibration_boards=(*scene.calibration_boards, BOARD))


def uncommissioned_camera(cell: SimCell) -> SimCamera:
    """The tool camera as the robot program knows it before commissioning."""
    return SimCamera(cell, CAMERA, nominal_mount=NOMINAL_MOUNT, nominal_intrinsics=APPROXIMATE)


@dataclass(frozen=True)
class Commissioned:
    """What commissioning measured, and its errors against the simulation's truth."""

    intrinsics: CameraIntrinsics
    hand_eye: HandEyeResult
    fx_error: float
    """Relative error of fx (dimensionless)."""
    mount_error_m: float
    mount_error_rad: float
    store: TeachStore


def _start_pose(cell: SimCell) -> FloatArray:
    """The tool pose (base frame, as the robot knows its mount) with the camera looking down
    at the board's centre from :data:`VIEW_DISTANCE_M`, by the nominal mount."""
    camera = make_transform(
        rotation_from_rpy(math.pi, 0.0, 0.0),
        BOARD.world_from_board[:3, 3] + [0.0, 0.0, VIEW_DISTANCE_M],
    )
    world_from_tool = camera @ invert_transform(NOMINAL_MOUNT)
    result: FloatArray = invert_transform(cell.scene.robot.world_from_base) @ world_from_tool
    return result


def commission_tool_camera(
    devices: Devices, cell: SimCell, taught: TeachStore, store_path: Path
) -> Commissioned:
    """Intrinsics, then hand-eye, of the tool camera (``devices`` must hold the
    :func:`uncommissioned_camera`); the taught records copied to ``store_path`` with the
    ``hand_eye/tool_camera`` record added. Raises ``ValueError`` when a step cannot give a
    trustworthy result (incomplete coverage, a ``redo`` verdict)."""
    devices.robot.move_linear(_start_pose(cell))
    views = collect_tool_views(devices, camera=CAMERA, inspection=BOARD_INSPECTION["name"])
    if views.image_size is None:
        raise ValueError("commissioning: the board was found in no view")
    solution = solve_intrinsics(views.views, views.image_size)
    if not solution.coverage.complete:
        raise ValueError(f"commissioning: intrinsics coverage {solution.coverage.describe()}")
    intrinsics = solution.intrinsics
    collected = collect_hand_eye_views(
        devices, camera=CAMERA, inspection=BOARD_INSPECTION["name"], intrinsics=intrinsics
    )
    result = solve_hand_eye(collected.views, intrinsics)
    if result.verdict == "redo":
        raise ValueError("commissioning: hand-eye verdict redo: " + "; ".join(result.reasons))
    shutil.copyfile(taught.path, store_path)  # the taught records as they are, revisions too
    store = TeachStore(store_path)
    store.put(
        hand_eye_record(
            CAMERA,
            "eye_in_hand",
            result.camera,
            intrinsics=intrinsics,
            verdict=result.verdict,
            reasons=result.reasons,
            figures={"rms_px": round(result.rms_px, 4)},
        )
    )
    truth = cell.scene.camera(CAMERA)
    return Commissioned(
        intrinsics,
        result,
        intrinsics.fx / truth.intrinsics.fx - 1.0,
        float(np.linalg.norm(result.camera[:3, 3] - truth.pose[:3, 3])),
        rotation_angle(result.camera[:3, :3].T @ truth.pose[:3, :3]),
        store,
    )
