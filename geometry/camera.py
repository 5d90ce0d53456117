"""Pinhole camera with Brown-Conrady distortion (OpenCV's model).

Frames and units (docs/conventions.md): points in the camera frame (x right, y down, z forward
along the optical axis) in metres; pixels as ``(u, v)`` = (column, row) floats, the centre of the
top-left pixel at ``(0, 0)``; distortion coefficients ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["CameraIntrinsics"]

FloatArray = NDArray[np.float64]


def _points(arr: ArrayLike, name: str, dim: int) -> FloatArray:
    out = np.asarray(arr, dtype=np.float64)
    if out.ndim == 1 and out.shape == (dim,):
        out = out[None, :]
    if out.ndim != 2 or out.shape[1] != dim:
        raise ValueError(f"{name} must have shape (N, {dim}), got {np.shape(arr)}")
    return out


@dataclass(frozen=True)
class CameraIntrinsics:
    """Intrinsics of a pinhole camera with OpenCV distortion.

    width, height: image size in pixels. fx, fy: focal lengths in pixels. cx, cy: principal
    point in pixels. dist: ``(k1, k2, p1, p2, k3)``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value <= 0:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        for name in ("cx", "cy"):
            if not np.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be finite, got {getattr(self, name)!r}")
        dist = tuple(float(d) for d in self.dist)
        if len(dist) != 5 or not all(np.isfinite(dist)):
            raise ValueError(
                f"dist must be 5 finite numbers (k1, k2, p1, p2, k3), got {self.dist!r}"
            )
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))

    @property
    def matrix(self) -> FloatArray:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(d != 0.0 for d in self.dist)

    def distort_normalized(self, xy: ArrayLike) -> FloatArray:
        """Apply the distortion to normalized coordinates ``(x/z, y/z)`` (N, 2) -> (N, 2)."""
        p = _points(xy, "xy", 2)
        k1, k2, p1, p2, k3 = self.dist
        x, y = p[:, 0], p[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, p_camera: ArrayLike) -> FloatArray:
        """Project points ``p_camera`` (N, 3) in metres to pixels ``uv`` (N, 2), with distortion.

        Points with z <= 0 (behind the camera) give NaN.
        """
        p = _points(p_camera, "p_camera", 3)
        z = p[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / z[:, None]
        xy[z <= 0] = np.nan
        xd = self.distort_normalized(xy)
        return np.stack([self.fx * xd[:, 0] + self.cx, self.fy * xd[:, 1] + self.cy], axis=1)

    def undistort_pixels(self, uv: ArrayLike, *, iterations: int = 20) -> FloatArray:
        """Undistorted normalized coordinates (N, 2) of pixels ``uv`` (N, 2).

        Fixed-point iteration like ``cv2.undistortPoints`` (with more iterations by default, so
        it converges further for strong distortion).
        """
        p = _points(uv, "uv", 2)
        if iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {iterations}")
        xd = (p[:, 0] - self.cx) / self.fx
        yd = (p[:, 1] - self.cy) / self.fy
        if not self.has_distortion:
            return np.stack([xd, yd], axis=1)
        k1, k2, p1, p2, k3 = self.dist
        x, y = xd.copy(), yd.copy()
        for _ in range(iterations):
            r2 = x * x + y * y
            icdist = 1.0 / (1.0 + r2 * (k1 + r2 * (k2 + r2 * k3)))
            dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            x = (xd - dx) * icdist
            y = (yd - dy) * icdist
        return np.stack([x, y], axis=1)

    def pixel_rays(self, uv: ArrayLike) -> FloatArray:
        """Unit direction vectors (N, 3) in the camera frame of the rays through pixels ``uv``."""
        xy = self.undistort_pixels(uv)
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        result: FloatArray = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        return result

    def backproject(self, uv: ArrayLike, depth_m: ArrayLike) -> FloatArray:
        """Points ``p_camera`` (N, 3) in metres at pixels ``uv`` (N, 2) with z-depth ``depth_m``.

        ``depth_m`` (N,) or scalar is the distance along the optical axis (z), not along the ray,
        as depth cameras report it.
        """
        xy = self.undistort_pixels(uv)
        z = np.broadcast_to(np.asarray(depth_m, dtype=np.float64), (xy.shape[0],))
        return np.stack([xy[:, 0] * z, xy[:, 1] * z, z], axis=1)

    def scaled(self, factor: float) -> CameraIntrinsics:
        """The same camera at ``factor`` times the resolution (pixel-centre convention kept)."""
        if not factor > 0:
            raise ValueError(f"factor must be positive, got {factor}")
        return CameraIntrinsics(
            width=round(self.width * factor),
            height=round(self.height * factor),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
            dist=self.dist,
        )
