"""Hand-eye calibration in the simulated cell, through a real server on loopback: the tool
camera's views of the ChArUco board (examples/scenes/intrinsics_cell.yaml, its arm given
0.03 mm / 0.01 deg repeatability), corners from the server's ``calibration_board``, the solved
``tool_from_camera`` against the scene's truth; then the whole chain: vision pick in the
Grundfos cell with the calibrated hand-eye and intrinsics from the teach store, while the
camera's own description is deliberately wrong. Accuracy, not timing."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from geometry import (
    CameraIntrinsics,
    invert_transform,
    make_transform,
    rotation_angle,
    rotation_from_rpy,
    transform_from_xyz_rpy,
    transform_points,
)
from robot_client import SyncVisionClient
from robot_client.commissioning import HandEyeResult, solve_hand_eye, solve_intrinsics
from robot_client.commissioning.collect import collect_tool_views
from robot_client.commissioning.hand_eye_collect import collect_hand_eye_views
from robot_client.devices.sim import SimCamera, sim_devices
from robot_client.skills import FailureReason, SkillContext, default_registry, execute
from robot_client.skills.camera_mounts import CalibratedCamera, hand_eye_record
from robot_client.teach_store import TeachStore
from simulation import SimCell, load_scene

ROOT = Path(__file__).resolve().parents[2]
COMMISSIONING = ROOT / "examples" / "scenes" / "intrinsics_cell.yaml"
PICK_SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
BOARD = """
  - name: board_tool
    type: calibration_board
    camera: tool
    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}
"""
# What the cell is told before commissioning: the lens's data sheet and the drawing's mount,
# 4 mm and 0.6 deg off (the truth: fx = fy = 1400 px, tool_from_camera xyz (0.07, 0, -0.1)).
APPROXIMATE = CameraIntrinsics(1024, 768, 1350.0, 1350.0, 512.0, 384.0)
NOMINAL_MOUNT = make_transform(rotation_from_rpy(0.01, 0.0, 0.0), [0.074, 0.0, -0.1])
DOWN = [np.pi, 0.0, 0.0]
L1 = {  # the conveyor search line of the example cell (base frame)
    "p_cam_start": transform_from_xyz_rpy([0.05, -0.55, 0.275], DOWN),
    "p_cam_end": transform_from_xyz_rpy([0.55, -0.55, 0.275], DOWN),
    "h_detect": 0.025,
    "h_grasp": 0.0125,
    "step_m": 0.1,
}
CAPS = ["cap_1", "cap_2", "cap_3"]
REPEATABILITY_M = 0.03e-3  # issue 18: the arm's repeatability, 0.03 mm and 0.01 deg
REPEATABILITY_RAD = math.radians(0.01)


@pytest.fixture(scope="module")
def vision(
    tmp_path_factory: pytest.TempPathFactory, cell_config: Any, live_server: Any
) -> Iterator[SyncVisionClient]:
    tmp = tmp_path_factory.mktemp("hand-eye-server")
    with (
        live_server(cell_config(tmp, tmp / "world.json", BOARD)) as port,
        SyncVisionClient("127.0.0.1", port, request_timeout_s=30.0) as client,
    ):
        yield client


def commissioning_cell(seed: int) -> SimCell:
    """The commissioning cell, its arm off by the repeatability of a real one."""
    scene = load_scene(COMMISSIONING)
    robot = replace(
        scene.robot, repeatability_m=REPEATABILITY_M, repeatability_rad=REPEATABILITY_RAD
    )
    return SimCell(replace(scene, robot=robot), seed=seed)


def errors(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation (deg) between two poses."""
    return (
        float(np.linalg.norm(found[:3, 3] - truth[:3, 3])),
        math.degrees(rotation_angle(found[:3, :3].T @ truth[:3, :3])),
    )


def calibrate(
    cell: SimCell, vision: SyncVisionClient, intrinsics: CameraIntrinsics, **camera: Any
) -> HandEyeResult:
    devices = sim_devices(cell, vision=vision)
    devices.cameras["tool_camera"] = SimCamera(cell, "tool_camera", **camera)
    collected = collect_hand_eye_views(
        devices, camera="tool_camera", inspection="board_tool", intrinsics=intrinsics
    )
    assert collected.skipped == []
    return solve_hand_eye(collected.views, intrinsics)


