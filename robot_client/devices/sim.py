"""The simulated cell as devices (the default backend), over :class:`simulation.SimCell`.

The active base frame is the sim robot's user frame (``set_user_frame``), so a calibration that
sets it is seen by the vision server's ``sim`` cameras through the shared world-state file
(``state_path``): every move, grasp and release is published there.

    devices = sim_devices("examples/scenes/grundfos_cell.yaml", state_path="/tmp/world.json")
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import CameraIntrinsics, invert_transform
from simulation import SimCell, WorkspaceError

from . import Capture, DeviceError, Devices, Unreachable, Vision

__all__ = ["SimCamera", "SimGripper", "SimRobot", "SimTime", "sim_devices"]

FloatArray = NDArray[np.float64]


class SimTime:
    """The cell's simulated clock: ``sleep`` advances simulated time (no real wait unless the
    scene's ``time_scale`` asks for it)."""

    def __init__(self, cell: SimCell) -> None:
        self.cell = cell

    def now(self) -> float:
        return self.cell.clock.now()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.cell.clock.advance(seconds)
            self.cell.publish()


class SimRobot:
    """:class:`~robot_client.devices.Robot` over the simulated arm."""

    def __init__(self, cell: SimCell) -> None:
        self.cell = cell
        self.moves = 0

    def base_from_tool(self) -> FloatArray:
        return self.cell.robot.tool_pose("user")

    def move_linear(self, base_from_tool: ArrayLike, *, speed_m_s: float | None = None) -> None:
        try:
            self.cell.robot.move_linear(base_from_tool, frame="user", speed_m_s=speed_m_s)
        except WorkspaceError as exc:
            raise Unreachable(str(exc)) from exc
        except ValueError as exc:
            raise DeviceError(f"sim robot: {exc}") from exc
        self.moves += 1

    def set_base_frame(self, base_from_user: ArrayLike) -> None:
        try:
            self.cell.robot.set_user_frame(base_from_user)
        except ValueError as exc:
            raise DeviceError(f"sim robot: {exc}") from exc

    def base_frame(self) -> FloatArray:
        return self.cell.robot.base_from_user

    def in_workspace(self, p: ArrayLike) -> bool:
        p_user = np.append(np.asarray(p, np.float64).reshape(3), 1.0)
        return self.cell.robot.in_workspace((self.cell.robot.base_from_user @ p_user)[:3])


class SimGripper:
    """:class:`~robot_client.devices.Gripper` over the simulated gripper."""

    def __init__(self, cell: SimCell) -> None:
        self.cell = cell

    def open(self) -> None:
        self.cell.gripper.release()

    def close(self) -> bool:
        self.cell.gripper.grasp()
        return self.holding

    @property
    def holding(self) -> bool:
        return self.cell.gripper.held is not None

    @property
    def held_part(self) -> str | None:
        """The name of the held part (the simulation knows; a real gripper does not)."""
        return self.cell.gripper.held


class SimCamera:
    """:class:`~robot_client.devices.Camera` over one simulated camera. A fixed camera's
    ``base_from_camera`` uses the nominal mount of the base (what the robot program was told),
    not the true docked one."""

    def __init__(
        self,
        cell: SimCell,
        name: str,
        *,
        nominal_mount: FloatArray | None = None,
        nominal_intrinsics: CameraIntrinsics | None = None,
    ) -> None:
        """``nominal_mount`` (``tool_from_camera``) and ``nominal_intrinsics``: what the robot
        program is told about a tool camera before commissioning (default: the scene's truth);
        images are always rendered with the truth."""
        self.cell = cell
        self.name = name
        self.spec = cell.scene.camera(name)
        if nominal_mount is not None and self.spec.mount != "tool":
            raise ValueError(f"camera {name!r} is fixed: a nominal mount is for a tool camera")
        self._mount = self.spec.pose.copy() if nominal_mount is None else nominal_mount.copy()
        self._intrinsics = nominal_intrinsics or self.spec.intrinsics

    @property
    def intrinsics(self) -> CameraIntrinsics:
        return self._intrinsics

    @property
    def has_depth(self) -> bool:
        return self.spec.depth is not None

    @property
    def tool_from_camera(self) -> FloatArray | None:
        return self._mount.copy() if self.spec.mount == "tool" else None

    def _base_from_camera(self) -> FloatArray:
        if self.spec.mount == "tool":
            # Where the arm says the tool is, as a real controller reports it (the image is
            # taken from the true pose, off by the arm's repeatability).
            pose: FloatArray = self.cell.robot.tool_pose("base") @ self._mount
            return pose
        nominal: FloatArray = (
            invert_transform(self.cell.scene.robot.world_from_base) @ self.spec.pose
        )
        return nominal

    def capture(self, *, depth_frames: int = 0) -> Capture:
        if depth_frames < 0:
            raise ValueError(f"depth_frames must be >= 0, got {depth_frames}")
        if depth_frames and not self.has_depth:
            raise ValueError(f"camera {self.name!r} has no depth sensor")
        base_from_camera = self._base_from_camera()
        base_from_user = self.cell.robot.base_from_user
        first = self.cell.render(self.name)
        depth: list[NDArray[np.uint16]] = []
        if depth_frames:
            assert first.depth is not None
            depth.append(first.depth)
            for _ in range(depth_frames - 1):
                frame = self.cell.render(self.name)
                assert frame.depth is not None
                depth.append(frame.depth)
        return Capture(
            color=first.color,
            depth=tuple(depth),
            intrinsics=self.intrinsics,
            base_from_camera=base_from_camera,
            base_from_user=base_from_user,
            camera=self.name,
        )


def sim_devices(
    scene: str | Path | SimCell,
    *,
    seed: int | None = None,
    state_path: str | Path | None = None,
    vision: Vision | None = None,
    fresh: bool = False,
) -> Devices:
    """Devices over a simulated cell (a scene file, or a ready :class:`SimCell`): the robot,
    the gripper, every scene camera by name, and ``vision`` (None: no vision server).

    The cell continues the world in ``state_path`` if there is one; ``fresh``: it starts again
    from the scene instead, with the parts the line's other stations deliver already in place
    (:meth:`SimCell.restart`, :meth:`SimCell.deliver`), and overwrites the file."""
    cell = (
        scene
        if isinstance(scene, SimCell)
        else SimCell.from_yaml(scene, seed=seed, state_path=state_path)
    )
    if fresh:
        cell.restart()
        cell.deliver()
    cameras = {spec.name: SimCamera(cell, spec.name) for spec in cell.scene.cameras}
    return Devices(
        robot=SimRobot(cell),
        gripper=SimGripper(cell),
        cameras=dict(cameras),
        vision=vision,
        clock=SimTime(cell),
    )
