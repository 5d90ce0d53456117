"""qr_pose on the simulated cell's RGB-D camera (Xtion-like depth noise) with ground truth."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from geometry import invert_transform, rotation_angle
from vision_server.analysis import BadImageError, DepthError, NotFoundError, QRPose, qr_pose

from .conftest import qr_cell, random_view

SIDE = 0.16


def _views(n: int, seed: int, **cell_kw: Any) -> list[tuple[Any, list[Any]]]:
    cell = qr_cell(5, **cell_kw)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        cell.world.base_from_tool = random_view(rng)
        frames = [cell.render("rgbd") for _ in range(5)]
        out.append((frames[0], [f.depth for f in frames]))
    return out


def _errors(pose: QRPose, camera_from_qr: np.ndarray, k: int) -> tuple[float, float, float]:
    e = invert_transform(camera_from_qr) @ pose.camera_from_qr
    p_qr = np.array([0.5 * np.cos(k), 0.5 * np.sin(k), 0.0, 1.0])  # 0.5 m from the code
    p_err = np.linalg.norm((pose.camera_from_qr - camera_from_qr) @ p_qr)
    return float(np.linalg.norm(e[:3, 3])), float(np.degrees(rotation_angle(e[:3, :3]))), p_err


@pytest.fixture(scope="module")
def views() -> list[tuple[Any, list[Any]]]:
    return _views(16, seed=3)


def test_plane_method_meets_the_accuracy_target(views: list[tuple[Any, list[Any]]]) -> None:
    errs = []
    for k, (frame, depth) in enumerate(views):
        truth = frame.truth.qr_codes["qr"]
        pose = qr_pose(frame.color, depth, frame.truth.intrinsics, side_m=SIDE)
        assert pose.text == "cellvision:station-1"
        assert pose.method == "plane"
        assert pose.camera_from_qr.shape == (4, 4)
        np.testing.assert_allclose(pose.corners_uv, truth.corners_uv, atol=0.4)
        np.testing.assert_allclose(pose.quality.side_lengths_m, SIDE, rtol=0.01)
        assert pose.quality.frames == 5
        assert pose.quality.valid_depth_fraction > 0.9
        assert pose.quality.inlier_fraction > 0.9
        assert pose.quality.plane_rms_m < 0.006
        errs.append(_errors(pose, truth.camera_from_qr, k))
    t, r, p = np.array(errs).T
    assert np.percentile(t, 95) <= 0.0005
    assert np.percentile(r, 95) <= 0.2
    assert np.percentile(p, 95) <= 0.002


def test_corners_method_is_the_papers(views: list[tuple[Any, list[Any]]]) -> None:
    errs = []
    for k, (frame, depth) in enumerate(views[:8]):
        truth = frame.truth.qr_codes["qr"]
        pose = qr_pose(frame.color, depth, frame.truth.intrinsics, method="corners")
        assert pose.method == "corners"
        assert np.all(pose.quality.corner_depth_std_m < 0.01)
        assert np.isnan(pose.quality.plane_rms_m)
        # eq 4: the origin is the mean of the corners
        np.testing.assert_allclose(pose.camera_from_qr[:3, 3], pose.corners_camera.mean(axis=0))
        errs.append(_errors(pose, truth.camera_from_qr, k))
    t, r, _ = np.array(errs).T
    # nine noisy depth pixels per corner: millimetres, tenths of degrees
    assert np.percentile(t, 95) <= 0.002
    assert np.percentile(r, 95) <= 1.0


def test_side_length_corrects_depth_scale_bias() -> None:
    errs_depth, errs_side = [], []
    for k, (frame, depth) in enumerate(_views(4, seed=9, scale_bias=0.01)):
        truth = frame.truth.qr_codes["qr"]
        intr = frame.truth.intrinsics
        biased = qr_pose(frame.color, depth, intr)
        fixed = qr_pose(frame.color, depth, intr, side_m=SIDE)
        assert fixed.quality.scale == pytest.approx(1 / 1.01, abs=0.002)
        errs_depth.append(_errors(biased, truth.camera_from_qr, k)[0])
        errs_side.append(_errors(fixed, truth.camera_from_qr, k)[0])
    assert min(errs_depth) > 0.006  # 1 % of about a metre
    assert max(errs_side) < 0.002


def test_given_corners_and_typed_failures(views: list[tuple[Any, list[Any]]]) -> None:
    frame, depth = views[0]
    intr = frame.truth.intrinsics
    truth = frame.truth.qr_codes["qr"]
    pose = qr_pose(None, depth, intr, corners=truth.corners_uv, expect="cellvision:station-1")
    assert pose.text == "cellvision:station-1"
    one = qr_pose(frame.color, depth[0], intr)  # a single (H, W) depth frame
    assert one.quality.frames == 1

    holed = [d.copy() for d in depth]
    u, v = np.rint(truth.corners_uv[2]).astype(int)
    for d in holed:
        d[v - 3 : v + 4, u - 3 : u + 4] = 0
    with pytest.raises(DepthError, match="c2"):
        qr_pose(frame.color, holed, intr, method="corners")
    qr_pose(frame.color, holed, intr)  # the plane does not need depth at the corners
    with pytest.raises(DepthError, match="too few valid depth"):
        qr_pose(frame.color, [np.zeros_like(d) for d in depth], intr)
    with pytest.raises(DepthError, match="degenerate"):
        qr_pose(None, depth, intr, corners=np.tile(truth.corners_uv[:1], (4, 1)))
    with pytest.raises(NotFoundError):
        qr_pose(np.full_like(frame.color, 128), depth, intr)
    with pytest.raises(NotFoundError):
        qr_pose(frame.color, depth, intr, expect="something else")
    with pytest.raises(BadImageError):
        qr_pose(frame.color, [d.astype(np.float32) for d in depth], intr)  # type: ignore[misc]
    with pytest.raises(BadImageError):
        qr_pose(frame.color, [d[:100] for d in depth], intr)
    # A crop of colour and depth together: registered to each other, not to the intrinsics.
    # The error names the colour image's size and the intrinsics', not the depth.
    crop = frame.color[:192, :224]
    with pytest.raises(BadImageError, match=r"colour image is 224x192, the camera's intrinsics"):
        qr_pose(crop, [d[:192, :224] for d in depth], intr)
