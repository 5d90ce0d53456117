"""Eye-to-hand calibration in the simulated cell, through a real server on loopback: the
ChArUco board bolted to the flange (examples/scenes/eye_to_hand_cell.yaml, the arm given
0.03 mm / 0.01 deg repeatability) shown to the fixed QC camera, corners from the server's
``calibration_board``, the solved ``base_from_camera`` against the scene's truth. Accuracy, not
timing."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from geometry import invert_transform, rotation_angle
from robot_client import SyncVisionClient
from robot_client.commissioning import solve_hand_eye
from robot_client.commissioning.hand_eye_collect import collect_hand_eye_views
from robot_client.devices.sim import sim_devices
from simulation import SimCell, load_scene

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples" / "scenes" / "eye_to_hand_cell.yaml"
# The fixed camera's images go in the request here (the robot client renders the sim camera);
# the inspection's server camera only names where they come from.
BOARD = """
  - name: board_fixed
    type: calibration_board
    camera: tool
    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}
"""
REPEATABILITY_M = 0.03e-3  # issue 18: the arm's repeatability, 0.03 mm and 0.01 deg
REPEATABILITY_RAD = math.radians(0.01)


@pytest.fixture(scope="module")
def vision(
    tmp_path_factory: pytest.TempPathFactory, cell_config: Any, live_server: Any
) -> Iterator[SyncVisionClient]:
    tmp = tmp_path_factory.mktemp("eye-to-hand-server")
    with (
        live_server(cell_config(tmp, tmp / "world.json", BOARD)) as port,
        SyncVisionClient("127.0.0.1", port, request_timeout_s=30.0) as client,
    ):
        yield client


def eye_to_hand_cell(seed: int) -> SimCell:
    scene = load_scene(SCENE)
    robot = replace(
        scene.robot, repeatability_m=REPEATABILITY_M, repeatability_rad=REPEATABILITY_RAD
    )
    return SimCell(replace(scene, robot=robot), seed=seed)


def true_base_from_camera(cell: SimCell) -> np.ndarray:
    pose: np.ndarray = (
        invert_transform(cell.scene.robot.world_from_base) @ cell.scene.camera("qc_camera").pose
    )
    return pose


def test_base_from_camera_meets_the_goal_in_the_simulated_cell(vision: SyncVisionClient) -> None:
    """Issue 18: p95 <= 0.3 mm and <= 0.05 deg (20 seeds in bench/hand_eye.py; here 2, each
    within the goal), from 15 poses, with the arm's repeatability and the sensor's noise."""
    for seed in range(2):
        cell = eye_to_hand_cell(seed)
        devices = sim_devices(cell, vision=vision)
        start = devices.robot.base_from_tool()
        intrinsics = cell.scene.camera("qc_camera").intrinsics
        collected = collect_hand_eye_views(
            devices, camera="qc_camera", inspection="board_fixed", intrinsics=intrinsics
        )
        assert collected.setup == "eye_to_hand"
        assert collected.skipped == []
        np.testing.assert_allclose(devices.robot.base_from_tool(), start)
        result = solve_hand_eye(collected.views, intrinsics, collected.setup)
        truth = true_base_from_camera(cell)
        translation = float(np.linalg.norm(result.camera[:3, 3] - truth[:3, 3]))
        rotation = math.degrees(rotation_angle(result.camera[:3, :3].T @ truth[:3, :3]))
        print(f"seed {seed}: {translation * 1e3:.3f} mm {rotation:.4f} deg")
        assert translation <= 0.3e-3, (seed, translation)
        assert rotation <= 0.05, (seed, rotation)
        assert result.verdict == "good", result.reasons
        assert len(result.views) == 15
        assert result.loop_translation_m < 1e-3
