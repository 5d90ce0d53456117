"""The simulated arm, its gripper and the simulated clock.

Frames: ``world`` (the cell, ground truth), ``base`` (the arm's base, mounted at
``world_from_base``; a mobile robot docks with some error, so the robot does not know it),
``tool`` (TCP, z along the approach direction) and ``user`` (a frame the robot program sets,
e.g. the QR frame after calibration: ``base_from_user``). Metres, radians, seconds.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import (
    invert_transform,
    make_transform,
    rotation_angle,
    rotation_from_axis_angle,
    rotation_from_rpy,
    transform_from_xyz_rpy,
)
from simulation.scene import RobotSpec, Scene
from simulation.world import World

__all__ = ["Gripper", "SimClock", "SimRobot", "WorkspaceError", "support_below"]

FloatArray = NDArray[np.float64]


class WorkspaceError(ValueError):
    """A move target outside the robot's workspace; the robot does not move."""


class SimClock:
    """Simulated time in seconds. ``time_scale`` 0 never waits; k > 0 sleeps dt / k per step."""

    def __init__(self, world: World, time_scale: float = 0.0) -> None:
        self._world = world
        self.time_scale = time_scale

    def now(self) -> float:
        return self._world.time_s

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError(f"dt must be >= 0, got {dt}")
        self._world.time_s += dt
        if self.time_scale > 0 and dt > 0:
            time.sleep(dt / self.time_scale)


