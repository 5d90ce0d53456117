"""Positions in the robot's base frame: where a found feature is, as a pose the robot can
move its TCP to with no maths of its own (``output: {frame: base}``, docs/configuration.md).

The feature's pixel ``(u, v)`` (distorted, as found) is undistorted with the camera's
intrinsics, its ray is cast from the camera's pose in the base frame (the camera's
``mount:``; for a camera on the tool, composed with the TCP pose the robot sends with its
trigger) and met with the horizontal plane ``z = plane_z_m`` of the base frame, where the
features lie (e.g. the tops of the parts). ``offset_m`` (base frame) is added, e.g. to grasp
below a part's top; the orientation is ``tool_rpy`` (the TCP's, e.g. pointing down), the
same for every part. Metres and radians here; the line protocol writes them in each
controller's units (:mod:`vision_server.frontends.line_poses`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform, rotation_from_rpy

from ..cameras import CameraMount, Intrinsics

__all__ = ["BaseFrame"]

Matrix = NDArray[np.float64]


@dataclass(frozen=True)
class BaseFrame:
    """How a pixel becomes a base-frame pose (see the module). ``camera``: the camera's name
    (for messages); ``plane_z_m``: the features' height in the base frame; ``offset_m``:
    added to the point (base frame, metres); ``tool_rpy``: the pose's orientation (radians,
    ``R = Rz(yaw) Ry(pitch) Rx(roll)``)."""

    camera: str
    intrinsics: Intrinsics | None
    """None: a sim camera's own (its scene's); :meth:`with_intrinsics` sets them."""
    mount: CameraMount
    plane_z_m: float
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tool_rpy: tuple[float, float, float] = (np.pi, 0.0, 0.0)

    def with_intrinsics(self, intrinsics: Intrinsics | None) -> BaseFrame:
        """These settings with the camera's intrinsics when they were not configured."""
        if self.intrinsics is not None or intrinsics is None:
            return self
        return replace(self, intrinsics=intrinsics)

    @property
    def needs_tool_pose(self) -> bool:
        """The camera is on the tool: a trigger must carry the robot's TCP pose."""
        return self.mount.kind == "tool"

    def pose(self, u: float, v: float, base_from_tool: Matrix | None = None) -> Matrix | None:
        """The 4x4 base-frame pose for the feature at pixel ``(u, v)``; None when its ray
        does not reach the plane (parallel, or the plane behind the camera) or ``u``/``v``
        are not finite (nothing found). Raises ValueError for a tool camera without
        ``base_from_tool``."""
        if self.intrinsics is None or not (np.isfinite(u) and np.isfinite(v)):
            return None
        base_from_camera = self.mount.base_from_camera(base_from_tool)
        ray_camera = self.intrinsics.to_geometry().pixel_rays(np.array([[u, v]]))[0]
        direction = base_from_camera[:3, :3] @ ray_camera
        origin = base_from_camera[:3, 3]
        if abs(direction[2]) < 1e-12:
            return None
        s = (self.plane_z_m - origin[2]) / direction[2]
        if not s > 0:
            return None
        point = origin + s * direction + np.asarray(self.offset_m)
        return make_transform(rotation_from_rpy(*self.tool_rpy), point)
