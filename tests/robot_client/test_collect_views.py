"""Collecting a tool camera's views through a real server on loopback: poses the robot cannot
take are skipped with their reason, and the robot ends where it started."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from loopback import server_in_thread

from robot_client import SyncVisionClient
from robot_client.commissioning.collect import collect_tool_views
from robot_client.devices.sim import sim_devices
from simulation import SimCell, load_scene
from vision_server.service import CellRuntime

CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  tool: {source: request}
inspections:
  - name: board_tool
    type: calibration_board
    camera: tool
    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}
"""


@pytest.fixture
def vision(tmp_path: Path) -> Iterator[SyncVisionClient]:
    path = tmp_path / "cell.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    runtime = CellRuntime(path)
    try:
        with server_in_thread(runtime.catalog) as server:
            client = SyncVisionClient("127.0.0.1", server.port, request_timeout_s=30.0)
            try:
                yield client
            finally:
                client.close()
    finally:
        runtime.close()


def _cell(max_z_m: float) -> SimCell:
    scene = load_scene("examples/scenes/intrinsics_cell.yaml")
    top = (scene.robot.workspace_max[0], scene.robot.workspace_max[1], max_z_m)
    robot = replace(scene.robot, workspace_max=top)
    return SimCell(replace(scene, robot=robot))


def test_every_planned_view_is_taken_in_the_open_cell(vision: SyncVisionClient) -> None:
    devices = sim_devices(_cell(0.8), vision=vision)
    start = devices.robot.base_from_tool()
    collected = collect_tool_views(devices, camera="tool_camera", inspection="board_tool")
    assert len(collected.views) == 15
    assert collected.skipped == []
    assert collected.image_size == (1024, 768)
    assert collected.board == "charuco 11x8, 30 mm squares"
    assert np.allclose(devices.robot.base_from_tool(), start)


def test_poses_above_the_workspace_are_skipped_with_the_reason(vision: SyncVisionClient) -> None:
    # The ceiling just above the start: the views from higher up cannot be taken.
    devices = sim_devices(_cell(0.38), vision=vision)
    start = devices.robot.base_from_tool()
    collected = collect_tool_views(devices, camera="tool_camera", inspection="board_tool")
    assert 0 < len(collected.skipped) < 15
    assert all("outside the robot's workspace" in why for _, why in collected.skipped)
    assert len(collected.views) + len(collected.skipped) == 15
    assert np.allclose(devices.robot.base_from_tool(), start)


def test_a_camera_that_does_not_see_the_board_at_the_start_is_told_so(
    vision: SyncVisionClient,
) -> None:
    devices = sim_devices(_cell(0.8), vision=vision)
    away = devices.robot.base_from_tool()
    away[:3, 3] += np.array([0.0, 0.6, 0.0])
    devices.robot.move_linear(away)
    with pytest.raises(ValueError, match="the board is not in view of camera 'tool_camera'"):
        collect_tool_views(devices, camera="tool_camera", inspection="board_tool")


def test_a_fixed_camera_is_refused(vision: SyncVisionClient) -> None:
    devices = sim_devices(_cell(0.8), vision=vision)
    with pytest.raises(ValueError, match="not on the tool: calibrate it with --fixed"):
        collect_tool_views(devices, camera="fixed_camera", inspection="board_tool")
