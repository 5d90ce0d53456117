"""The structured-light depth model: noise, quantisation, invalid pixels, systematic errors."""

from __future__ import annotations

import numpy as np
import pytest

from simulation import SimCell, scene_from_text

from .conftest import BOARD_SCENE


def _cell(depth: str = "", seed: int = 5) -> SimCell:
    # No dropout unless ``depth`` sets it (scene files refuse a key written twice).
    settings = depth.removeprefix(", ") if "dropout:" in depth else "dropout: 0.0" + depth
    text = BOARD_SCENE.replace("noise_sigma: 1.0}", "noise_sigma: 1.0, depth: {" + settings + "}}")
    return SimCell(scene_from_text(text), seed=seed)


def _wall_pixels(frame_depth: np.ndarray, truth_mask: np.ndarray) -> np.ndarray:
    # Away from the QR board and the wall's edges: a plane exactly 0.99 m away (z-depth).
    inner = truth_mask.copy()
    inner[:, 180:460] = False
    inner[:, :40] = False
    inner[:, -40:] = False
    return frame_depth[inner]


def test_depth_noise_and_quantisation_at_one_metre() -> None:
    cell = _cell()
    values = []
    for _ in range(3):
        frame = cell.render("rgbd")
        assert frame.depth is not None
        assert frame.depth.dtype == np.uint16
        values.append(_wall_pixels(frame.depth, frame.truth.mask("wall")))
    z = np.concatenate(values).astype(np.float64)
    assert z.size > 50_000
    assert np.all(z > 0)
    z_true_mm = 990.0
    # Disparity sigma 0.06 px -> 1.3 mm at 0.99 m, plus quantisation: between 1.2 and 1.9 mm.
    assert 1.2 < z.std() < 1.9
    assert abs(z.mean() - z_true_mm) < 0.5
    # Only whole 1/8 px disparity steps occur: about z^2 / (8 fb) = 2.8 mm apart.
    levels = np.unique(z)
    steps = np.diff(levels)
    assert len(levels) >= 3
    assert np.all(np.abs(steps - 0.99**2 / (8 * 43.5) * 1000) <= 1.0)


def test_true_depth_is_z_not_ray_length() -> None:
    frame = _cell().render("rgbd")
    z = frame.truth.depth_true_m
    assert z is not None
    wall = frame.truth.mask("wall")
    np.testing.assert_allclose(z[wall], 0.99, atol=1e-5)  # flat fronto-parallel wall: constant z
    qr = frame.truth.mask("qr")
    np.testing.assert_allclose(z[qr], 0.989, atol=1e-5)


def test_invalid_pixels_at_edges_and_dropouts() -> None:
    frame = _cell().render("rgbd")
    assert frame.depth is not None
    z = frame.truth.depth_true_m
    assert z is not None
    # Where the view passes the wall's side edge to the background: no depth on both sides.
    wall = frame.truth.mask("wall")
    cols = np.flatnonzero(wall[240])
    left = cols.min()
    assert left > 0
    assert frame.depth[240, left] == 0
    assert frame.depth[240, left - 1] == 0
    assert frame.depth[240, left + 3] > 0
    dropped = _cell(depth=", dropout: 0.05").render("rgbd")
    assert dropped.depth is not None
    fraction = np.mean(_wall_pixels(dropped.depth, dropped.truth.mask("wall")) == 0)
    assert fraction == pytest.approx(0.05, abs=0.01)


def test_scale_bias_and_misregistration() -> None:
    base = _cell().render("rgbd")
    biased = _cell(depth=", scale_bias: 0.01").render("rgbd")
    assert base.depth is not None
    assert biased.depth is not None
    mask = base.truth.mask("wall")
    ratio = _wall_pixels(biased.depth, mask).mean() / _wall_pixels(base.depth, mask).mean()
    assert ratio == pytest.approx(1.01, abs=0.001)
    shifted = _cell(depth=", misregistration_px: [5, 0], disparity_sigma_px: 0.0").render("rgbd")
    clean = _cell(depth=", disparity_sigma_px: 0.0").render("rgbd")
    assert shifted.depth is not None
    assert clean.depth is not None
    np.testing.assert_array_equal(shifted.depth[:, 5:], clean.depth[:, :-5])
    assert np.all(shifted.depth[:, :5] == 0)
