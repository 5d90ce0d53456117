"""Flat parts of exactly known size on a plane seen straight on: ground truth for measurement.

A part is a shape on a plane ``distance_mm`` in front of a camera and perpendicular to its
optical axis (plane x right, y down, in mm, as the camera frame's). Each image pixel's
coverage by the part is the fraction of ``supersample`` x ``supersample`` sample points
inside it, every sample point mapped through the camera's lens model (distortion included)
onto the plane; then a Gaussian optical blur and camera noise. Only a window of the image is
supersampled (the part must lie inside it); the rest is the ground's grey.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics

__all__ = ["Shape", "bar", "disc", "plane_point", "render_flat_part"]

FloatArray = NDArray[np.float64]
Shape = Callable[[FloatArray, FloatArray], NDArray[np.bool_]]
"""Which plane points ``(x_mm, y_mm)`` (same-shaped arrays) the part covers."""


def bar(centre_mm: tuple[float, float], width_mm: float, angle_rad: float) -> Shape:
    """An infinitely long bar ``width_mm`` wide through ``centre_mm`` whose width runs along
    ``angle_rad`` (from plane x towards y)."""
    c, s = float(np.cos(angle_rad)), float(np.sin(angle_rad))

    def inside(x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        return np.abs((x - centre_mm[0]) * c + (y - centre_mm[1]) * s) <= width_mm / 2.0

    return inside


def disc(centre_mm: tuple[float, float], diameter_mm: float) -> Shape:
    """A disc of ``diameter_mm`` centred at ``centre_mm``."""

    def inside(x: FloatArray, y: FloatArray) -> NDArray[np.bool_]:
        return np.hypot(x - centre_mm[0], y - centre_mm[1]) <= diameter_mm / 2.0

    return inside


def plane_point(
    camera: CameraIntrinsics, distance_mm: float, uv: tuple[float, float]
) -> tuple[float, float]:
    """The plane point (mm) that image pixel ``uv`` sees."""
    x, y = camera.undistort_pixels(np.array([uv], np.float64))[0] * distance_mm
    return float(x), float(y)


def render_flat_part(
    camera: CameraIntrinsics,
    distance_mm: float,
    shape: Shape,
    window: tuple[int, int, int, int],
    *,
    ground: float = 60.0,
    part: float = 190.0,
    blur_sigma_px: float = 0.8,
    noise_sigma: float = 1.5,
    supersample: int = 6,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """A gray ``(height, width)`` image of ``shape`` (grey ``part``) on the ground (grey
    ``ground``), coverage computed in ``window`` = ``(u, v, width, height)`` pixels only."""
    u0, v0, w, h = window
    s = supersample
    grid_v, grid_u = np.mgrid[0 : h * s, 0 : w * s].astype(np.float64)
    # sample centres in image pixels (pixel centres at integers)
    us = u0 + (grid_u + 0.5) / s - 0.5
    vs = v0 + (grid_v + 0.5) / s - 0.5
    rays = camera.undistort_pixels(np.stack([us.ravel(), vs.ravel()], axis=1))
    covered = shape(rays[:, 0] * distance_mm, rays[:, 1] * distance_mm).reshape(us.shape)
    cover = covered.reshape(h, s, w, s).mean(axis=(1, 3))
    image: NDArray[np.float64] = np.full((camera.height, camera.width), ground, np.float64)
    image[v0 : v0 + h, u0 : u0 + w] += cover * (part - ground)
    if blur_sigma_px > 0:
        image = np.asarray(cv2.GaussianBlur(image, (0, 0), blur_sigma_px), np.float64)
    if noise_sigma > 0:
        image = image + np.random.default_rng(seed).normal(0.0, noise_sigma, image.shape)
    return np.asarray(np.clip(np.rint(image), 0, 255), np.uint8)
