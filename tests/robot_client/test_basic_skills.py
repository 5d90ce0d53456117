"""move_to, place and press on the simulated cell, checked against its ground truth."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from geometry import invert_transform, make_transform, transform_from_xyz_rpy
from robot_client.devices.sim import sim_devices
from robot_client.skills import Calibration, FailureReason, SkillContext, default_registry, execute
from simulation import BOARD_FROM_QR, SimCell, load_scene

SCENE = Path(__file__).resolve().parents[2] / "examples/scenes/grundfos_cell.yaml"
DOWN = [np.pi, 0.0, 0.0]
REG = default_registry()


def _ctx(cell: SimCell | None = None) -> SkillContext:
    return SkillContext.create(sim_devices(cell or SimCell.from_yaml(SCENE)))


def _grasp(ctx: SkillContext, part: str) -> None:
    cell = ctx.robot.cell  # type: ignore[attr-defined]
    p_world = cell.gripper.grasp_point(part)
    p_base = (invert_transform(cell.robot.world_from_base) @ np.append(p_world, 1.0))[:3]
    ctx.robot.move_linear(transform_from_xyz_rpy(p_base + [0, 0, 0.1], DOWN))
    ctx.robot.move_linear(transform_from_xyz_rpy(p_base, DOWN))
    assert ctx.gripper.close()
    ctx.world.held_part = part


def test_move_to_goes_to_the_taught_pose() -> None:
    ctx = _ctx()
    skill = REG.get("move_to")
    target = transform_from_xyz_rpy([0.05, -0.55, 0.275], DOWN)
    record = skill.teach("search_l1", {"pose": target, "speed_m_s": 0.5}, ctx)
    t0 = ctx.clock.now()
    outcome = execute(skill, record, ctx)
    assert outcome.ok, outcome
    assert np.allclose(ctx.robot.base_from_tool(), target, atol=1e-8)
    assert outcome.duration_s == pytest.approx(ctx.clock.now() - t0)
    assert outcome.duration_s > 0


def test_move_to_out_of_reach_is_unreachable() -> None:
    ctx = _ctx()
    skill = REG.get("move_to")
    record = skill.teach("far", {"pose": transform_from_xyz_rpy([2.0, 0, 0.3], DOWN)}, ctx)
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.UNREACHABLE
    assert "workspace" in outcome.message


def test_place_needs_a_held_part() -> None:
    ctx = _ctx()
    skill = REG.get("place")
    record = skill.teach("bin_l2", {"pose": transform_from_xyz_rpy([0.68, 0.3, 0.05], DOWN)}, ctx)
    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.NOT_HOLDING
    assert outcome.phase == "pre"
    assert "holds no part" in outcome.message


def test_place_puts_the_part_in_the_bin() -> None:
    ctx = _ctx()
    _grasp(ctx, "cap_4")
    skill = REG.get("place")
    place_pose = transform_from_xyz_rpy([0.68, 0.3, 0.05], DOWN)
    record = skill.teach("bin_l2", {"pose": place_pose, "approach_m": 0.12}, ctx)
    outcome = execute(skill, record, ctx)
    assert outcome.ok, outcome
    assert outcome.data["part"] == "cap_4"
    cell = ctx.robot.cell  # type: ignore[attr-defined]
    assert cell.world.parts["cap_4"].location == "bin_l2"
    assert not ctx.world.holding
    assert ctx.world.held_part is None
    # it ended above the place pose, back along the tool's z (up, for a tool looking down)
    assert np.allclose(ctx.robot.base_from_tool()[:3, 3], [0.68, 0.3, 0.17], atol=1e-8)


def _wide_cell() -> SimCell:
    """The example cell with a workspace that reaches the station panel's switch."""
    scene = load_scene(SCENE)
    robot = dataclasses.replace(scene.robot, workspace_max=(1.5, 1.0, 0.8))
    return SimCell(dataclasses.replace(scene, robot=robot))


def _recorded_moves(ctx: SkillContext) -> list[NDArray[np.float64]]:
    moves: list[NDArray[np.float64]] = []
    robot = ctx.robot
    original = robot.move_linear

    def move(pose: NDArray[np.float64], *, speed_m_s: float | None = None) -> None:
        original(pose, speed_m_s=speed_m_s)
        moves.append(robot.base_frame() @ robot.base_from_tool())

    robot.move_linear = move  # type: ignore[method-assign]
    return moves


def test_press_taught_in_the_qr_frame_pushes_the_switch() -> None:
    cell = _wide_cell()
    ctx = _ctx(cell)
    frame = "qr:station-1"
    board = cell.scene.qr_boards[0]
    base_from_world = invert_transform(cell.robot.world_from_base)
    base_from_qr = base_from_world @ board.world_from_board @ BOARD_FROM_QR
    switch_world = cell.scene.switches[0].world_from_switch[:3, 3]
    p_qr = (invert_transform(base_from_qr) @ base_from_world @ np.append(switch_world, 1.0))[:3]
    qr_from_touch = make_transform(np.eye(3), p_qr)  # tool z = the QR's z, into the panel
    skill = REG.get("press")
    record = skill.teach(
        "conveyor_switch", {"pose": qr_from_touch, "depth_m": 0.006}, ctx, frame=frame
    )
    assert record.frame == frame

    outcome = execute(skill, record, ctx)
    assert outcome.reason is FailureReason.NO_CALIBRATION
    assert "run its calibration skill first" in outcome.message

    ctx.world.set_calibration(
        Calibration(frame, base_from_qr, ctx.clock.now(), {"residual_m": 3e-4})
    )
    moves = _recorded_moves(ctx)
    outcome = execute(skill, record, ctx)
    assert outcome.ok, outcome
    assert len(moves) == 3
    approach, pressed, retract = (m[:3, 3] for m in moves)
    switch_base = (base_from_world @ np.append(switch_world, 1.0))[:3]
    into_panel = base_from_qr[:3, 2]
    assert np.allclose(pressed, switch_base + 0.006 * into_panel, atol=1e-8)
    assert np.allclose(approach, switch_base - 0.05 * into_panel, atol=1e-8)
    assert np.allclose(retract, approach)
    assert into_panel[0] == pytest.approx(1.0, abs=1e-6)  # the panel faces the robot along -x


def test_basic_skills_state_their_conditions() -> None:
    assert [c.name for c in REG.get("place").spec.pre] == ["holding"]
    assert [c.name for c in REG.get("place").spec.post] == ["gripper_empty"]
    assert [c.name for c in REG.get("press").spec.pre] == ["calibration_valid"]
    assert REG.get("press").spec.calibrated
