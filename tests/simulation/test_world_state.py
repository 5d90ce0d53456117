"""Sharing the world between processes through the atomically written world-state file."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from geometry import invert_transform, transform_from_xyz_rpy
from simulation import SimCell, World, WorldStateFile

from .conftest import EXAMPLE_SCENE, REPO


def _pick(cell: SimCell, name: str) -> None:
    p_world = cell.gripper.grasp_point(name)
    p_base = invert_transform(cell.robot.world_from_base) @ np.append(p_world, 1.0)
    cell.robot.move_linear(transform_from_xyz_rpy(p_base[:3], [np.pi, 0, 0]))
    assert cell.gripper.grasp() == name


def test_world_round_trip(tmp_path: Path) -> None:
    cell = SimCell.from_yaml(EXAMPLE_SCENE)
    world = cell.world
    again = World.from_dict(json.loads(json.dumps(world.to_dict())))
    assert again.parts.keys() == world.parts.keys()
    for name in world.parts:
        np.testing.assert_array_equal(again.part_pose(name), world.part_pose(name))
    with pytest.raises(ValueError, match="format"):
        World.from_dict({"format": "something else"})


def test_two_cells_share_the_world(tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    client = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    server = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    assert server.render("qc_camera").truth.parts["magnet"].location == ""
    _pick(client, "magnet")
    # Put the magnet beside the rotor core, where the QC camera looks for it.
    core = client.world.part_pose("rotor_core")[:3, 3]
    target = core + [0.05, 0.0, 0.02]
    p_base = invert_transform(client.robot.world_from_base) @ np.append(target, 1.0)
    client.robot.move_linear(transform_from_xyz_rpy(p_base[:3], [np.pi, 0, 0]))
    assert client.gripper.release() == "magnet"

    frame = server.render("qc_camera")
    assert frame.truth.parts["magnet"].location == "qc_table"
    np.testing.assert_allclose(
        server.world.part_pose("magnet"), client.world.part_pose("magnet"), atol=1e-12
    )
    assert frame.truth.features["magnet.top_centre"].visible
    np.testing.assert_allclose(server.world.base_from_tool, client.world.base_from_tool)
    # Nothing new: the server does not re-read.
    assert not server.sync()


def test_reader_skips_unchanged_file(tmp_path: Path) -> None:
    path = tmp_path / "w.json"
    writer, reader = WorldStateFile(path), WorldStateFile(path)
    assert reader.read_if_changed() is None  # no file yet
    world = SimCell.from_yaml(EXAMPLE_SCENE).world
    world.version = 3
    writer.write(world)
    assert reader.read_if_changed() is not None
    assert reader.read_if_changed() is None
    world.version = 4
    writer.write(world)
    got = reader.read_if_changed()
    assert got is not None
    assert got.version == 4
    assert not list(tmp_path.glob(".w.json.*"))  # no temporary files left behind


def test_a_real_second_process_sees_the_robot(tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    server = SimCell.from_yaml(EXAMPLE_SCENE, state_path=state)
    assert server.render("tool_camera").truth.features["cap_2.top_centre"].visible is not None
    script = f"""
import numpy as np
from geometry import invert_transform, transform_from_xyz_rpy
from simulation import SimCell
cell = SimCell.from_yaml({str(EXAMPLE_SCENE)!r}, state_path={str(state)!r})
p = invert_transform(cell.robot.world_from_base) @ np.append(cell.gripper.grasp_point("cap_2"), 1)
cell.robot.move_linear(transform_from_xyz_rpy(p[:3], [np.pi, 0, 0]))
assert cell.gripper.grasp() == "cap_2"
p[2] += 0.2
cell.robot.move_linear(transform_from_xyz_rpy(p[:3], [np.pi, 0, 0]))
"""
    subprocess.run([sys.executable, "-c", script], check=True, cwd=REPO, timeout=60)
    server.sync()
    assert server.world.parts["cap_2"].held
    assert server.world.part_pose("cap_2")[2, 3] == pytest.approx(0.8 + 0.2, abs=1e-9)