def test_tool_from_camera_meets_the_goal_in_the_simulated_cell(vision: SyncVisionClient) -> None:
    """Issue 18: p95 <= 0.3 mm and <= 0.05 deg (20 seeds in bench/hand_eye.py; here 4, each
    within the goal), from 15 poses, with the arm's repeatability and the sensor's noise."""
    for seed in range(4):
        cell = commissioning_cell(seed)
        truth = cell.scene.camera("tool_camera").pose
        result = calibrate(cell, vision, cell.scene.camera("tool_camera").intrinsics)
        translation, rotation = errors(result.camera, truth)
        assert translation <= 0.3e-3, (seed, translation)
        assert rotation <= 0.05, (seed, rotation)
        assert result.verdict == "good", result.reasons  # no good view sent to be checked
        assert len(result.views) == 15
        assert result.rms_px < 0.5
        # The residuals say how good it is: the loop within a millimetre.
        assert result.loop_translation_m < 1e-3


def chain_store(vision: SyncVisionClient, tmp_path: Path) -> tuple[TeachStore, CameraIntrinsics]:
    """Commission the tool camera from the approximate description: intrinsics first (with
    the approximate ones to plan), then the hand-eye with the solved intrinsics; the result
    stored as ``calibrate-hand-eye --yes`` does."""
    cell = commissioning_cell(11)
    devices = sim_devices(cell, vision=vision)
    devices.cameras["tool_camera"] = SimCamera(
        cell, "tool_camera", nominal_mount=NOMINAL_MOUNT, nominal_intrinsics=APPROXIMATE
    )
    views = collect_tool_views(devices, camera="tool_camera", inspection="board_tool")
    assert views.image_size is not None
    intrinsics = solve_intrinsics(views.views, views.image_size).intrinsics
    result = calibrate(
        cell,
        vision,
        intrinsics,
        nominal_mount=NOMINAL_MOUNT,
        nominal_intrinsics=APPROXIMATE,
    )
    translation, rotation = errors(result.camera, cell.scene.camera("tool_camera").pose)
    assert translation <= 0.3e-3, translation
    assert rotation <= 0.05, rotation
    store = TeachStore(tmp_path / "taught.yaml")
    store.put(
        hand_eye_record(
            "tool_camera",
            "eye_in_hand",
            result.camera,
            intrinsics=intrinsics,
            verdict=result.verdict,
            reasons=result.reasons,
            figures={"rms_px": result.rms_px},
        )
    )
    return store, intrinsics


def pick_errors(
    vision: SyncVisionClient, store: TeachStore | None, seeds: range
) -> tuple[list[float], int]:
    """Vision pick of the three caps on the conveyor, in the Grundfos cell whose arm has the
    same repeatability and whose tool camera is described as before commissioning: the grasp
    errors (m) of the picks that grasped, and the number of picks that failed."""
    registry = default_registry()
    picked: list[float] = []
    failed = 0
    for seed in seeds:
        scene = load_scene(PICK_SCENE)
        robot = replace(
            scene.robot, repeatability_m=REPEATABILITY_M, repeatability_rad=REPEATABILITY_RAD
        )
        cell = SimCell(replace(scene, robot=robot), seed=seed)
        devices = sim_devices(cell, vision=vision)
        devices.cameras["tool_camera"] = SimCamera(
            cell, "tool_camera", nominal_mount=NOMINAL_MOUNT, nominal_intrinsics=APPROXIMATE
        )
        ctx = SkillContext.create(devices, store=store)
        record = registry.get("vision_pick").teach("l1", L1, ctx)
        for k in range(len(CAPS)):
            ctx.robot.move_linear(L1["p_cam_start"])
            outcome = execute(registry.get("vision_pick"), record, ctx)
            held = cell.gripper.held
            if not outcome.ok or held is None:
                assert outcome.reason in (FailureReason.GRASP_FAILED, FailureReason.OUT_OF_REGION)
                failed += 1
                break
            tool_from_world = invert_transform(cell.world.world_from_tool())
            grasp = transform_points(tool_from_world, cell.gripper.grasp_point(held))
            picked.append(float(np.linalg.norm(grasp)))
            ctx.gripper.open()
            ctx.world.held_part = None
            pose = cell.world.parts[held].world_from_part.copy()
            pose[:2, 3] = (2.0 + 0.1 * k, 2.0)  # onto the floor, out of sight
            cell.world.parts[held].world_from_part = pose
            cell.publish()
    return picked, failed