def _as_pose(pose: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be a finite 4x4 transform")
    rot = arr[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise ValueError(f"{name} must have a proper rotation part")
    return arr


class SimRobot:
    """A Cartesian arm that moves its tool linearly at ``speed_m_s`` in simulated time.

    With the scene's ``repeatability``, a move ends a random few hundredths of a millimetre
    from its target while the arm reports the target, as a real arm's encoders do: the world
    (what cameras see, what the gripper grasps) has the true pose, :meth:`tool_pose` the
    reported one. ``rng`` draws these errors (default: a fixed seed)."""

    def __init__(
        self,
        spec: RobotSpec,
        world: World,
        clock: SimClock,
        on_change: Callable[[], None] = lambda: None,
        *,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.spec = spec
        self._world = world
        self._clock = clock
        self._on_change = on_change
        self._rng = rng if rng is not None else np.random.default_rng(0)
        # (true pose, reported pose) of the last move; the report holds while the world's
        # tool is still at that true pose (a restart or another process moves it elsewhere).
        self._last_move: tuple[FloatArray, FloatArray] | None = None

    # --- poses --------------------------------------------------------------------------
    @property
    def world_from_base(self) -> FloatArray:
        """Ground truth mount of the arm (the robot itself does not know it)."""
        return self._world.world_from_base.copy()

    @property
    def base_from_user(self) -> FloatArray:
        return self._world.base_from_user.copy()

    def set_user_frame(self, base_from_user: ArrayLike) -> None:
        """Set the frame in which ``frame='user'`` poses are given (calibration sets it)."""
        self._world.base_from_user = _as_pose(base_from_user, "base_from_user").copy()
        self._world.version += 1
        self._on_change()

    def _reported(self) -> FloatArray:
        true = self._world.base_from_tool
        if self._last_move is not None and np.array_equal(self._last_move[0], true):
            return self._last_move[1].copy()
        return true.copy()

    def tool_pose(self, frame: str = "base") -> FloatArray:
        """``base_from_tool`` (frame='base') or ``user_from_tool`` (frame='user') as the arm
        reports it (off the true pose by its repeatability, if the scene gives one)."""
        if frame == "base":
            return self._reported()
        if frame == "user":
            return invert_transform(self._world.base_from_user) @ self._reported()
        raise ValueError(f"frame must be 'base' or 'user', got {frame!r}")

    def _arrival(self, target: FloatArray) -> FloatArray:
        """Where a move to ``target`` truly ends (the repeatability's random error)."""
        if self.spec.repeatability_m <= 0 and self.spec.repeatability_rad <= 0:
            return target.copy()
        axis = self._rng.normal(size=3)
        angle = float(self._rng.normal(0.0, self.spec.repeatability_rad))
        turn = rotation_from_axis_angle(axis / np.linalg.norm(axis), angle)
        shift = self._rng.normal(0.0, self.spec.repeatability_m, 3)
        return make_transform(turn @ target[:3, :3], target[:3, 3] + shift)

    def in_workspace(self, p_base: ArrayLike) -> bool:
        p = np.asarray(p_base, dtype=np.float64)
        lo, hi = np.array(self.spec.workspace_min), np.array(self.spec.workspace_max)
        return bool(np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9))

    # --- motion -------------------------------------------------------------------------
    def move_linear(
        self, target: ArrayLike, *, frame: str = "base", speed_m_s: float | None = None
    ) -> float:
        """Move the tool in a straight line to ``target`` (base_from_tool or user_from_tool).

        The workspace is a box, so a straight move between two points inside it stays inside.
        Returns the duration in simulated seconds; raises :class:`WorkspaceError` (and does not
        move) when the target lies outside the workspace.
        """
        pose = _as_pose(target, "target")
        if frame == "user":
            pose = self._world.base_from_user @ pose
        elif frame != "base":
            raise ValueError(f"frame must be 'base' or 'user', got {frame!r}")
        speed = self.spec.speed_m_s if speed_m_s is None else speed_m_s
        if not speed > 0:
            raise ValueError(f"speed_m_s must be positive, got {speed_m_s}")
        if not self.in_workspace(pose[:3, 3]):
            raise WorkspaceError(
                f"target position {np.round(pose[:3, 3], 4).tolist()} (base frame) is outside "
                f"the workspace {self.spec.workspace_min}..{self.spec.workspace_max}"
            )
        current = self._world.base_from_tool
        distance = float(np.linalg.norm(pose[:3, 3] - current[:3, 3]))
        angle = rotation_angle(current[:3, :3].T @ pose[:3, :3])
        duration = max(distance / speed, angle / self.spec.angular_speed_rad_s)
        self._clock.advance(duration)
        true = self._arrival(pose)
        self._world.base_from_tool = true
        self._last_move = (true.copy(), pose.copy())
        self._world.version += 1
        self._on_change()
        return duration

    def dock(self, rng: np.random.Generator) -> FloatArray:
        """Re-mount the base as a mobile robot arriving at the cell: the nominal
        ``world_from_base`` with a random docking error (scene ``robot.docking_error``).
        Returns the new ground-truth ``world_from_base``."""
        dx, dy = rng.uniform(-1.0, 1.0, size=2) * self.spec.docking_error_xy_m
        dyaw = float(rng.uniform(-1.0, 1.0)) * self.spec.docking_error_yaw
        error = make_transform(rotation_from_rpy(0.0, 0.0, dyaw), [dx, dy, 0.0])
        self._world.world_from_base = self.spec.world_from_base @ error
        self._world.version += 1
        self._on_change()
        return self.world_from_base


def support_below(scene: Scene, p_world: ArrayLike) -> tuple[str, float]:
    """The highest support (surface, bin floor, box top) under ``p_world`` and no higher than
    it (+5 mm); returns (name, top height in metres), ('', 0.0) if there is none."""
    p = np.asarray(p_world, dtype=np.float64)
    best = ("", 0.0)
    best_z = -np.inf
    candidates: list[tuple[str, FloatArray, float, float, float]] = []
    for s in scene.surfaces:
        candidates.append((s.name, s.world_from_surface, s.size[0], s.size[1], 0.0))
    for b in scene.bins:
        candidates.append((b.name, b.world_from_bin, b.size[0], b.size[1], b.wall_m))
    for box in scene.boxes:
        candidates.append((box.name, box.world_from_box, box.size[0], box.size[1], box.size[2]))
    for name, pose, sx, sy, top in candidates:
        local = invert_transform(pose) @ np.append(p, 1.0)
        z = float((pose @ np.array([0.0, 0.0, top, 1.0]))[2])
        inside = abs(local[0]) <= sx / 2 and abs(local[1]) <= sy / 2
        if inside and z <= p[2] + 0.005 and z > best_z:
            best, best_z = (name, z), z
    return best


class Gripper:
    """A parallel gripper at the TCP. A grasp succeeds only if a free part's grasp point lies
    within the tolerances of the TCP; the held part then moves with the tool."""

    def __init__(
        self,
        scene: Scene,
        world: World,
        clock: SimClock,
        on_change: Callable[[], None] = lambda: None,
        actuation_s: float = 0.3,
    ) -> None:
        self.scene = scene
        self._world = world
        self._clock = clock
        self._on_change = on_change
        self.actuation_s = actuation_s

    @property
    def held(self) -> str | None:
        return self._world.held_part()

    def grasp_point(self, name: str) -> FloatArray:
        """The grasp point of part ``name`` in the world frame."""
        spec = self.scene.part(name)
        local = np.array([0.0, 0.0, spec.top_height - spec.grasp_depth_m, 1.0])
        result: FloatArray = (self._world.part_pose(name) @ local)[:3]
        return result

    def grasp(self) -> str | None:
        """Close the gripper; the name of the part now held, or None (nothing within tolerance)."""
        self._clock.advance(self.actuation_s)
        if self.held is not None:
            return None
        world_from_tool = self._world.world_from_tool()
        tcp = world_from_tool[:3, 3]
        tol = self.scene.robot.gripper
        best: tuple[float, str] | None = None
        for name, state in self._world.parts.items():
            delta = self.grasp_point(name) - tcp
            lateral = float(np.hypot(delta[0], delta[1]))
            if (
                lateral <= tol.tolerance_xy_m
                and abs(delta[2]) <= tol.tolerance_z_m
                and (best is None or lateral < best[0])
            ):
                best = (lateral, name)
            del state
        if best is None:
            return None
        name = best[1]
        state = self._world.parts[name]
        state.tool_from_part = invert_transform(world_from_tool) @ state.world_from_part
        state.held = True
        state.location = ""
        self._world.version += 1
        self._on_change()
        return name

    def release(self) -> str | None:
        """Open the gripper: the held part drops upright onto the support below it (keeping its
        x, y and yaw); returns its name, or None if nothing was held."""
        self._clock.advance(self.actuation_s)
        name = self.held
        if name is None:
            return None
        state = self._world.parts[name]
        pose = self._world.part_pose(name)
        support, z = support_below(self.scene, pose[:3, 3])
        yaw = float(np.arctan2(pose[1, 0], pose[0, 0]))
        state.world_from_part = transform_from_xyz_rpy([pose[0, 3], pose[1, 3], z], [0, 0, yaw])
        state.held = False
        state.tool_from_part = None
        state.location = support
        self._world.version += 1
        self._on_change()
        return name

    place = release
