"""Starting the simulated cell again from its scene, and the line's deliveries (the scene's
``delivered`` poses): what ``robot-client ... --fresh`` and ``make demo``'s late station use."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geometry import invert_transform, transform_from_xyz_rpy
from simulation import SceneError, SimCell, load_scene, scene_from_text

from .conftest import BOARD_SCENE, EXAMPLE_SCENE

SLOT_WORLD = (0.20, 0.65)  # the example scene's magnet slot: 0.05 m along +x from the core


def test_the_example_scene_delivers_the_magnet_into_its_slot() -> None:
    scene = load_scene(EXAMPLE_SCENE)
    slot = scene.part("magnet").world_from_delivered
    assert slot is not None
    np.testing.assert_allclose(slot[:3, 3], [*SLOT_WORLD, 0.8])  # on the qc table's top
    np.testing.assert_allclose(slot[:3, :3], np.eye(3))
    assert [p.name for p in scene.parts if p.world_from_delivered is not None] == ["magnet"]


def test_a_delivery_names_an_unknown_support_or_key() -> None:
    part = "  - {name: c, type: rotor_cap, at: [0, 0], support: wall, delivered: %s}\n"
    for delivered, expected in [
        (
            "{at: [0, 0], support: nowhere}",
            r"parts\[0\] \(name='c'\) -> delivered -> support: unknown support",
        ),
        (
            "{at: [0, 0], support: wall, spin: 1}",
            r"parts\[0\] \(name='c'\) -> delivered -> spin: unknown key",
        ),
    ]:
        text = BOARD_SCENE.replace("qr_boards:", "parts:\n" + part % delivered + "qr_boards:")
        with pytest.raises(SceneError, match=expected):
            scene_from_text(text)


def test_deliver_moves_the_part_and_the_other_process_sees_it(tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    robot_side = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    camera_side = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    feeder = robot_side.world.part_pose("magnet").copy()
    assert robot_side.deliver() == ["magnet"]
    assert robot_side.world.parts["magnet"].location == "qc_table"
    assert not np.allclose(robot_side.world.part_pose("magnet"), feeder)
    truth = camera_side.render("qc_camera").truth
    np.testing.assert_allclose(truth.parts["magnet"].world_from_part[:2, 3], SLOT_WORLD)
    assert truth.features["magnet.top_centre"].visible
    with pytest.raises(KeyError, match="cap_1"):
        robot_side.deliver("cap_1")  # the scene delivers no caps


def test_deliver_leaves_a_held_part_in_the_gripper(tmp_path: Path) -> None:
    cell = SimCell.from_yaml(EXAMPLE_SCENE)
    p_base = invert_transform(cell.robot.world_from_base) @ np.append(
        cell.gripper.grasp_point("magnet"), 1.0
    )
    cell.robot.move_linear(transform_from_xyz_rpy(p_base[:3], [np.pi, 0, 0]))
    assert cell.gripper.grasp() == "magnet"
    assert cell.deliver() == []
    assert cell.gripper.held == "magnet"


def test_restart_replaces_the_world_another_run_left(tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    earlier = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    start = {name: earlier.world.part_pose(name).copy() for name in earlier.world.parts}
    earlier.dock()
    earlier.deliver()
    earlier.clock.advance(12.0)
    earlier.publish()
    reader = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)  # e.g. the server's qc camera

    again = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)  # continues the file ...
    assert again.world.time_s == pytest.approx(12.0)
    again.restart()  # ... until it starts again
    for cell in (again, SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)):
        assert cell.world.time_s == 0.0
        np.testing.assert_allclose(cell.world.world_from_base, cell.scene.robot.world_from_base)
        np.testing.assert_allclose(cell.world.base_from_tool, cell.scene.robot.home)
        for name, pose in start.items():
            np.testing.assert_allclose(cell.world.part_pose(name), pose)
    assert reader.sync()  # a reader follows the restarted writer
    np.testing.assert_allclose(reader.world.part_pose("magnet"), start["magnet"])
