"""The sensor check's fit and qr_pose's depth correction on the simulated RGB-D camera with a
misregistered, scaled depth (issue 18 part 3): fixed seeds, ground truth from the simulation."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from geometry import invert_transform, rotation_angle
from vision_server.analysis import AnalysisError, fit_depth_registration, qr_pose

from .conftest import qr_cell, random_view

SIDE = 0.16
SHIFT_PX = (2.0, 1.0)
BIAS = 0.005


def _views(n: int, seed: int, **cell_kw: Any) -> list[tuple[Any, list[Any]]]:
    cell = qr_cell(5, **cell_kw)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        cell.world.base_from_tool = random_view(rng)
        frames = [cell.render("rgbd") for _ in range(5)]
        out.append((frames[0], [f.depth for f in frames]))
    return out


def _p95(views: list[tuple[Any, list[Any]]], **kw: Any) -> tuple[float, float]:
    t, r = [], []
    for frame, depth in views:
        truth = frame.truth.qr_codes["qr"].camera_from_qr
        pose = qr_pose(frame.color, depth, frame.truth.intrinsics, side_m=SIDE, **kw)
        e = invert_transform(truth) @ pose.camera_from_qr
        t.append(float(np.linalg.norm(e[:3, 3])))
        r.append(float(np.degrees(rotation_angle(e[:3, :3]))))
    return float(np.percentile(t, 95)), float(np.percentile(r, 95))


SIM_CORNER_BIAS_PX = -0.03
"""The corner detector's bias on the code's side on the simulated camera, measured against the
renderer's truth (as an integrator measures it against a known reference; bench section 4
measures it each run: -0.032 +- 0.006 px with today's corner refinement, -0.07 px with an
earlier one): configured, as the qr_pose inspection's ``corner_bias_px``, not assumed by the
analysis."""


@pytest.fixture(scope="module")
def misregistered() -> list[tuple[Any, list[Any]]]:
    return _views(24, seed=3, misregistration_px=SHIFT_PX, scale_bias=BIAS)


def _corrected(reg: Any) -> dict[str, Any]:
    """qr_pose's keywords for a sensor check's correction with its uncertainties."""
    return {
        "depth_scale": reg.scale,
        "depth_shift_px": reg.shift_px,
        "depth_scale_std": reg.scale_std,
        "depth_shift_std_px": reg.shift_std_px,
        "corner_bias_px": SIM_CORNER_BIAS_PX,
    }


def _check(views: list[tuple[Any, list[Any]]]) -> Any:
    poses = [qr_pose(f.color, d, f.truth.intrinsics, side_m=SIDE) for f, d in views]
    q = [p.quality for p in poses]
    return fit_depth_registration(
        [x.depth_vs_side for x in q],
        [x.shift_sensitivity for x in q],
        [x.side_px for x in q],
        corner_bias_px=SIM_CORNER_BIAS_PX,
    )


def test_sensor_check_measures_shift_and_scale(misregistered: Any) -> None:
    reg = _check(misregistered[:12])
    assert reg.views == 12
    assert reg.scale == pytest.approx(1 + BIAS, abs=0.0015)
    np.testing.assert_allclose(reg.shift_px, SHIFT_PX, atol=0.75)
    assert reg.residual_rms < 0.001


def test_corrected_pose_meets_the_goal_under_sensor_errors(misregistered: Any) -> None:
    reg = _check(misregistered[:12])
    held_out = misregistered[12:]  # the check's views are not the evaluated ones
    raw_t, _ = _p95(held_out, scale="depth")
    t, r = _p95(held_out, **_corrected(reg))
    assert raw_t > 0.001  # the uncorrected depth's errors cost millimetres
    assert t <= 0.0005
    assert r <= 0.2


@pytest.mark.parametrize("bias", [-0.01, 0.01])
def test_corrected_pose_at_one_percent_scale_error(bias: float) -> None:
    views = _views(24, seed=3, misregistration_px=SHIFT_PX, scale_bias=bias)
    reg = _check(views[:12])
    assert reg.scale == pytest.approx(1 + bias, abs=0.0015)
    t, r = _p95(views[12:], **_corrected(reg))
    assert t <= 0.0005
    assert r <= 0.2


def test_fusion_with_the_side_on_a_well_checked_sensor() -> None:
    # (-2, 1) px: before issue 29 the check's shift was (-0.35, +0.46) px off on these views
    # and the corrected depth alone 0.55 mm p95, which the printed side pulled back. With the
    # tilt fused from the depth and the corners each view's shift sensitivity is truer: the
    # check is within 0.3 px, the correction alone meets the goal (0.43 mm) and the fusion by
    # the check's uncertainty keeps it (0.46 mm)
    views = _views(24, seed=3, misregistration_px=(-2.0, 1.0), scale_bias=0.01)
    reg = _check(views[:12])
    np.testing.assert_allclose(reg.shift_px, (-2.0, 1.0), atol=0.3)
    alone, _ = _p95(views[12:], depth_scale=reg.scale, depth_shift_px=reg.shift_px)
    fused, r = _p95(views[12:], **_corrected(reg))
    assert alone <= 0.0005
    assert fused <= 0.0005
    assert r <= 0.2


def test_perfect_sensor_checks_as_perfect() -> None:
    reg = _check(_views(12, seed=4))
    assert abs(reg.scale - 1.0) < 0.0015
    assert np.all(np.abs(reg.shift_px) < 0.75)


def test_fit_needs_views_and_tilts() -> None:
    with pytest.raises(AnalysisError, match="at least 2 views"):
        fit_depth_registration([0.01], [[0.0, 0.0]])
    # square to the camera: the shift is not determined, only the scale
    reg = fit_depth_registration([0.004, 0.006, 0.005, 0.005], np.zeros((4, 2)))
    assert reg.scale == pytest.approx(1.005)
    assert reg.shift_px == (0.0, 0.0)
    assert np.isnan(reg.shift_std_px[0])
    with pytest.raises(ValueError, match="depth_scale"):
        qr_pose(None, np.zeros((4, 4), np.uint16), _intrinsics(), depth_scale=0.0)


def _intrinsics() -> Any:
    from geometry import CameraIntrinsics

    return CameraIntrinsics(4, 4, 2.0, 2.0, 1.5, 1.5)
