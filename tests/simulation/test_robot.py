"""The simulated arm and gripper: timing, workspace, user frame, grasp tolerance, place."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geometry import invert_transform, transform_from_xyz_rpy
from simulation import SimCell, WorkspaceError

DOWN = (np.pi, 0.0, 0.0)


def _pose(x: float, y: float, z: float) -> np.ndarray:
    return transform_from_xyz_rpy([x, y, z], DOWN)


def test_linear_move_takes_distance_over_speed(example_cell: SimCell) -> None:
    robot = example_cell.robot
    start = robot.tool_pose()
    target = start.copy()
    target[:3, 3] += [0.1, -0.2, 0.0]
    t0 = example_cell.clock.now()
    duration = robot.move_linear(target)
    assert duration == pytest.approx(np.hypot(0.1, 0.2) / 0.25)
    assert example_cell.clock.now() - t0 == pytest.approx(duration)
    np.testing.assert_allclose(robot.tool_pose(), target)
    assert robot.move_linear(target, speed_m_s=0.5) == 0.0


def test_workspace_limits(example_cell: SimCell) -> None:
    robot = example_cell.robot
    before = robot.tool_pose()
    with pytest.raises(WorkspaceError, match="outside the workspace"):
        robot.move_linear(_pose(1.5, 0.0, 0.3))
    np.testing.assert_array_equal(robot.tool_pose(), before)
    with pytest.raises(ValueError, match="target"):
        robot.move_linear(np.eye(4) * 2)


def test_user_frame(example_cell: SimCell) -> None:
    robot = example_cell.robot
    base_from_user = transform_from_xyz_rpy([0.2, -0.1, 0.0], [0.0, 0.0, 0.3])
    robot.set_user_frame(base_from_user)
    user_from_tool = _pose(0.1, 0.0, 0.3)
    robot.move_linear(user_from_tool, frame="user")
    np.testing.assert_allclose(robot.tool_pose(), base_from_user @ user_from_tool, atol=1e-12)
    np.testing.assert_allclose(robot.tool_pose("user"), user_from_tool, atol=1e-12)


def test_tool_camera_follows_the_tool(example_cell: SimCell) -> None:
    example_cell.robot.move_linear(_pose(0.3, -0.55, 0.275))
    world_from_camera = example_cell.world_from_camera("tool_camera")
    expected = (
        example_cell.robot.world_from_base
        @ example_cell.robot.tool_pose()
        @ example_cell.scene.camera("tool_camera").pose
    )
    np.testing.assert_allclose(world_from_camera, expected)
    # Looking straight down from 0.35 m above the cap tops (0.825 m).
    assert world_from_camera[2, 3] == pytest.approx(0.825 + 0.35)
    np.testing.assert_allclose(world_from_camera[:3, 2], [0, 0, -1], atol=1e-12)


def _grasp_target(cell: SimCell, name: str, dx: float = 0.0, dz: float = 0.0) -> np.ndarray:
    p_world = cell.gripper.grasp_point(name) + np.array([dx, 0.0, dz])
    p_base = invert_transform(cell.robot.world_from_base) @ np.append(p_world, 1.0)
    return _pose(*p_base[:3])


def test_grasp_only_within_tolerance(example_cell: SimCell) -> None:
    cell = example_cell
    cell.robot.move_linear(_grasp_target(cell, "cap_2", dx=0.006))
    assert cell.gripper.grasp() is None
    cell.robot.move_linear(_grasp_target(cell, "cap_2", dz=0.012))
    assert cell.gripper.grasp() is None
    cell.robot.move_linear(_grasp_target(cell, "cap_2", dx=0.003, dz=0.004))
    assert cell.gripper.grasp() == "cap_2"
    assert cell.gripper.held == "cap_2"
    assert cell.gripper.grasp() is None  # already holding one


def test_held_part_moves_with_tool_and_is_placed(example_cell: SimCell) -> None:
    cell = example_cell
    cell.robot.move_linear(_grasp_target(cell, "cap_4"))
    assert cell.gripper.grasp() == "cap_4"
    before = cell.world.part_pose("cap_4")
    lift = cell.robot.tool_pose()
    lift[:3, 3] += [0.0, 0.0, 0.1]
    cell.robot.move_linear(lift)
    np.testing.assert_allclose(cell.world.part_pose("cap_4")[:3, 3], before[:3, 3] + [0, 0, 0.1])
    # Over the bin on table L2, release: the cap drops onto the bin floor.
    bin_spec = cell.scene.bins[0]
    over_bin = bin_spec.world_from_bin[:3, 3] + [0.0, 0.0, 0.15]
    p_base = invert_transform(cell.robot.world_from_base) @ np.append(over_bin, 1.0)
    cell.robot.move_linear(_pose(*p_base[:3]))
    assert cell.gripper.release() == "cap_4"
    assert cell.gripper.held is None
    state = cell.world.parts["cap_4"]
    assert state.location == "bin_l2"
    floor = bin_spec.world_from_bin[2, 3] + bin_spec.wall_m
    assert state.world_from_part[2, 3] == pytest.approx(floor)
    assert cell.gripper.release() is None


def test_docking_error_is_seeded() -> None:
    from .conftest import EXAMPLE_SCENE

    a, b = SimCell.from_yaml(EXAMPLE_SCENE), SimCell.from_yaml(EXAMPLE_SCENE)
    pa, pb = a.dock(), b.dock()
    np.testing.assert_array_equal(pa, pb)
    nominal = a.scene.robot.world_from_base
    offset = np.linalg.norm(pa[:2, 3] - nominal[:2, 3])
    assert 0 < offset <= 0.02 * np.sqrt(2)


def test_repeatability_moves_the_true_tool_while_the_arm_reports_the_target() -> None:
    """Scene ``robot.repeatability``: the world (cameras, gripper) has the tool where it truly
    ended, the arm reports the commanded pose; the error's spread is the one asked for."""
    from dataclasses import replace

    from geometry import rotation_angle

    from .conftest import EXAMPLE_SCENE

    exact = SimCell.from_yaml(EXAMPLE_SCENE)
    spec = replace(exact.scene.robot, repeatability_m=0.03e-3, repeatability_rad=1.75e-4)
    cell = SimCell(replace(exact.scene, robot=spec))
    shifts, turns = [], []
    for i in range(200):
        target = _pose(0.5 + 0.001 * (i % 7), 0.0, 0.3)
        cell.robot.move_linear(target)
        np.testing.assert_array_equal(cell.robot.tool_pose(), target)
        true = cell.world.base_from_tool
        shifts.append(true[:3, 3] - target[:3, 3])
        turns.append(rotation_angle(target[:3, :3].T @ true[:3, :3]))
    assert float(np.std(shifts)) == pytest.approx(0.03e-3, rel=0.2)
    assert float(np.sqrt(np.mean(np.square(turns)))) == pytest.approx(1.75e-4, rel=0.2)
    # Once something else puts the tool elsewhere, the arm reports where it is.
    cell.restart()
    np.testing.assert_array_equal(cell.robot.tool_pose(), cell.world.base_from_tool)
    exact.robot.move_linear(_pose(0.5, 0.0, 0.3))
    np.testing.assert_array_equal(exact.world.base_from_tool, _pose(0.5, 0.0, 0.3))


def test_repeatability_is_read_from_the_scene(tmp_path: Path) -> None:
    from .conftest import EXAMPLE_SCENE

    text = Path(EXAMPLE_SCENE).read_text(encoding="utf-8")
    text = text.replace(
        "  docking_error:", "  repeatability: {m: 0.00003, rad: 0.000175}\n  docking_error:", 1
    )
    path = tmp_path / "scene.yaml"
    path.write_text(text, encoding="utf-8")
    spec = SimCell.from_yaml(path).scene.robot
    assert (spec.repeatability_m, spec.repeatability_rad) == (0.00003, 0.000175)
