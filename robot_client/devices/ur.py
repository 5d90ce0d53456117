"""Universal Robots through ur_rtde (an optional extra: ``pip install cellvision[ur]``).

Each method maps to one documented ur_rtde call:

=============================  ==========================================================
device primitive               ur_rtde
=============================  ==========================================================
``Robot.base_from_tool()``     ``RTDEReceiveInterface.getActualTCPPose()`` → [x, y, z, rx,
                               ry, rz] (metres, axis-angle rotation vector in radians)
``Robot.move_linear(pose)``    ``RTDEControlInterface.moveL(pose, speed, acceleration)``
                               (blocking; returns False when the controller refuses)
``Robot.in_workspace(p)``      ``RTDEControlInterface.isPoseWithinSafetyLimits(pose)``
``Robot.set_tcp(tool_from_tcp)`` ``RTDEControlInterface.setTcp(pose)``
``Robot.set_base_frame(m)``    none: a software transform applied before ``moveL`` and after
                               ``getActualTCPPose`` (the controller keeps its own base)
``Robot.stop()``               ``RTDEControlInterface.stopL(deceleration)``
``Gripper.open()/close()``     ``RTDEIOInterface.setStandardDigitalOut(pin, level)`` or
                               ``setToolDigitalOut(pin, level)`` (an I/O-driven gripper)
``Gripper.holding``            ``RTDEReceiveInterface.getDigitalInState(pin)`` (a part-present
                               signal wired to an input), else the commanded output
=============================  ==========================================================

ur_rtde is imported only by :func:`connect_ur`, so this module imports without it; the classes
take the interface objects, so tests drive them with a fake of the same API.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import invert_transform, make_transform, rotation_angle, rotation_from_axis_angle

from . import Camera, Clock, DeviceError, Devices, MonotonicClock, Unreachable, Vision

__all__ = [
    "URGripper",
    "URRobot",
    "axis_angle_from_rotation",
    "connect_ur",
    "pose_from_ur",
    "rotation_from_ur_vector",
    "ur_from_pose",
]

FloatArray = NDArray[np.float64]


class RTDEControl(Protocol):
    """The part of ``rtde_control.RTDEControlInterface`` we use."""

    def moveL(self, pose: list[float], speed: float, acceleration: float) -> bool: ...  # noqa: N802
    def setTcp(self, tcp_offset: list[float]) -> bool: ...  # noqa: N802
    def isPoseWithinSafetyLimits(self, pose: list[float]) -> bool: ...  # noqa: N802
    def stopL(self, a: float) -> None: ...  # noqa: N802
    def disconnect(self) -> None: ...


class RTDEReceive(Protocol):
    """The part of ``rtde_receive.RTDEReceiveInterface`` we use."""

    def getActualTCPPose(self) -> list[float]: ...  # noqa: N802
    def getDigitalInState(self, input_id: int) -> bool: ...  # noqa: N802
    def getDigitalOutState(self, output_id: int) -> bool: ...  # noqa: N802
    def disconnect(self) -> None: ...


class RTDEIO(Protocol):
    """The part of ``rtde_io.RTDEIOInterface`` we use."""

    def setStandardDigitalOut(self, output_id: int, signal_level: bool) -> bool: ...  # noqa: N802
    def setToolDigitalOut(self, output_id: int, signal_level: bool) -> bool: ...  # noqa: N802


# --- axis-angle (UR rotation vectors) ------------------------------------------------------


def rotation_from_ur_vector(rotvec: ArrayLike) -> FloatArray:
    """The rotation matrix of a UR rotation vector ``[rx, ry, rz]`` (axis * angle, radians)."""
    v = np.asarray(rotvec, np.float64).reshape(3)
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.eye(3)
    return rotation_from_axis_angle(v, angle)


def axis_angle_from_rotation(rotation: ArrayLike) -> FloatArray:
    """The rotation vector (3,) = unit axis * angle, angle in [0, pi], of a rotation (3, 3)."""
    rot = np.asarray(rotation, np.float64)
    angle = rotation_angle(rot)
    if angle < 1e-12:
        return np.zeros(3)
    skew = np.array([rot[2, 1] - rot[1, 2], rot[0, 2] - rot[2, 0], rot[1, 0] - rot[0, 1]])
    if angle < np.pi - 1e-6:
        axis = skew / (2.0 * np.sin(angle))
    else:
        # Near pi the skew part vanishes: R + I = 2 a a^T; take the best-conditioned column.
        sym = (rot + np.eye(3)) / 2.0
        k = int(np.argmax(np.diag(sym)))
        axis = sym[:, k] / np.sqrt(max(sym[k, k], 1e-300))
        if float(np.dot(axis, skew)) < 0:
            axis = -axis
    result: FloatArray = axis / np.linalg.norm(axis) * angle
    return result


def pose_from_ur(pose: Sequence[float]) -> FloatArray:
    """``[x, y, z, rx, ry, rz]`` (ur_rtde's pose) → 4x4 ``base_from_tool``."""
    values = np.asarray(pose, np.float64).reshape(-1)
    if values.shape != (6,) or not np.all(np.isfinite(values)):
        raise DeviceError(f"bad UR pose {list(pose)!r}: expected 6 finite numbers")
    return make_transform(rotation_from_ur_vector(values[3:]), values[:3])


def ur_from_pose(base_from_tool: ArrayLike) -> list[float]:
    """4x4 ``base_from_tool`` → ``[x, y, z, rx, ry, rz]`` for ur_rtde."""
    mat = np.asarray(base_from_tool, np.float64)
    if mat.shape != (4, 4) or not np.all(np.isfinite(mat)):
        raise ValueError("base_from_tool must be a finite 4x4 transform")
    return [float(v) for v in (*mat[:3, 3], *axis_angle_from_rotation(mat[:3, :3]))]


# --- devices --------------------------------------------------------------------------------


class URRobot:
    """:class:`~robot_client.devices.Robot` over ur_rtde's control and receive interfaces.

    ``speed_m_s`` / ``acceleration_m_s2`` are moveL's defaults (ur_rtde's own are 0.25 and 1.2).
    The active base frame is kept here, in software.
    """

    def __init__(
        self,
        control: RTDEControl,
        receive: RTDEReceive,
        *,
        speed_m_s: float = 0.25,
        acceleration_m_s2: float = 1.2,
    ) -> None:
        self.control, self.receive = control, receive
        self.speed_m_s, self.acceleration_m_s2 = speed_m_s, acceleration_m_s2
        self._base_from_user = np.eye(4)

    def base_from_tool(self) -> FloatArray:
        mount_from_tool = pose_from_ur(self.receive.getActualTCPPose())
        result: FloatArray = invert_transform(self._base_from_user) @ mount_from_tool
        return result

    def _mount_pose(self, base_from_tool: ArrayLike) -> list[float]:
        pose = np.asarray(base_from_tool, np.float64)
        if pose.shape != (4, 4):
            raise DeviceError("UR robot: a pose must be a 4x4 transform")
        return ur_from_pose(self._base_from_user @ pose)

    def move_linear(self, base_from_tool: ArrayLike, *, speed_m_s: float | None = None) -> None:
        speed = self.speed_m_s if speed_m_s is None else speed_m_s
        if not speed > 0:
            raise DeviceError(f"UR robot: speed_m_s must be positive, got {speed}")
        target = self._mount_pose(base_from_tool)
        if not self.control.isPoseWithinSafetyLimits(target):
            raise Unreachable(
                f"UR robot: pose {np.round(target, 4).tolist()} is outside the safety limits"
            )
        if not self.control.moveL(target, speed, self.acceleration_m_s2):
            raise DeviceError(f"UR robot: moveL to {np.round(target, 4).tolist()} failed")

    def set_base_frame(self, base_from_user: ArrayLike) -> None:
        mat = np.asarray(base_from_user, np.float64)
        if mat.shape != (4, 4) or not np.allclose(mat[3], [0, 0, 0, 1]):
            raise DeviceError("UR robot: base_from_user must be a 4x4 transform")
        self._base_from_user = mat.copy()

    def base_frame(self) -> FloatArray:
        return self._base_from_user.copy()

    def in_workspace(self, p: ArrayLike) -> bool:
        # The controller judges whole poses: ask about p with the current tool orientation.
        pose = self.base_from_tool()
        pose[:3, 3] = np.asarray(p, np.float64).reshape(3)
        return bool(self.control.isPoseWithinSafetyLimits(self._mount_pose(pose)))

    def set_tcp(self, tool_from_tcp: ArrayLike) -> None:
        """Set the TCP offset on the flange (``setTcp``)."""
        if not self.control.setTcp(ur_from_pose(tool_from_tcp)):
            raise DeviceError("UR robot: setTcp failed")

    def stop(self, deceleration_m_s2: float = 10.0) -> None:
        self.control.stopL(deceleration_m_s2)

    def close(self) -> None:
        self.control.disconnect()
        self.receive.disconnect()


class URGripper:
    """:class:`~robot_client.devices.Gripper` for a gripper driven by one digital output
    (closed when ``close_level``), with an optional part-present digital input.

    Without ``holding_input`` the gripper cannot sense a part: ``holding`` then reports the
    commanded state (closed = holding), which a missed grasp fools.
    """

    def __init__(
        self,
        io: RTDEIO,
        receive: RTDEReceive,
        *,
        output: int = 0,
        tool_output: bool = False,
        close_level: bool = True,
        holding_input: int | None = None,
        actuation_s: float = 0.5,
        clock: Clock | None = None,
    ) -> None:
        self.io, self.receive = io, receive
        self.output, self.tool_output, self.close_level = output, tool_output, close_level
        self.holding_input, self.actuation_s = holding_input, actuation_s
        self.clock: Clock = clock or MonotonicClock()
        self._closed = False

    def _set(self, level: bool) -> None:
        setter: Callable[[int, bool], bool] = (
            self.io.setToolDigitalOut if self.tool_output else self.io.setStandardDigitalOut
        )
        if not setter(self.output, level):
            raise DeviceError(f"UR gripper: setting digital output {self.output} failed")
        self.clock.sleep(self.actuation_s)

    def open(self) -> None:
        self._set(not self.close_level)
        self._closed = False

    def close(self) -> bool:
        self._set(self.close_level)
        self._closed = True
        return self.holding

    @property
    def holding(self) -> bool:
        if self.holding_input is not None:
            return bool(self.receive.getDigitalInState(self.holding_input))
        return self._closed


def connect_ur(
    host: str,
    *,
    cameras: dict[str, Camera] | None = None,
    vision: Vision | None = None,
    gripper_output: int = 0,
    gripper_tool_output: bool = False,
    holding_input: int | None = None,
    speed_m_s: float = 0.25,
) -> Devices:
    """Connect to a UR controller at ``host`` (imports ur_rtde here; DeviceError if missing)."""
    try:
        rtde_control: Any = importlib.import_module("rtde_control")
        rtde_receive: Any = importlib.import_module("rtde_receive")
        rtde_io: Any = importlib.import_module("rtde_io")
    except ImportError as exc:
        raise DeviceError(
            "the UR backend needs ur_rtde: pip install 'cellvision[ur]' (or ur-rtde)"
        ) from exc
    try:
        control = rtde_control.RTDEControlInterface(host)
        receive = rtde_receive.RTDEReceiveInterface(host)
        io = rtde_io.RTDEIOInterface(host)
    except RuntimeError as exc:
        raise DeviceError(f"cannot connect to the UR controller at {host}: {exc}") from exc
    robot = URRobot(control, receive, speed_m_s=speed_m_s)
    gripper = URGripper(
        io,
        receive,
        output=gripper_output,
        tool_output=gripper_tool_output,
        holding_input=holding_input,
    )
    return Devices(robot=robot, gripper=gripper, cameras=dict(cameras or {}), vision=vision)
