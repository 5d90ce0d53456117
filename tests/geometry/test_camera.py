"""CameraIntrinsics against OpenCV's projectPoints / undistortPoints."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geometry import CameraIntrinsics

CAMERAS = [
    CameraIntrinsics(1024, 768, 1200.0, 1195.0, 515.3, 380.9, (-0.12, 0.08, 0.001, -0.0007, -0.02)),
    CameraIntrinsics(640, 480, 570.3, 570.3, 319.5, 239.5),
]


def _points_in_view(cam: CameraIntrinsics, rng: np.random.Generator, n: int) -> np.ndarray:
    z = rng.uniform(0.3, 2.0, size=n)
    x = rng.uniform(-0.35, 0.35, size=n) * z
    y = rng.uniform(-0.28, 0.28, size=n) * z
    return np.stack([x, y, z], axis=1)


@pytest.mark.parametrize("cam", CAMERAS)
def test_project_matches_cv2(cam: CameraIntrinsics) -> None:
    rng = np.random.default_rng(10)
    p = _points_in_view(cam, rng, 200)
    expected, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.matrix, np.array(cam.dist))
    np.testing.assert_allclose(cam.project(p), expected.reshape(-1, 2), atol=1e-9)


@pytest.mark.parametrize("cam", CAMERAS)
def test_undistort_matches_cv2_and_inverts_project(cam: CameraIntrinsics) -> None:
    rng = np.random.default_rng(11)
    p = _points_in_view(cam, rng, 200)
    uv = cam.project(p)
    ours = cam.undistort_pixels(uv)
    theirs = cv2.undistortPoints(
        uv.reshape(-1, 1, 2),
        cam.matrix,
        np.array(cam.dist),
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-14),
    ).reshape(-1, 2)
    np.testing.assert_allclose(ours, theirs, atol=1e-7)
    np.testing.assert_allclose(ours, p[:, :2] / p[:, 2:], atol=1e-7)


def test_rays_and_backprojection() -> None:
    cam = CAMERAS[0]
    rng = np.random.default_rng(12)
    p = _points_in_view(cam, rng, 50)
    uv = cam.project(p)
    rays = cam.pixel_rays(uv)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    np.testing.assert_allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-7)
    np.testing.assert_allclose(cam.backproject(uv, p[:, 2]), p, atol=1e-6)


def test_project_behind_camera_is_nan() -> None:
    uv = CAMERAS[1].project([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    assert np.all(np.isnan(uv[0]))
    np.testing.assert_allclose(uv[1], [319.5, 239.5])


def test_scaled_keeps_pixel_centre_convention() -> None:
    cam = CAMERAS[1]
    big = cam.scaled(2.0)
    p = np.array([[0.1, -0.05, 1.0]])
    np.testing.assert_allclose(big.project(p), (cam.project(p) + 0.5) * 2 - 0.5)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"width": 0}, "width"),
        ({"height": -3}, "height"),
        ({"fx": 0.0}, "fx"),
        ({"fy": float("nan")}, "fy"),
        ({"cx": float("inf")}, "cx"),
        ({"dist": (0.0, 0.0)}, "dist"),
    ],
)
def test_validation_names_the_argument(kwargs: dict[str, object], name: str) -> None:
    args: dict[str, object] = {
        "width": 640,
        "height": 480,
        "fx": 500.0,
        "fy": 500.0,
        "cx": 320.0,
        "cy": 240.0,
    }
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        CameraIntrinsics(**args)  # type: ignore[arg-type]


def test_bad_point_shapes() -> None:
    with pytest.raises(ValueError, match="p_camera"):
        CAMERAS[1].project(np.zeros((4, 2)))
    with pytest.raises(ValueError, match="uv"):
        CAMERAS[1].undistort_pixels(np.zeros((4, 3)))
