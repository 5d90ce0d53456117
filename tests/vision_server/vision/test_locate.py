"""Feature locate on rendered 1024x768 images with exact ground truth (8x supersampled)."""

from __future__ import annotations

import _vision_render as render
import numpy as np
import pytest

from vision_server.vision import (
    ParameterError,
    RoiError,
    TemplateError,
    locate,
    locate_blobs,
    locate_circles,
    locate_template,
)

W, H = 1024, 768


def _cap(img: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
    """A rotor cap seen from above: bright disc (r 30 px) with a darker hub (r 12 px)."""
    h, w = img.shape
    outer = render.disc_coverage(centre, 30.0, width=w, height=h)
    hub = render.disc_coverage(centre, 12.0, width=w, height=h)
    img = img * (1 - outer) + 200.0 * outer
    return img * (1 - hub) + 110.0 * hub


def _scenes(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``n`` images with three caps each at random sub-pixel, non-overlapping centres."""
    rng = np.random.default_rng(seed)
    scenes = []
    for _ in range(n):
        centres: list[np.ndarray] = []
        while len(centres) < 3:
            c = np.array([rng.uniform(60, W - 60), rng.uniform(60, H - 60)])
            if all(np.linalg.norm(c - o) > 100 for o in centres):
                centres.append(c)
        img = np.full((H, W), 50.0)
        for c in centres:
            img = _cap(img, (c[0], c[1]))
        scenes.append((render.to_uint8(img, rng, 2.5), np.array(centres)))
    return scenes


@pytest.fixture(scope="module")
def scenes() -> list[tuple[np.ndarray, np.ndarray]]:
    return _scenes(8, seed=0)


def _errors(found: tuple, truth: np.ndarray) -> list[float]:
    assert len(found) == len(truth)
    return [float(np.min(np.hypot(truth[:, 0] - f.u, truth[:, 1] - f.v))) for f in found]


def test_template_subpixel_accuracy(scenes: list) -> None:
    template = render.to_uint8(
        _cap(np.full((81, 81), 50.0), (40.0, 40.0)), np.random.default_rng(1), 0
    )
    errors = []
    for image, truth in scenes:
        found = locate_template(image, template, max_count=5, min_score=0.6)
        errors += _errors(found, truth)
        assert all(f.score > 0.9 for f in found)
    # Measured: median about 0.04 px.
    assert np.median(errors) <= 0.1


def test_circle_subpixel_accuracy(scenes: list) -> None:
    errors, radii = [], []
    for image, truth in scenes:
        found = locate_circles(image, radius_range=(25, 35), max_count=5)
        errors += _errors(found, truth)
        radii += [f.radius for f in found]
    # Measured: median about 0.01 px; radius within 0.1 px.
    assert np.median(errors) <= 0.1
    np.testing.assert_allclose(radii, 30.0, atol=0.2)


def test_blob_centroids_and_roi_offset(scenes: list) -> None:
    image, truth = scenes[0]
    found = locate_blobs(image, threshold=80, area_range=(1000, 5000), min_circularity=0.8)
    assert max(_errors(found, truth)) < 0.1
    # The darker hub counts by its coverage: between the disc without and with the hub.
    assert all(np.pi * (30**2 - 12**2) < (f.area or 0) < np.pi * 30**2 + 60 for f in found)
    c = truth[0]
    roi = [int(c[0]) - 45, int(c[1]) - 45, 90, 90]
    (f,) = locate(image, method="blob", roi=roi, threshold=80)
    assert np.hypot(f.u - c[0], f.v - c[1]) < 0.1
    (f,) = locate(image, method="circle", roi=roi, radius_range=(25, 35))
    assert np.hypot(f.u - c[0], f.v - c[1]) < 0.1


def test_template_rotation_search() -> None:
    rng = np.random.default_rng(4)

    # An asymmetric part: a bar with a disc at one end.
    def part(angle: float, shape: tuple[int, int], centre: tuple[float, float]) -> np.ndarray:
        h, w = shape
        img = np.full((h, w), 40.0)
        for t in np.linspace(-25, 25, 11):
            p = (centre[0] + t * np.cos(angle), centre[1] - t * np.sin(angle))
            img = np.maximum(img, 40 + 170 * render.disc_coverage(p, 6.0, width=w, height=h))
        tip = (centre[0] + 25 * np.cos(angle), centre[1] - 25 * np.sin(angle))
        return np.maximum(img, 40 + 170 * render.disc_coverage(tip, 11.0, width=w, height=h))

    template = render.to_uint8(part(0.0, (61, 81), (40.0, 30.0)), rng, 0)
    truth_angle, centre = np.deg2rad(37.0), (150.4, 120.7)
    image = render.to_uint8(part(truth_angle, (240, 300), centre), rng, 2.0)
    (f,) = locate_template(
        image, template, angle_range=(-np.pi / 3, np.pi / 3), angle_step=np.deg2rad(5)
    )
    assert abs(f.angle - truth_angle) < np.deg2rad(2.0)
    assert np.hypot(f.u - centre[0], f.v - centre[1]) < 0.5


def test_bgr_input_and_errors(scenes: list) -> None:
    image, _ = scenes[0]
    bgr = np.repeat(image[:, :, None], 3, axis=2)
    assert len(locate(bgr, method="circle", radius_range=(25, 35), max_count=5)) == 3
    with pytest.raises(TemplateError, match="missing"):
        locate(image, method="template")
    with pytest.raises(TemplateError, match="larger"):
        locate_template(image, np.zeros((50, 50), np.uint8) + 7, roi=[0, 0, 40, 40])
    with pytest.raises(RoiError, match="not inside"):
        locate_blobs(image, roi=[1000, 0, 100, 100])
    with pytest.raises(ParameterError, match="method"):
        locate(image, method="sift")  # type: ignore[arg-type]
    assert locate_circles(np.full((100, 100), 80, np.uint8)) == ()
