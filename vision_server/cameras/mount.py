"""Where a camera is, for answers in the robot's base frame: its extrinsic calibration.

A camera is either **fixed** in the cell (``base_from_camera``, the camera's pose in the
robot's base frame) or **on the tool** (``tool_from_camera``, its pose in the TCP frame; the
robot then reports its TCP pose, ``base_from_tool``, with each trigger). Poses are written
``{xyz: [x, y, z], rpy: [roll, pitch, yaw]}``: metres, and radians with
``R = Rz(yaw) Ry(pitch) Rx(roll)`` (docs/conventions.md); the camera frame is OpenCV's (x
right, y down, z along the optical axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from geometry import transform_from_xyz_rpy

__all__ = ["MOUNT_KEYS", "CameraMount"]

MOUNT_KEYS = ("base_from_camera", "tool_from_camera")
"""The keys of a camera's ``mount:`` (exactly one of them)."""


def _triple(name: str, value: object) -> tuple[float, float, float]:
    if isinstance(value, str | bytes) or not isinstance(value, list | tuple) or len(value) != 3:
        raise ValueError(f"{name} must be a list of 3 numbers, got {value!r}")
    out: list[float] = []
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int | float) or not math.isfinite(item):
            raise ValueError(f"{name} must hold finite numbers, got {value!r}")
        out.append(float(item))
    return out[0], out[1], out[2]


@dataclass(frozen=True)
class CameraMount:
    """``kind``: ``fixed`` (``pose`` is base_from_camera) or ``tool`` (``pose`` is
    tool_from_camera). ``xyz`` in metres, ``rpy`` in radians (see the module)."""

    kind: Literal["fixed", "tool"]
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]

    def __post_init__(self) -> None:
        if self.kind not in ("fixed", "tool"):
            raise ValueError(f"kind must be 'fixed' or 'tool', got {self.kind!r}")
        object.__setattr__(self, "xyz", _triple("xyz", self.xyz))
        object.__setattr__(self, "rpy", _triple("rpy", self.rpy))

    @property
    def key(self) -> str:
        """The configuration key this mount was read from."""
        return MOUNT_KEYS[0] if self.kind == "fixed" else MOUNT_KEYS[1]

    def pose(self) -> NDArray[np.float64]:
        """The 4x4 ``base_from_camera`` (fixed) or ``tool_from_camera`` (tool)."""
        return transform_from_xyz_rpy(self.xyz, self.rpy)

    def base_from_camera(self, base_from_tool: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """The camera's pose in the base frame; a tool camera needs the robot's TCP pose
        (``ValueError`` without it)."""
        if self.kind == "fixed":
            return self.pose()
        if base_from_tool is None:
            raise ValueError("the camera is on the tool: the robot's TCP pose is needed")
        result: NDArray[np.float64] = base_from_tool @ self.pose()
        return result
