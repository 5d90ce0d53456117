"""Ray-plane intersection and plane fitting."""

from __future__ import annotations

import numpy as np
import pytest

from geometry import fit_plane, intersect_ray_plane


def test_intersect_ray_plane() -> None:
    p = intersect_ray_plane([0, 0, 1], [0.5, 0, -1], [0, 0, 0.2], [0, 0, 1])
    assert p is not None
    np.testing.assert_allclose(p, [0.4, 0.0, 0.2])
    # Parallel ray and a plane behind the origin give None.
    assert intersect_ray_plane([0, 0, 1], [1, 0, 0], [0, 0, 0], [0, 0, 1]) is None
    assert intersect_ray_plane([0, 0, 1], [0, 0, 1], [0, 0, 0], [0, 0, 1]) is None
    with pytest.raises(ValueError, match="direction"):
        intersect_ray_plane([0, 0, 1], [0, 0, 0], [0, 0, 0], [0, 0, 1])


def _plane_points(rng: np.random.Generator, n: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    normal = np.array([0.1, -0.2, -1.0])
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    centre = np.array([0.05, 0.02, 1.0])
    uv = rng.uniform(-0.1, 0.1, size=(n, 2))
    pts = centre + uv[:, :1] * e1 + uv[:, 1:] * e2 + rng.normal(scale=noise, size=(n, 1)) * normal
    return pts, normal


def test_least_squares_fit() -> None:
    rng = np.random.default_rng(20)
    pts, normal = _plane_points(rng, 500, 0.001)
    fit = fit_plane(pts)
    n, d, inliers, rms = fit
    assert abs(abs(n @ normal) - 1) < 1e-4
    assert d > 0  # the normal faces the origin
    assert inliers.all()
    assert rms == pytest.approx(0.001, rel=0.15)
    np.testing.assert_allclose(pts @ n + d, 0, atol=0.005)
    assert fit.normal is n


def test_ransac_rejects_outliers() -> None:
    rng = np.random.default_rng(21)
    pts, normal = _plane_points(rng, 400, 0.0005)
    outliers = rng.uniform([-0.1, -0.1, 0.5], [0.1, 0.1, 0.9], size=(100, 3))
    allpts = np.vstack([pts, outliers, [[np.nan, 0, 1]]])
    n, _, inliers, rms = fit_plane(allpts, ransac_threshold_m=0.003, rng=np.random.default_rng(0))
    assert abs(abs(n @ normal) - 1) < 1e-4
    assert inliers[:400].mean() > 0.98
    assert inliers[400:].mean() < 0.05
    assert not inliers[-1]
    assert rms < 0.001


def test_fit_plane_validation() -> None:
    with pytest.raises(ValueError, match="points"):
        fit_plane(np.zeros((2, 3)))
    with pytest.raises(ValueError, match="ransac_threshold_m"):
        fit_plane(np.zeros((5, 3)), ransac_threshold_m=0.0)
