"""The centres of a QR code's three finder patterns, to a small fraction of a pixel, free of the
edge bias that the code's outer corners carry.

Why: ``qr_pose`` takes the printed side's distance from the code's image size. The outer
corners (:func:`.qr.refine_corners`) read that size short by ~0.03 px on the simulated camera,
with a view-to-view spread of ~0.02 px that does not average over frames (it depends on the
view, not on the noise): at 1.4 m that alone is ~0.5 mm along the ray (bench/calibration.py,
the decomposition table). A finder pattern is symmetric about its centre (dark 1, light 1,
dark 3, light 1, dark 1 modules across, both ways), so the mean of its six edge crossings
along a line through its core is its centre whatever the blur, the threshold or the camera's
edge response, which move each crossing by the same amount away from the dark and so cancel
in pairs. The distances between the three centres, (N - 7) modules of the printed code, then
give its image size without the corners' bias.

Method: the code is rectified through the homography of its four corners (c0 top-left, c1
top-right, c2 bottom-right, c3 bottom-left; ``modules`` N across) at ``px_per_module``
samples per module (bilinear); for each finder, the profile along x averaged over the rows of
its 3-module core (and along y over its columns) must cross the mid-level between its dark
and light exactly six times within the finder and its 1-module light border; the centre is the
crossings' mean, mapped back through the homography (the corners' small error only distorts
the rectification locally by an affine map to first order, which keeps the centre of a
symmetric pattern).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["FINDER_ORIGINS", "finder_centres"]

FloatArray = NDArray[np.float64]

FINDER_ORIGINS = ("top-left", "top-right", "bottom-left")
"""The order of :func:`finder_centres`' rows: the finders at c0, c1 and c3."""


def _crossings(profile: FloatArray, level: float) -> FloatArray:
    """Sub-pixel positions (sample units) where ``profile`` crosses ``level`` (linear)."""
    above = profile > level
    i = np.flatnonzero(above[1:] != above[:-1])
    a, b = profile[i], profile[i + 1]
    result: FloatArray = i + (level - a) / (b - a)
    return result


# Bands across a finder (in modules from its edge, inset from the module boundaries) and the
# crossings a line through each band must show: the outer ring (0 and 7), the light ring
# (0, 1, 6, 7) and the core (0, 1, 2, 5, 6, 7). Every band is symmetric about the centre, so
# each band's mean crossing is the centre; all of them together use the whole finder.
_BANDS = (((0.2, 0.8), 2), ((1.2, 1.8), 4), ((2.2, 4.8), 6), ((5.2, 5.8), 4), ((6.2, 6.8), 2))


def _centre(box: FloatArray, p: int, dark: float, light: float, axis: int) -> float | None:
    """The finder's centre along ``axis`` (0: x, 1: y) of the rectified ``box`` (8 p, 8 p),
    samples: the mean of every band's crossings, each band's profile averaged across it
    (the bands' weights: their crossings); None when a band shows a different count."""
    level = 0.5 * (dark + light)
    total = 0.0
    count = 0
    for (a, b), expected in _BANDS:
        rows = slice(int(round((a + 0.5) * p)), int(round((b + 0.5) * p)))
        profile = box[rows, :].mean(axis=0) if axis == 0 else box[:, rows].mean(axis=1)
        x = _crossings(profile, level)
        if x.size != expected:
            return None
        total += sum(_edge_centroid(profile, float(c), p) for c in x)
        count += expected
    return total / count


def _edge_centroid(profile: FloatArray, crossing: float, p: int) -> float:
    """The edge near ``crossing`` (samples) of ``profile`` as the centroid of the absolute
    slope within half a module (``p`` / 2 samples) of it. Why not the crossing itself: on a
    sharp image the grey level of a pixel is the area it covers, and the linear interpolation
    between two such pixels crosses the mid-level up to ~0.07 px from the edge, depending on
    where the edge falls within the pixel (on a code aligned with the pixel rows that does
    not average out along the edge); the slope's centroid is exact for that area sampling and
    for any symmetric blur."""
    slope = np.abs(np.diff(profile))  # slope[i] lies between samples i and i + 1
    lo = max(int(np.ceil(crossing - 0.5 * p - 0.5)), 0)
    hi = min(int(np.floor(crossing + 0.5 * p - 0.5)), slope.size - 1)
    w = slope[lo : hi + 1]
    total = float(w.sum())
    if not total > 0:
        return crossing
    return float((w * (np.arange(lo, hi + 1) + 0.5)).sum()) / total


def finder_centres(
    gray: NDArray[np.generic],
    corners_uv: FloatArray,
    modules: int,
    *,
    px_per_module: int = 8,
) -> FloatArray | None:
    """The centres (3, 2) in image pixels ``(u, v)`` of the top-left, top-right and
    bottom-left finder patterns of the QR code with corners ``corners_uv`` (4, 2; c0..c3 as
    in docs/conventions.md) and ``modules`` modules across (17 + 4 version), in ``gray``
    (H, W) grey levels. None when a finder does not show its six crossings (a code too small,
    damaged, or the wrong ``modules``): then the caller keeps the corners.
    """
    if modules < 21 or (modules - 17) % 4 != 0:
        raise ValueError(f"modules must be 17 + 4 version (21, 25, ...), got {modules}")
    n, p = modules, px_per_module
    if p < 2 or p % 2:
        raise ValueError(f"px_per_module must be even and >= 2, got {p}")
    margin = 1  # modules of quiet zone / separator kept around the finders
    square = (np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float64) + margin) * p
    image_from_rect = cv2.getPerspectiveTransform(
        square.astype(np.float32), np.asarray(corners_uv, np.float32)
    )
    size = (n + 2 * margin) * p
    rect = cv2.warpPerspective(
        np.asarray(gray, np.float32),
        image_from_rect,
        (size, size),
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    ).astype(np.float64)
    centres = []
    for ox, oy in ((0, 0), (n - 7, 0), (0, n - 7)):
        # the finder with half a module of its light border on each side; sample (i, j) of
        # the rectified image is at rectified coordinates (j, i) (OpenCV: pixel centres at
        # integers, as the corners)
        x0, y0 = (2 * (ox + margin) - 1) * p // 2, (2 * (oy + margin) - 1) * p // 2
        box = rect[y0 : y0 + 8 * p, x0 : x0 + 8 * p]
        if box.shape != (8 * p, 8 * p):
            return None
        dark, light = np.percentile(box, 10), np.percentile(box, 90)
        if not light - dark > 10.0:  # no contrast: not a finder at this place
            return None
        centre = [_centre(box, p, dark, light, axis) for axis in (0, 1)]
        if None in centre:
            return None
        centres.append([x0 + float(centre[0] or 0.0), y0 + float(centre[1] or 0.0)])
    rect_pts = np.array(centres, np.float64).reshape(-1, 1, 2)
    image = cv2.perspectiveTransform(rect_pts, image_from_rect).reshape(-1, 2)
    result: FloatArray = np.asarray(image, np.float64)
    return result
