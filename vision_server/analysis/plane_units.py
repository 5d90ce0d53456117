"""Units of a measurement: image pixels, or millimetres on the measuring plane.

A calibration maps image pixels ``(u, v)`` (centre of the top-left pixel at ``(0, 0)``) to
points of the measuring plane in its unit, so that every length, diameter and distance is
computed between mapped points and comes out in that unit:

- :class:`PixelUnits`: identity, unit ``px``.
- :class:`ScaleUnits`: a scale taken from a reference of known size (``mm_per_px``), unit
  ``mm``; for a lens without distortion looking straight at the plane.
- :class:`PlaneUnits`: the camera's intrinsics (with distortion) and the distance of the plane
  from the camera along its optical axis, the camera looking perpendicular at it: a pixel is
  undistorted to the normalised ray ``(x, y)`` and meets the plane at ``Z (x, y)``, in mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics

__all__ = ["PixelUnits", "PlaneUnits", "ScaleUnits", "Units"]

FloatArray = NDArray[np.float64]


class Units(Protocol):
    @property
    def unit(self) -> str:
        """``px`` or ``mm``: the unit of the plane's coordinates."""
        ...

    def to_plane(self, points_uv: object) -> FloatArray:
        """Points ``(N, 2)`` of the image (px) on the measuring plane, in :attr:`unit`."""
        ...


@dataclass(frozen=True)
class PixelUnits:
    unit: str = "px"

    def to_plane(self, points_uv: object) -> FloatArray:
        return np.asarray(points_uv, np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class ScaleUnits:
    """``mm_per_px`` millimetres per image pixel, the same along u and v."""

    mm_per_px: float
    unit: str = "mm"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.mm_per_px) and self.mm_per_px > 0):
            raise ValueError(f"mm_per_px must be > 0, got {self.mm_per_px!r}")

    def to_plane(self, points_uv: object) -> FloatArray:
        return np.asarray(points_uv, np.float64).reshape(-1, 2) * self.mm_per_px


@dataclass(frozen=True)
class PlaneUnits:
    """A plane ``distance_mm`` in front of a camera (``camera``: its intrinsics with
    distortion), perpendicular to its optical axis. Plane coordinates are the camera frame's
    x (right) and y (down) on the plane, in mm."""

    camera: CameraIntrinsics
    distance_mm: float
    unit: str = "mm"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.distance_mm) and self.distance_mm > 0):
            raise ValueError(f"distance_mm must be > 0, got {self.distance_mm!r}")

    @property
    def mm_per_px(self) -> float:
        """The scale at the principal point (mean of u and v)."""
        return self.distance_mm * (1.0 / self.camera.fx + 1.0 / self.camera.fy) / 2.0

    def to_plane(self, points_uv: object) -> FloatArray:
        uv = np.asarray(points_uv, np.float64).reshape(-1, 2)
        if len(uv) == 0:
            return uv
        return self.camera.undistort_pixels(uv) * self.distance_mm