def test_vision_pick_with_the_calibrated_hand_eye_and_intrinsics(
    vision: SyncVisionClient, tmp_path: Path
) -> None:
    """Issue 18: the whole chain keeps the pick error p95 <= 0.5 mm; the camera's own
    (uncommissioned) description would not."""
    store, intrinsics = chain_store(vision, tmp_path)
    ctx = SkillContext.create(sim_devices(commissioning_cell(0)), store=store)
    camera = ctx.camera("tool_camera")
    assert isinstance(camera, CalibratedCamera)
    assert camera.intrinsics == intrinsics
    picked, failed = pick_errors(vision, store, range(40, 43))
    assert failed == 0
    assert len(picked) == 9
    assert np.percentile(picked, 95) <= 0.5e-3, picked
    uncommissioned, failed = pick_errors(vision, None, range(40, 41))
    mm = np.asarray(picked) * 1000
    print(f"\ncalibrated: p50 {np.median(mm):.3f} mm, p95 {np.percentile(mm, 95):.3f} mm")
    print(f"uncommissioned: {np.round(np.asarray(uncommissioned) * 1000, 3)} mm, {failed} failed")
    assert failed > 0 or min(uncommissioned) > 1e-3, uncommissioned


def test_a_fixed_camera_or_a_board_out_of_view_is_told_so(vision: SyncVisionClient) -> None:
    cell = commissioning_cell(0)
    devices = sim_devices(cell, vision=vision)
    intrinsics = cell.scene.camera("tool_camera").intrinsics
    # The fixed camera sees the board on the table, which stays put as the tool moves.
    start = devices.robot.base_from_tool()
    with pytest.raises(ValueError, match="'fixed_camera' sees did not move with the tool"):
        collect_hand_eye_views(
            devices,
            camera="fixed_camera",
            inspection="board_tool",
            intrinsics=cell.scene.camera("fixed_camera").intrinsics,
        )
    np.testing.assert_allclose(devices.robot.base_from_tool(), start)
    away = devices.robot.base_from_tool()
    away[:3, 3] += [0.0, 0.6, 0.0]
    devices.robot.move_linear(away)
    with pytest.raises(ValueError, match="the board is not in view of camera 'tool_camera'"):
        collect_hand_eye_views(
            devices, camera="tool_camera", inspection="board_tool", intrinsics=intrinsics
        )


def test_poses_the_robot_cannot_reach_are_skipped_with_the_reason(
    vision: SyncVisionClient,
) -> None:
    scene = commissioning_cell(0).scene
    # The ceiling just above the start: the poses from higher up cannot be taken.
    top = (scene.robot.workspace_max[0], scene.robot.workspace_max[1], 0.4)
    cell = SimCell(replace(scene, robot=replace(scene.robot, workspace_max=top)), seed=0)
    devices = sim_devices(cell, vision=vision)
    start = devices.robot.base_from_tool()
    intrinsics = cell.scene.camera("tool_camera").intrinsics
    collected = collect_hand_eye_views(
        devices, camera="tool_camera", inspection="board_tool", intrinsics=intrinsics
    )
    assert 0 < len(collected.skipped) < 15
    assert all("outside the robot's workspace" in why for _, why in collected.skipped)
    assert len(collected.views) + len(collected.skipped) == 15
    taken = {label for label, _ in collected.skipped} | set(collected.labels)
    assert taken == {f"pose {i}" for i in range(1, 16)}
    np.testing.assert_allclose(devices.robot.base_from_tool(), start)
    result = solve_hand_eye(collected.views, intrinsics)  # the rest still gives a pose
    assert result.verdict != "redo", result.reasons
