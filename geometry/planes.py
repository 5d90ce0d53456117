"""Planes: ray intersection and least-squares / RANSAC fitting.

A plane is ``{p : normal . p + d = 0}`` with a unit ``normal``; all points and distances in
metres, in whatever frame the caller uses consistently.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["PlaneFit", "fit_plane", "intersect_ray_plane"]

FloatArray = NDArray[np.float64]


def _vec3(v: ArrayLike, name: str) -> FloatArray:
    arr = np.asarray(v, dtype=np.float64).reshape(-1)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be 3 finite numbers, got {v!r}")
    return arr


def intersect_ray_plane(
    origin: ArrayLike,
    direction: ArrayLike,
    plane_point: ArrayLike,
    plane_normal: ArrayLike,
    *,
    eps: float = 1e-12,
) -> FloatArray | None:
    """Point (3,) where the ray ``origin + s * direction`` (s >= 0) meets the plane, or None.

    Returns None when the ray is parallel to the plane or the plane lies behind the origin.
    All arguments are in one frame; ``direction`` and ``plane_normal`` need not be unit length.
    """
    o = _vec3(origin, "origin")
    d = _vec3(direction, "direction")
    p0 = _vec3(plane_point, "plane_point")
    n = _vec3(plane_normal, "plane_normal")
    if np.linalg.norm(d) < eps:
        raise ValueError("direction must be non-zero")
    if np.linalg.norm(n) < eps:
        raise ValueError("plane_normal must be non-zero")
    denom = float(n @ d)
    if abs(denom) < eps * np.linalg.norm(n) * np.linalg.norm(d):
        return None
    s = float(n @ (p0 - o)) / denom
    if s < 0:
        return None
    result: FloatArray = o + s * d
    return result


class PlaneFit(tuple[FloatArray, float, NDArray[np.bool_], float]):
    """Result of :func:`fit_plane`: ``(normal, d, inliers, rms)``; a tuple, so it unpacks."""

    __slots__ = ()

    @property
    def normal(self) -> FloatArray:
        return self[0]

    @property
    def d(self) -> float:
        return self[1]

    @property
    def inliers(self) -> NDArray[np.bool_]:
        return self[2]

    @property
    def rms(self) -> float:
        return self[3]


def _least_squares(points: FloatArray) -> tuple[FloatArray, float]:
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    normal = vt[2]
    return normal, -float(normal @ centroid)


def fit_plane(
    points: ArrayLike,
    *,
    ransac_threshold_m: float | None = None,
    ransac_iterations: int = 200,
    rng: np.random.Generator | None = None,
) -> PlaneFit:
    """Fit a plane to ``points`` (N, 3), N >= 3.

    Without ``ransac_threshold_m``: total least squares over all points. With it: RANSAC over
    3-point samples (``ransac_iterations`` draws from ``rng``, default seeded 0 for
    reproducibility), inliers within the threshold (metres), then least squares on the inliers.

    Returns ``(normal, d, inliers, rms)``: a unit normal (3,) oriented towards the frame's
    origin (so ``d >= 0``; for points in a camera frame it faces the camera); ``d`` such that
    ``normal . p + d = 0`` (metres, the origin's distance to the plane); a boolean mask (N,) of
    the points used (inliers; non-finite points are never inliers); and the RMS point-to-plane
    distance of the inliers in metres.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    finite = np.all(np.isfinite(pts), axis=1)
    if int(finite.sum()) < 3:
        raise ValueError("points must contain at least 3 finite points")
    if ransac_threshold_m is not None and not ransac_threshold_m > 0:
        raise ValueError(f"ransac_threshold_m must be positive, got {ransac_threshold_m}")
    if ransac_iterations < 1:
        raise ValueError(f"ransac_iterations must be >= 1, got {ransac_iterations}")

    inliers = finite.copy()
    if ransac_threshold_m is not None:
        gen = rng if rng is not None else np.random.default_rng(0)
        idx = np.flatnonzero(finite)
        good = pts[idx]
        samples = gen.integers(0, idx.size, size=(ransac_iterations, 3))
        a, b, c = good[samples[:, 0]], good[samples[:, 1]], good[samples[:, 2]]
        normals = np.cross(b - a, c - a)
        norms = np.linalg.norm(normals, axis=1)
        ok = norms > 1e-12
        best_count = -1
        best_mask = finite
        for k in np.flatnonzero(ok):
            n = normals[k] / norms[k]
            dist = np.abs((good - a[k]) @ n)
            mask = dist <= ransac_threshold_m
            count = int(mask.sum())
            if count > best_count:
                best_count = count
                best_mask = np.zeros_like(finite)
                best_mask[idx[mask]] = True
        if best_count >= 3:
            inliers = best_mask
            # One refit and re-selection step tightens the consensus set.
            normal, d = _least_squares(pts[inliers])
            refined = finite & (np.abs(pts @ normal + d) <= ransac_threshold_m)
            if int(refined.sum()) >= 3:
                inliers = refined

    normal, d = _least_squares(pts[inliers])
    if d < 0:
        normal, d = -normal, -d
    residuals = pts[inliers] @ normal + d
    rms = float(np.sqrt(np.mean(residuals**2)))
    return PlaneFit((normal, d, inliers, rms))
