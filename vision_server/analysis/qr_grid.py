"""A QR code's outer corners from its whole module grid, to a small fraction of a pixel and
free of the edge bias that the corner detector's outer edges carry.

Why: ``qr_pose`` takes the printed side's distance from the code's image size. The outer
corners (:func:`.qr.refine_corners`) read the side ~0.03 px short on the simulated camera,
with a view-to-view spread of ~0.02 px that does not average over frames (it depends on the
view, not on the noise): at 1.4 m that alone is ~0.5 mm along the ray (bench/calibration.py,
the decomposition table). Every module boundary of the code lies on a regular grid, and the
code has hundreds of them: their positions give the grid's origin and pitch, and whatever
moves an edge away from the dark side (blur, threshold, the camera's edge response) moves
dark-to-light and light-to-dark edges in opposite directions, which a term per polarity
absorbs.

Method: the code is rectified through the homography of its four corners (c0 top-left, c1
top-right, c2 bottom-right, c3 bottom-left; ``modules`` N across) at ``px_per_module`` samples
per module (bilinear). Along the middle of every module row (and column) the profile's
crossings of the mid-level between the code's dark and light are located, each refined to the
centroid of the profile's slope around it (on a sharp image a pixel's grey level is the area
it covers, and the linear interpolation between two pixels crosses the mid-level up to
~0.07 px from the edge depending on where the edge falls in the pixel; the slope's centroid is
exact for that area sampling and for any symmetric blur). Each crossing near a module
boundary k gives position = origin + pitch k + shear t + keystone k t + bias polarity (t: the
row or column it was measured in), fitted by least squares (twice, dropping residuals beyond 4
robust std); the shear and keystone terms take up the small projective error that the
corners' own error puts into the rectification. The corners are where the grid's k = 0 and
k = N lines meet, mapped back through the homography.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics

__all__ = ["grid_corners"]

FloatArray = NDArray[np.float64]
MIN_EDGES = 20
"""Fewer module edges than this in either direction: no grid fit (a code too small, damaged,
or the wrong ``modules``)."""


def _crossings(profile: FloatArray, level: float) -> FloatArray:
    """Sub-pixel positions (sample units) where ``profile`` crosses ``level`` (linear)."""
    above = profile > level
    i = np.flatnonzero(above[1:] != above[:-1])
    a, b = profile[i], profile[i + 1]
    result: FloatArray = i + (level - a) / (b - a)
    return result


def _edge_centroids(slope: FloatArray, crossings: FloatArray, p: int) -> FloatArray:
    """The edges near ``crossings`` (samples) of a profile, each the centroid of its absolute
    ``slope`` (``slope[i]`` = |profile[i + 1] - profile[i]|, between those samples) within
    half a module (``p`` / 2 samples) of it (see the module's docstring); by cumulative sums,
    all at once."""
    lo = np.clip(np.ceil(crossings - 0.5 * p - 0.5).astype(np.int64), 0, slope.size - 1)
    hi = np.clip(np.floor(crossings + 0.5 * p - 0.5).astype(np.int64), 0, slope.size - 1)
    mass = np.concatenate([[0.0], np.cumsum(slope)])
    moment = np.concatenate([[0.0], np.cumsum(slope * (np.arange(slope.size) + 0.5))])
    total = mass[hi + 1] - mass[lo]
    first = moment[hi + 1] - moment[lo]
    result: FloatArray = np.where(total > 0, first / np.where(total > 0, total, 1.0), crossings)
    return result


def _fit_axis(
    rect: FloatArray, n: int, p: int, margin: int, level: float, axis: int
) -> FloatArray | None:
    """The grid lines along ``axis`` (0: the x of vertical boundaries, 1: the y of horizontal
    ones) in modules: coefficients (origin, pitch, shear, keystone, polarity bias) of
    position = origin + pitch k + shear t + keystone k t + bias polarity, k the boundary's
    index and t the module row (column) it was measured in, centred. The shear and keystone
    terms take up the rectification's small projective error (from the corners' own); None
    when too few crossings lie on the grid."""
    ks: list[float] = []
    ts: list[float] = []
    pos: list[float] = []
    pol: list[float] = []
    crossings = 0
    for j in range(n):
        band = slice(int((margin + j + 0.25) * p), int((margin + j + 0.75) * p))
        profile = rect[band, :].mean(axis=0) if axis == 0 else rect[:, band].mean(axis=1)
        found = _crossings(profile, level)
        crossings += found.size
        u = _edge_centroids(np.abs(np.diff(profile)), found, p) / p - margin
        k = np.rint(u)
        # off a module boundary: noise or a damaged module
        on = (np.abs(u - k) <= 0.35) & (k >= 0) & (k <= n)
        i = found.astype(np.int64)
        rising = profile[np.minimum(i + 1, profile.size - 1)] > profile[i]
        ks.extend(k[on].tolist())
        ts.extend([j + 0.5 - 0.5 * n] * int(on.sum()))
        pos.extend(u[on].tolist())
        pol.extend(np.where(rising[on], 1.0, -1.0).tolist())
    # a wrong module count puts most crossings off the grid
    if len(ks) < MIN_EDGES or len(ks) < 0.8 * crossings:
        return None
    k_arr, t_arr = np.asarray(ks), np.asarray(ts)
    a = np.column_stack([np.ones(k_arr.size), k_arr, t_arr, k_arr * t_arr, np.asarray(pol)])
    y = np.asarray(pos)
    keep = np.ones(y.size, bool)
    solution = np.zeros(5)
    for _ in range(2):
        if int(keep.sum()) < MIN_EDGES:
            return None
        solution = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
        residual = y - a @ solution
        spread = 1.4826 * float(np.median(np.abs(residual[keep]))) + 1e-9
        keep = np.abs(residual) < 4.0 * spread
    return solution


def grid_corners(
    gray: NDArray[np.generic],
    corners_uv: FloatArray,
    modules: int,
    *,
    px_per_module: int = 8,
    intrinsics: CameraIntrinsics | None = None,
) -> FloatArray | None:
    """The code's outer corners (4, 2), c0..c3 in image pixels ``(u, v)``, from the module
    grid of the QR code with corners ``corners_uv`` (4, 2; c0..c3 as in docs/conventions.md)
    and ``modules`` modules across (17 + 4 version), in ``gray`` (H, W) grey levels. None when
    the grid is not found (see MIN_EDGES): then the caller keeps the corners.

    ``intrinsics`` with lens distortion: the code is rectified through the homography of its
    *undistorted* corners and each sample is looked up at its distorted pixel, so that the
    module lines are straight in the rectified image (issue 29: with k1 = -0.08 and the code
    half way to the image's edge, the homography of the distorted corners bent them, and the
    grid's side read short enough to put the code ~0.5 mm too far at 1 m).
    """
    if modules < 21 or (modules - 17) % 4 != 0:
        raise ValueError(f"modules must be 17 + 4 version (21, 25, ...), got {modules}")
    if px_per_module < 4:
        raise ValueError(f"px_per_module must be >= 4, got {px_per_module}")
    n, p, margin = modules, px_per_module, 1
    square = (np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float64) + margin) * p
    size = (n + 2 * margin) * p
    distorted = intrinsics is not None and intrinsics.has_distortion
    if intrinsics is not None and distorted:
        # rect -> undistorted normalised coordinates, then each sample's distorted pixel
        xy = intrinsics.undistort_pixels(np.asarray(corners_uv, np.float64))
        image_from_rect = cv2.getPerspectiveTransform(
            square.astype(np.float32), xy.astype(np.float32)
        )
        grid = np.stack(np.meshgrid(np.arange(size), np.arange(size)), axis=-1).reshape(-1, 1, 2)
        normalised = cv2.perspectiveTransform(grid.astype(np.float64), image_from_rect)
        points = np.concatenate([normalised.reshape(-1, 2), np.ones((size * size, 1))], axis=1)
        uv = intrinsics.project(points).astype(np.float32).reshape(size, size, 2)
        rect = cv2.remap(
            np.asarray(gray, np.float32),
            uv[..., 0],
            uv[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.float64)
    else:
        image_from_rect = cv2.getPerspectiveTransform(
            square.astype(np.float32), np.asarray(corners_uv, np.float32)
        )
        rect = cv2.warpPerspective(
            np.asarray(gray, np.float32),
            image_from_rect,
            (size, size),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        ).astype(np.float64)
    inner = rect[margin * p : (n + margin) * p, margin * p : (n + margin) * p]
    dark, light = np.percentile(inner, 10), np.percentile(inner, 90)
    if not light - dark > 10.0:
        return None
    level = 0.5 * float(dark + light)
    fits = [_fit_axis(rect, n, p, margin, level, axis) for axis in (0, 1)]
    if fits[0] is None or fits[1] is None:
        return None
    fx, fy = fits[0], fits[1]
    if not (0.9 < fx[1] < 1.1 and 0.9 < fy[1] < 1.1):
        return None

    def line(f: FloatArray, k: float, t: float) -> float:
        return float(f[0] + f[1] * k + f[2] * t + f[3] * k * t)

    # each corner where its two boundary lines meet: x of the vertical boundary k = 0 or N at
    # row coordinate t, y of the horizontal one at column coordinate s (one fixed-point step
    # from the square's corner is plenty: the shear terms are ~1e-3)
    rect_corners = []
    for kx, ky in ((0, 0), (n, 0), (n, n), (0, n)):
        x = line(fx, kx, ky - 0.5 * n)
        y = line(fy, ky, kx - 0.5 * n)
        x = line(fx, kx, y - 0.5 * n)
        y = line(fy, ky, x - 0.5 * n)
        rect_corners.append([x, y])
    rect_corners_arr = (np.asarray(rect_corners) + margin) * p
    image = cv2.perspectiveTransform(rect_corners_arr.reshape(-1, 1, 2), image_from_rect)
    result: FloatArray = np.asarray(image.reshape(-1, 2), np.float64)
    if intrinsics is not None and distorted:
        result = intrinsics.project(np.concatenate([result, np.ones((4, 1))], axis=1))
    return result
