"""The simulated backend: device primitives over SimCell, sharing the world-state file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geometry import invert_transform, transform_from_xyz_rpy
from robot_client.devices import Camera, DeviceError, Gripper, Robot, Unreachable
from robot_client.devices.sim import sim_devices
from simulation import SimCell

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "examples/scenes/grundfos_cell.yaml"
DOWN = [np.pi, 0.0, 0.0]


def test_sim_devices_satisfy_the_interfaces() -> None:
    devices = sim_devices(SCENE)
    assert isinstance(devices.robot, Robot)
    assert isinstance(devices.gripper, Gripper)
    assert set(devices.cameras) == {"tool_camera", "qc_camera", "rgbd"}
    assert all(isinstance(c, Camera) for c in devices.cameras.values())
    with pytest.raises(DeviceError, match="no camera 'nope'"):
        devices.camera("nope")


def test_move_and_base_frame_are_the_sim_user_frame() -> None:
    devices = sim_devices(SCENE)
    robot = devices.robot
    target = transform_from_xyz_rpy([0.3, -0.4, 0.3], DOWN)
    t0 = devices.clock.now()
    robot.move_linear(target)
    assert devices.clock.now() > t0  # simulated time
    assert np.allclose(robot.base_from_tool(), target)
    base_from_user = transform_from_xyz_rpy([0.1, 0.0, 0.0], [0, 0, 0.2])
    robot.set_base_frame(base_from_user)
    assert np.allclose(robot.base_frame(), base_from_user)
    assert np.allclose(robot.base_frame() @ robot.base_from_tool(), target)
    user_target = transform_from_xyz_rpy([0.2, -0.3, 0.25], DOWN)
    robot.move_linear(user_target)
    assert np.allclose(robot.base_from_tool(), user_target)
    with pytest.raises(Unreachable, match="outside the workspace"):
        robot.move_linear(transform_from_xyz_rpy([3.0, 0.0, 0.3], DOWN))
    assert not robot.in_workspace([3.0, 0.0, 0.3])


def test_gripper_grasps_a_part_at_its_grasp_point() -> None:
    devices = sim_devices(SCENE)
    cell = devices.robot.cell  # type: ignore[attr-defined]
    assert devices.gripper.close() is False
    devices.gripper.open()
    p_world = cell.gripper.grasp_point("cap_4")
    p_base = (invert_transform(cell.robot.world_from_base) @ np.append(p_world, 1))[:3]
    devices.robot.move_linear(transform_from_xyz_rpy(p_base, DOWN))
    assert devices.gripper.close() is True
    assert devices.gripper.holding
    assert devices.gripper.held_part == "cap_4"  # type: ignore[attr-defined]
    devices.gripper.open()
    assert not devices.gripper.holding


def test_tool_camera_capture_knows_where_it_was(tmp_path: Path) -> None:
    devices = sim_devices(SCENE, state_path=tmp_path / "world.json")
    devices.robot.move_linear(transform_from_xyz_rpy([0.3, -0.55, 0.275], DOWN))
    cam = devices.camera("tool_camera")
    cap = cam.capture()
    assert cap.color.shape == (768, 1024)
    assert cap.depth == ()
    assert cap.intrinsics == cam.intrinsics
    assert cam.tool_from_camera is not None
    expected = devices.robot.base_from_tool() @ cam.tool_from_camera
    assert np.allclose(cap.base_from_camera, expected)
    assert np.allclose(cap.user_from_camera, expected)
    with pytest.raises(ValueError, match="no depth"):
        cam.capture(depth_frames=2)


def test_rgbd_capture_gives_the_depth_frames_asked() -> None:
    devices = sim_devices(SCENE)
    devices.robot.move_linear(
        transform_from_xyz_rpy([0.25, -0.36, 0.35], [-np.pi / 2, 0, -np.pi / 2])
    )
    cap = devices.camera("rgbd").capture(depth_frames=3)
    assert len(cap.depth) == 3
    assert all(d.dtype == np.uint16 and d.shape == (480, 640) for d in cap.depth)
    assert not np.array_equal(cap.depth[0], cap.depth[1])  # independent noise


def test_fixed_camera_pose_is_the_nominal_mount() -> None:
    devices = sim_devices(SCENE)
    cam = devices.camera("qc_camera")
    assert cam.tool_from_camera is None
    cap = cam.capture()
    cell = devices.robot.cell  # type: ignore[attr-defined]
    assert np.allclose(cap.base_from_camera[:3, 3], [0.15, 0.65, 0.6])
    assert cap.base_from_camera.shape == (4, 4)
    assert cell is not None


def test_moves_are_published_for_the_server_process(tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    devices = sim_devices(SCENE, state_path=state)
    server_side = SimCell.from_yaml(SCENE, state_path=state)
    target = transform_from_xyz_rpy([0.5, -0.2, 0.3], DOWN)
    devices.robot.move_linear(target)
    devices.robot.set_base_frame(transform_from_xyz_rpy([0.0, 0.1, 0.0], [0, 0, 0]))
    assert server_side.sync()
    assert np.allclose(server_side.world.base_from_tool, target)
    assert np.allclose(server_side.robot.base_from_user[:3, 3], [0.0, 0.1, 0.0])


def test_server_intrinsics_keep_their_distortion_on_the_client() -> None:
    """The server's FRAMES intrinsics (``dist``, SPEC §6.4) reach the client's camera model
    whole; before, the server sent another name and the client silently used no distortion."""
    from robot_client.devices.vision import intrinsics_from_dict
    from vision_server.cameras import Intrinsics

    sent = Intrinsics(
        fx=800.0, fy=810.0, cx=320.0, cy=240.0, width=640, height=480,
        distortion=(0.1, -0.2, 0.001, 0.002, 0.05),
    )  # fmt: skip
    got = intrinsics_from_dict(sent.to_dict())
    assert got.dist == (0.1, -0.2, 0.001, 0.002, 0.05)
    assert (got.fx, got.fy, got.cx, got.cy, got.width, got.height) == (800, 810, 320, 240, 640, 480)
    four = Intrinsics(
        fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=2, height=2, distortion=(0.1, 0.2, 0.0, 0.0)
    )
    assert intrinsics_from_dict(four.to_dict()).dist == (0.1, 0.2, 0.0, 0.0, 0.0)
    rational = Intrinsics(
        fx=1.0, fy=1.0, cx=0.0, cy=0.0, width=2, height=2,
        distortion=(0.1, 0.2, 0.0, 0.0, 0.0, 0.3, 0.0, 0.0),
    )  # fmt: skip
    with pytest.raises(DeviceError, match="k4 and on"):
        intrinsics_from_dict(rational.to_dict())


def test_a_camera_the_robot_lacks_is_a_usage_error_in_the_cli(tmp_path: Path) -> None:
    """A mistyped --camera was reported as a device error (exit 3, like a robot that does not
    answer); it is the caller's mistake (exit 2), and still a DeviceError for a skill."""
    from protocol.cli import ErrorKind
    from robot_client.commands.program import _classify
    from robot_client.devices import DeviceError, UnknownDevice

    devices = sim_devices(SCENE, state_path=tmp_path / "world.json")
    try:
        with pytest.raises(UnknownDevice, match="no camera 'nosuch' on this robot") as excinfo:
            devices.camera("nosuch")
    finally:
        devices.close()
    assert isinstance(excinfo.value, DeviceError)
    classified = _classify(excinfo.value)
    assert classified is not None
    assert classified[0] is ErrorKind.USAGE
