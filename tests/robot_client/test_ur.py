"""The UR backend against a fake of ur_rtde's API: same method names and semantics, with state
(moveL moves the TCP that getActualTCPPose reports; digital outputs are remembered)."""

from __future__ import annotations

import sys
import types

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from geometry import rotation_angle, rotation_from_axis_angle, transform_from_xyz_rpy
from robot_client.devices import DeviceError, Gripper, Robot, Unreachable
from robot_client.devices.ur import (
    URGripper,
    URRobot,
    axis_angle_from_rotation,
    connect_ur,
    pose_from_ur,
    rotation_from_ur_vector,
    ur_from_pose,
)


class FakeUR:
    """One controller: RTDEControlInterface, RTDEReceiveInterface and RTDEIOInterface in one
    object, as the real three share one robot. Poses are [x, y, z, rx, ry, rz]; the safety
    limits are a sphere of ``reach_m`` around the base."""

    def __init__(self, reach_m: float = 0.85) -> None:
        self.tcp = [0.3, -0.2, 0.4, np.pi, 0.0, 0.0]
        self.tcp_offset = [0.0] * 6
        self.reach_m = reach_m
        self.standard_out = [False] * 8
        self.tool_out = [False] * 2
        self.digital_in = [False] * 8
        self.calls: list[tuple[str, tuple[object, ...]]] = []
        self.connected = True
        self.refuse_moves = False

    # control
    def moveL(self, pose, speed=0.25, acceleration=1.2, asynchronous=False):  # noqa: N802
        self.calls.append(("moveL", (list(pose), speed, acceleration)))
        if self.refuse_moves or not self.isPoseWithinSafetyLimits(pose):
            return False
        self.tcp = list(pose)
        return True

    def isPoseWithinSafetyLimits(self, pose):  # noqa: N802
        return bool(np.linalg.norm(pose[:3]) <= self.reach_m)

    def setTcp(self, tcp_offset):  # noqa: N802
        self.calls.append(("setTcp", (list(tcp_offset),)))
        self.tcp_offset = list(tcp_offset)
        return True

    def stopL(self, a=10.0):  # noqa: N802
        self.calls.append(("stopL", (a,)))

    def disconnect(self):
        self.connected = False

    # receive
    def getActualTCPPose(self):  # noqa: N802
        return list(self.tcp)

    def getDigitalInState(self, input_id):  # noqa: N802
        return self.digital_in[input_id]

    def getDigitalOutState(self, output_id):  # noqa: N802
        return self.standard_out[output_id]

    # io
    def setStandardDigitalOut(self, output_id, signal_level):  # noqa: N802
        self.calls.append(("setStandardDigitalOut", (output_id, signal_level)))
        self.standard_out[output_id] = bool(signal_level)
        return True

    def setToolDigitalOut(self, output_id, signal_level):  # noqa: N802
        self.calls.append(("setToolDigitalOut", (output_id, signal_level)))
        self.tool_out[output_id] = bool(signal_level)
        return True


class NoWait:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += seconds


