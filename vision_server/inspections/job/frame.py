"""The part frame a ``fixture`` step makes, and sampling an ROI given in it.

A part frame is a 2D pixel frame attached to a located feature: its origin is the feature's
position ``(u0, v0)`` in full-image pixels and its x axis points at ``angle_rad`` from the
image's +u axis towards +v (clockwise on the screen, as locate's angles); its y axis is x turned
by +90 degrees (towards +v when the angle is 0), so a part frame at angle 0 is the image's axes
moved to the feature. Units are image pixels (no scale: the camera looks at the part).

A point ``(x, y)`` of the part frame is the image point::

    u = u0 + x cos(angle) - y sin(angle)
    v = v0 + x sin(angle) + y cos(angle)

An ROI ``[x, y, width, height]`` in the part frame covers the part-frame pixel centres
``x .. x + width - 1`` and ``y .. y + height - 1``: it is sampled into a ``width`` x ``height``
image with bilinear interpolation (:func:`sample`), which is the plain crop when the frame is
at angle 0 on whole pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

Image = NDArray[Any]
Affine = NDArray[np.float64]
"""A 2x3 matrix mapping ``(x, y, 1)`` of a frame to ``(u, v)`` image pixels."""

ROI = tuple[int, int, int, int]


@dataclass(frozen=True)
class PartFrame:
    """A part frame: origin ``(u, v)`` in image pixels, x axis at ``angle_rad`` (from +u
    towards +v)."""

    u: float
    v: float
    angle_rad: float = 0.0

    def image_from_part(self) -> Affine:
        """The 2x3 matrix taking part-frame pixels to image pixels."""
        c, s = math.cos(self.angle_rad), math.sin(self.angle_rad)
        return np.array([[c, -s, self.u], [s, c, self.v]], dtype=np.float64)


IDENTITY: Affine = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def roi_transform(frame: PartFrame, roi: ROI) -> Affine:
    """The 2x3 matrix taking a pixel ``(i, j)`` of the sampled ROI to image pixels."""
    x, y = roi[0], roi[1]
    m = frame.image_from_part()
    out: Affine = m.copy()
    out[:, 2] = m[:, :2] @ np.array([x, y], dtype=np.float64) + m[:, 2]
    return out


def apply(matrix: Affine, points: Any) -> NDArray[np.float64]:
    """``points`` (N, 2) through a 2x3 matrix."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out: NDArray[np.float64] = pts @ matrix[:, :2].T + matrix[:, 2]
    return out


def outline(matrix: Affine, width: int, height: int) -> NDArray[np.float64]:
    """The four image-pixel corners of a ``width`` x ``height`` region (pixel edges, not
    centres), clockwise on the screen from its top-left."""
    corners = [(-0.5, -0.5), (width - 0.5, -0.5), (width - 0.5, height - 0.5), (-0.5, height - 0.5)]
    return apply(matrix, corners)


def inside(matrix: Affine, width: int, height: int, image_shape: tuple[int, ...]) -> bool:
    """Whether every pixel centre of the region lies in the image (no invented pixels)."""
    centres = apply(matrix, [(0, 0), (width - 1, 0), (width - 1, height - 1), (0, height - 1)])
    rows, cols = image_shape[:2]
    return bool(
        (centres[:, 0] >= -0.5).all()
        and (centres[:, 0] <= cols - 0.5).all()
        and (centres[:, 1] >= -0.5).all()
        and (centres[:, 1] <= rows - 0.5).all()
    )


def sample(image: Image, matrix: Affine, width: int, height: int) -> Image:
    """The region's pixels: ``out[j, i]`` is the image at ``matrix @ (i, j, 1)`` (bilinear;
    replicated edge for the half pixel at the image's border)."""
    out: Image = cv2.warpAffine(
        image,
        matrix,
        (width, height),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out


__all__ = [
    "IDENTITY",
    "Affine",
    "PartFrame",
    "apply",
    "inside",
    "outline",
    "roi_transform",
    "sample",
]
