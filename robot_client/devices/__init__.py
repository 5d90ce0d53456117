"""Device primitives: the robot, its gripper, cameras and the vision client, behind small
interfaces (the paper's lowest layer). Skills use only these; backends implement them.

Frames and units (docs/conventions.md): 4x4 ``b_from_a`` transforms, metres, radians, seconds.
The robot has a *mount* base frame (``base``) and an *active* base frame that
:meth:`Robot.set_base_frame` re-sets (the paper's "set the robot's frame base", e.g. to the QR
frame after calibration). Robot poses and moves are in the active frame.

Backends: :mod:`robot_client.devices.sim` (the simulated cell, the default) and
:mod:`robot_client.devices.ur` (Universal Robots through ur_rtde, an optional extra).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import CameraIntrinsics, invert_transform

__all__ = [
    "Camera",
    "Capture",
    "Clock",
    "DeviceError",
    "Devices",
    "Gripper",
    "MonotonicClock",
    "Robot",
    "UnknownDevice",
    "Unreachable",
    "Vision",
]

FloatArray = NDArray[np.float64]


class DeviceError(RuntimeError):
    """A device could not do what it was asked (the message says which device and why)."""


class UnknownDevice(DeviceError, LookupError):
    """A device named that this robot does not have (a camera name mistyped): the caller's
    mistake, reported as a usage error by the command line, still a DeviceError for a skill."""


class Unreachable(DeviceError):
    """A move target the robot cannot reach (outside its workspace or safety limits); the
    robot did not move."""


@runtime_checkable
class Robot(Protocol):
    """An arm that moves its tool (TCP) linearly. Poses are ``base_from_tool`` in the robot's
    *active* base frame (identity = the mount; see :meth:`set_base_frame`)."""

    def base_from_tool(self) -> FloatArray:
        """The current TCP pose in the active base frame (4x4, metres)."""
        ...

    def move_linear(self, base_from_tool: ArrayLike, *, speed_m_s: float | None = None) -> None:
        """Move the TCP in a straight line to ``base_from_tool`` (active base frame); blocks
        until the move ends. Raises :class:`Unreachable` (no motion) or :class:`DeviceError`."""
        ...

    def set_base_frame(self, base_from_user: ArrayLike) -> None:
        """Make ``user`` (given in the mount base frame) the active base frame."""
        ...

    def base_frame(self) -> FloatArray:
        """The active base frame in the mount base frame (``base_from_user``)."""
        ...

    def in_workspace(self, p: ArrayLike) -> bool:
        """Whether the point ``p`` (3,), in the active base frame, is reachable."""
        ...


@runtime_checkable
class Gripper(Protocol):
    """A gripper at the TCP."""

    def open(self) -> None:
        """Open (release whatever is held); blocks until done."""
        ...

    def close(self) -> bool:
        """Close; True if something is now held."""
        ...

    @property
    def holding(self) -> bool:
        """Whether something is held (sensed, not remembered)."""
        ...


@dataclass(frozen=True, eq=False)
class Capture:
    """One capture: ``color`` uint8 (H, W) or (H, W, 3) BGR; ``depth`` uint16 millimetre
    frames (0 = no depth), empty for colour only; the camera's ``intrinsics``;
    ``base_from_camera`` at capture time in the robot's *mount* base frame, and the active
    frame ``base_from_user`` then (so ``user_from_camera`` is in the frame moves use)."""

    color: NDArray[np.uint8]
    depth: tuple[NDArray[np.uint16], ...]
    intrinsics: CameraIntrinsics
    base_from_camera: FloatArray
    base_from_user: FloatArray = field(default_factory=lambda: np.eye(4))
    camera: str = ""

    @property
    def user_from_camera(self) -> FloatArray:
        """The camera pose in the robot's active base frame at capture time."""
        result: FloatArray = invert_transform(self.base_from_user) @ self.base_from_camera
        return result


@runtime_checkable
class Camera(Protocol):
    """A camera the robot program reads directly (tool-mounted or fixed)."""

    @property
    def intrinsics(self) -> CameraIntrinsics: ...

    @property
    def tool_from_camera(self) -> FloatArray | None:
        """The camera's pose on the tool (hand-eye calibration), or None for a fixed camera."""
        ...

    def capture(self, *, depth_frames: int = 0) -> Capture:
        """One colour image and ``depth_frames`` depth images (ValueError if the camera has no
        depth and ``depth_frames`` > 0)."""
        ...


@runtime_checkable
class Vision(Protocol):
    """The vision server as the robot sees it: the blocking protocol client.

    :class:`robot_client.SyncVisionClient` is one; :class:`robot_client.devices.vision.LazyVision`
    connects on first use. Results are :class:`protocol.Result`, frames :class:`protocol.Frames`.
    """

    def ping(self, data: str = "") -> float: ...

    def list_inspections(self) -> tuple[dict[str, Any], ...]: ...

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any: ...

    def capture(self, camera: str, **kwargs: Any) -> Any: ...


class Clock(Protocol):
    """Time as skills see it: the simulated clock in the sim, the monotonic clock otherwise."""

    def now(self) -> float:
        """Seconds (any origin)."""
        ...

    def sleep(self, seconds: float) -> None: ...


class MonotonicClock:
    """Real time: :func:`time.monotonic` and :func:`time.sleep`."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


@dataclass
class Devices:
    """The devices of one robot: what skills get (tasks never see it)."""

    robot: Robot
    gripper: Gripper
    cameras: dict[str, Camera] = field(default_factory=dict)
    vision: Vision | None = None
    clock: Clock = field(default_factory=MonotonicClock)

    def camera(self, name: str) -> Camera:
        try:
            return self.cameras[name]
        except KeyError:
            known = ", ".join(sorted(self.cameras)) or "none"
            raise UnknownDevice(f"no camera {name!r} on this robot (cameras: {known})") from None

    def close(self) -> None:
        """Close what can be closed (the vision client, robot connections)."""
        for thing in (self.vision, self.robot, self.gripper):
            closer = getattr(thing, "close", None)
            if callable(closer):
                closer()