angles = st.floats(-np.pi, np.pi, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(st.tuples(angles, angles, angles), st.floats(0.0, np.pi))
def test_axis_angle_round_trip_matches_geometry(
    axis: tuple[float, float, float], angle: float
) -> None:
    if np.linalg.norm(axis) < 1e-3:
        axis = (0.0, 0.0, 1.0)
    rot = rotation_from_axis_angle(axis, angle)
    vec = axis_angle_from_rotation(rot)
    assert np.linalg.norm(vec) == pytest.approx(angle, abs=1e-6)
    assert rotation_angle(rotation_from_ur_vector(vec).T @ rot) < 1e-6


@pytest.mark.parametrize(
    "vec",
    [
        [0, 0, 0],
        [np.pi, 0, 0],
        [0, np.pi, 0],
        [0.3, -1.2, 0.5],
        [2.0, 2.0, 0.5],
        [0, 0, -np.pi + 1e-9],
    ],
)
def test_rotation_vectors_agree_with_opencv_rodrigues(vec: list[float]) -> None:
    rot = rotation_from_ur_vector(vec)
    expected, _ = cv2.Rodrigues(np.asarray(vec, np.float64))
    assert np.allclose(rot, expected, atol=1e-9)
    back, _ = cv2.Rodrigues(rot)
    assert (
        rotation_angle(
            rotation_from_ur_vector(axis_angle_from_rotation(rot)).T
            @ rotation_from_ur_vector(back.ravel())
        )
        < 1e-6
    )


def test_pose_conversion_round_trip_and_bad_input() -> None:
    pose = transform_from_xyz_rpy([0.4, -0.1, 0.3], [np.pi, 0.1, -0.4])
    assert np.allclose(pose_from_ur(ur_from_pose(pose)), pose, atol=1e-9)
    with pytest.raises(DeviceError, match="6 finite numbers"):
        pose_from_ur([0.0, 1.0, 2.0])


def test_robot_moves_through_moveL_and_reads_getActualTCPPose() -> None:
    fake = FakeUR()
    robot = URRobot(fake, fake, speed_m_s=0.1, acceleration_m_s2=0.5)
    assert isinstance(robot, Robot)
    target = transform_from_xyz_rpy([0.4, 0.1, 0.3], [np.pi, 0.0, 0.2])
    robot.move_linear(target)
    name, (pose, speed, accel) = fake.calls[-1]
    assert (name, speed, accel) == ("moveL", 0.1, 0.5)
    assert np.allclose(pose_from_ur(pose), target)
    assert np.allclose(robot.base_from_tool(), target, atol=1e-9)
    robot.move_linear(target, speed_m_s=0.02)
    assert fake.calls[-1][1][1] == 0.02


def test_base_frame_is_a_software_transform_before_moveL() -> None:
    fake = FakeUR()
    robot = URRobot(fake, fake)
    base_from_user = transform_from_xyz_rpy([0.1, 0.2, 0.0], [0.0, 0.0, 0.5])
    robot.set_base_frame(base_from_user)
    assert np.allclose(robot.base_frame(), base_from_user)
    user_from_tool = transform_from_xyz_rpy([0.2, 0.0, 0.3], [np.pi, 0.0, 0.0])
    robot.move_linear(user_from_tool)
    # the controller got the pose in its own base frame
    assert np.allclose(pose_from_ur(fake.tcp), base_from_user @ user_from_tool, atol=1e-9)
    assert np.allclose(robot.base_from_tool(), user_from_tool, atol=1e-9)


def test_unreachable_and_refused_moves() -> None:
    fake = FakeUR(reach_m=0.5)
    robot = URRobot(fake, fake)
    before = list(fake.tcp)
    with pytest.raises(Unreachable, match="safety limits"):
        robot.move_linear(transform_from_xyz_rpy([0.9, 0.0, 0.2], [np.pi, 0, 0]))
    assert fake.tcp == before
    assert not robot.in_workspace([0.9, 0.0, 0.2])
    assert robot.in_workspace([0.2, 0.0, 0.2])
    fake.refuse_moves = True
    with pytest.raises(DeviceError, match="moveL"):
        robot.move_linear(transform_from_xyz_rpy([0.2, 0.0, 0.2], [np.pi, 0, 0]))


def test_set_tcp_stop_and_close() -> None:
    fake = FakeUR()
    robot = URRobot(fake, fake)
    robot.set_tcp(transform_from_xyz_rpy([0.0, 0.0, 0.15], [0, 0, 0]))
    assert np.allclose(fake.tcp_offset, [0, 0, 0.15, 0, 0, 0])
    robot.stop()
    assert fake.calls[-1] == ("stopL", (10.0,))
    robot.close()
    assert not fake.connected


def test_gripper_on_a_standard_output_with_a_part_sensor() -> None:
    fake = FakeUR()
    clock = NoWait()
    gripper = URGripper(fake, fake, output=2, holding_input=5, actuation_s=0.4, clock=clock)
    assert isinstance(gripper, Gripper)
    assert gripper.close() is False  # closed on nothing: the sensor says so
    assert fake.standard_out[2] is True
    fake.digital_in[5] = True
    assert gripper.holding
    gripper.open()
    assert fake.standard_out[2] is False
    assert clock.t == pytest.approx(0.8)


def test_gripper_on_a_tool_output_without_sensor_reports_commanded_state() -> None:
    fake = FakeUR()
    gripper = URGripper(fake, fake, output=1, tool_output=True, close_level=False, clock=NoWait())
    assert gripper.close() is True
    assert fake.tool_out[1] is False
    gripper.open()
    assert fake.tool_out[1] is True
    assert not gripper.holding


def test_connect_ur_imports_ur_rtde_lazily(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = FakeUR()
    for module, cls in (
        ("rtde_control", "RTDEControlInterface"),
        ("rtde_receive", "RTDEReceiveInterface"),
        ("rtde_io", "RTDEIOInterface"),
    ):
        mod = types.ModuleType(module)
        setattr(mod, cls, lambda host, _f=fake: _f)
        monkeypatch.setitem(sys.modules, module, mod)
    devices = connect_ur("192.0.2.10", holding_input=0)
    assert np.allclose(devices.robot.base_from_tool(), pose_from_ur(fake.tcp))


def test_connect_ur_without_ur_rtde_says_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rtde_control", None)
    with pytest.raises(DeviceError, match=r"cellvision\[ur\]"):
        connect_ur("192.0.2.10")
