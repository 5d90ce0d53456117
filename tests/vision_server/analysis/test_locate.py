"""Feature locate: sub-pixel accuracy on synthetic images with exact ground truth and on the
simulated cell's tool camera, plus the input checks."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from vision_server.analysis import BadImageError, NotFoundError, RoiError, TemplateError
from vision_server.analysis.locate import (
    Feature,
    crop_roi,
    locate,
    locate_blobs,
    locate_circles,
    locate_one,
    locate_template,
)

REPO = Path(__file__).resolve().parents[3]
SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"
SUPERSAMPLE = 8

Inside = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.bool_]]


# --- synthetic images -------------------------------------------------------------------------


def paint(
    canvas: NDArray[np.float64], inside: Inside, box: tuple[int, int, int, int], level: float
):
    """Paint the shape ``inside(u, v)`` with grey ``level`` into ``canvas``, anti-aliased by
    8x supersampling then area averaging, within ``box`` = (u0, v0, u1, v1) pixels."""
    import cv2

    u0, v0, u1, v1 = box
    u0, v0 = max(u0, 0), max(v0, 0)
    u1, v1 = min(u1, canvas.shape[1]), min(v1, canvas.shape[0])
    s = SUPERSAMPLE
    vs, us = np.mgrid[0 : (v1 - v0) * s, 0 : (u1 - u0) * s].astype(np.float64)
    # Sample (i, j) of the fine grid sits at full-image position ((j + 0.5) / s - 0.5 + u0, ...).
    cover = inside((us + 0.5) / s - 0.5 + u0, (vs + 0.5) / s - 0.5 + v0).astype(np.float32)
    coverage = cv2.resize(cover, (u1 - u0, v1 - v0), interpolation=cv2.INTER_AREA)
    patch = canvas[v0:v1, u0:u1]
    canvas[v0:v1, u0:u1] = patch + coverage * (level - patch)


def disc(u: float, v: float, r: float) -> Inside:
    return lambda x, y: (x - u) ** 2 + (y - v) ** 2 <= r * r


def finish(canvas: NDArray[np.float64], noise: float, seed: int) -> NDArray[np.uint8]:
    noisy = canvas + np.random.default_rng(seed).normal(0.0, noise, canvas.shape)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def disc_image(
    seed: int,
    *,
    count: int = 4,
    size: tuple[int, int] = (1024, 768),
    radius: tuple[float, float] = (20.0, 60.0),
    fg: float = 200.0,
    bg: float = 50.0,
    noise: float = 2.5,
) -> tuple[NDArray[np.uint8], list[tuple[float, float, float]]]:
    """Non-overlapping anti-aliased discs at random sub-pixel centres on a gradient background."""
    rng = np.random.default_rng(seed)
    w, h = size
    canvas = bg + np.linspace(-10, 10, w)[None, :] + np.zeros((h, 1))
    discs: list[tuple[float, float, float]] = []
    while len(discs) < count:
        r = rng.uniform(*radius)
        u, v = rng.uniform(r + 5, w - r - 5), rng.uniform(r + 5, h - r - 5)
        if all(math.hypot(u - a, v - b) > r + c + 10 for a, b, c in discs):
            discs.append((u, v, r))
            box = (int(u - r) - 2, int(v - r) - 2, int(u + r) + 3, int(v + r) + 3)
            paint(canvas, disc(u, v, r), box, fg + rng.uniform(-20, 20))
    return finish(canvas, noise, seed + 1000), discs


def blob_texture(rng: np.random.Generator, n: int, spread: float) -> NDArray[np.float64]:
    """Gaussian spots (u, v, sigma, amplitude): a smooth texture known everywhere exactly."""
    return np.stack(
        [
            rng.uniform(-spread, spread, n),
            rng.uniform(-spread, spread, n),
            rng.uniform(3.0, 7.0, n),
            rng.choice([-1.0, 1.0], n) * rng.uniform(30.0, 70.0, n),
        ],
        axis=1,
    )


def texture(spots: NDArray[np.float64], x: NDArray[np.float64], y: NDArray[np.float64]):
    out = np.zeros_like(x)
    for sx, sy, sigma, amplitude in spots:
        out += amplitude * np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / (2 * sigma * sigma))
    return out


def template_scene(
    spots: NDArray[np.float64],
    poses: list[tuple[float, float, float]],
    *,
    size: tuple[int, int],
    noise: float = 2.5,
    seed: int = 0,
) -> NDArray[np.uint8]:
    """The textured object placed at each (u, v, angle): object point p appears at
    (u, v) + R(angle) p, R turning +u towards +v."""
    w, h = size
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    canvas = np.full((h, w), 120.0)
    for u, v, angle in poses:
        c, s = math.cos(angle), math.sin(angle)
        near = (np.abs(x - u) < 80) & (np.abs(y - v) < 80)
        dx, dy = x[near] - u, y[near] - v
        canvas[near] += texture(spots, c * dx + s * dy, -s * dx + c * dy)
    return finish(canvas, noise, seed)


def make_template(spots: NDArray[np.float64], half: int = 32) -> NDArray[np.uint8]:
    y, x = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    return np.clip(np.rint(120.0 + texture(spots, x, y)), 0, 255).astype(np.uint8)


def nearest(features: list[Feature], u: float, v: float) -> tuple[Feature, float]:
    best = min(features, key=lambda f: math.hypot(f.u - u, f.v - v))
    return best, math.hypot(best.u - u, best.v - v)


# --- circles ----------------------------------------------------------------------------------


def test_circles_sub_pixel_on_synthetic_discs() -> None:
    errors, radius_errors = [], []
    for seed in range(6):
        image, discs = disc_image(seed)
        found = locate_circles(image, radius_range=(15, 70), max_count=10)
        assert len(found) == len(discs)
        for u, v, r in discs:
            feature, error = nearest(found, u, v)
            errors.append(error)
            assert feature.radius is not None
            radius_errors.append(abs(feature.radius - r))
            assert feature.score > 0.9
            assert feature.angle == 0.0
    median, p95 = np.median(errors), np.percentile(errors, 95)
    print(f"circle, synthetic: median {median:.3f} px, p95 {p95:.3f} px, n={len(errors)}")
    assert median <= 0.1
    assert p95 <= 0.2
    assert np.median(radius_errors) <= 0.1


def test_dark_circles_and_roi_offset() -> None:
    image, discs = disc_image(11, count=3, fg=40.0, bg=180.0)
    u, v, r = discs[0]
    roi = [int(u - r - 10), int(v - r - 10), int(2 * r + 20), int(2 * r + 20)]
    roi = [max(roi[0], 0), max(roi[1], 0), roi[2], roi[3]]
    roi[2] = min(roi[2], 1024 - roi[0])
    roi[3] = min(roi[3], 768 - roi[1])
    found = locate_circles(image, roi=roi, polarity="dark", radius_range=(15, 70))
    assert len(found) == 1
    assert math.hypot(found[0].u - u, found[0].v - v) < 0.15
    # The bright polarity finds nothing round and bright there.
    assert locate_circles(image, roi=roi, polarity="bright", radius_range=(15, 70)) == []


def test_circles_respect_radius_range_and_max_count() -> None:
    image, discs = disc_image(3, count=4, radius=(20, 60))
    found = locate_circles(image, radius_range=(15, 70), max_count=2)
    assert len(found) == 2
    small = min(r for _, _, r in discs)
    only_small = locate_circles(image, radius_range=(small - 3, small + 3))
    assert all(f.radius is not None and abs(f.radius - small) < 3 for f in only_small)


def test_no_circle_in_noise() -> None:
    image = finish(np.full((300, 400), 100.0), 3.0, 5)
    assert locate_circles(image, radius_range=(10, 80)) == []


def _rim_centre(p_camera: NDArray[np.float64], radius_m: float, intrinsics) -> NDArray[np.float64]:
    """Centre of the circle best fitting the cap's top rim as projected with lens distortion."""
    theta = np.linspace(0.0, 2 * np.pi, 360, endpoint=False)
    rim = np.stack(
        [
            p_camera[0] + radius_m * np.cos(theta),
            p_camera[1] + radius_m * np.sin(theta),
            np.full_like(theta, p_camera[2]),
        ],
        axis=1,
    )
    uv = intrinsics.project(rim)
    a = np.stack([uv[:, 0], uv[:, 1], np.ones(len(uv))], axis=1)
    d, e, _ = np.linalg.lstsq(a, -(uv**2).sum(axis=1), rcond=None)[0]
    return np.array([-d / 2, -e / 2])


def test_circles_on_simulated_tool_camera() -> None:
    from geometry import transform_from_xyz_rpy
    from simulation import SimCell

    to_truth, to_rim = [], []
    for seed in range(4):
        cell = SimCell.from_yaml(SCENE, seed=seed)
        for x in (0.1, 0.2, 0.3, 0.45):
            cell.robot.move_linear(transform_from_xyz_rpy([x, -0.55, 0.275], [np.pi, 0, 0]))
            frame = cell.render("tool_camera")
            found = locate_circles(frame.color, radius_range=(50, 110))
            for name, truth in frame.truth.features.items():
                if not name.startswith("cap_") or not truth.visible:
                    continue
                u, v = truth.uv
                if not (90 < u < 1024 - 90 and 90 < v < 768 - 90):
                    continue  # the disc must lie wholly inside the image
                feature, error = nearest(found, u, v)
                to_truth.append(error)
                rim = _rim_centre(truth.p_camera, 0.02, frame.truth.intrinsics)
                to_rim.append(math.hypot(feature.u - rim[0], feature.v - rim[1]))
    assert len(to_truth) >= 16
    print(
        f"circle, sim tool camera: vs projected centre median {np.median(to_truth):.3f} "
        f"p95 {np.percentile(to_truth, 95):.3f} px; vs distorted rim's circle median "
        f"{np.median(to_rim):.3f} p95 {np.percentile(to_rim, 95):.3f} px; n={len(to_truth)}"
    )
    # The detector finds the imaged rim to well below 0.1 px ...
    assert np.median(to_rim) <= 0.1
    assert np.percentile(to_rim, 95) <= 0.2
    # ... whose centre the mild barrel distortion moves up to ~0.3 px from the projected
    # centre (towards the image centre); undistort first where that matters.
    assert np.median(to_truth) <= 0.35


# --- template ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def spots() -> NDArray[np.float64]:
    return blob_texture(np.random.default_rng(1), 40, 28.0)


def test_template_sub_pixel_without_rotation(spots: NDArray[np.float64]) -> None:
    rng = np.random.default_rng(2)
    template = make_template(spots)
    errors = []
    for trial in range(12):
        u, v = rng.uniform(100, 924), rng.uniform(100, 668)
        image = template_scene(spots, [(u, v, 0.0)], size=(1024, 768), seed=trial)
        found = locate_template(image, template)
        assert len(found) == 1
        errors.append(math.hypot(found[0].u - u, found[0].v - v))
        assert found[0].score > 0.95
        assert found[0].angle == 0.0
    median, p95 = np.median(errors), np.percentile(errors, 95)
    print(f"template, synthetic: median {median:.3f} px, p95 {p95:.3f} px")
    assert median <= 0.1
    assert p95 <= 0.2


def test_template_with_rotation(spots: NDArray[np.float64]) -> None:
    rng = np.random.default_rng(3)
    template = make_template(spots)
    errors, angle_errors = [], []
    for trial in range(8):
        u, v, angle = rng.uniform(120, 280), rng.uniform(120, 280), rng.uniform(-0.6, 0.6)
        image = template_scene(spots, [(u, v, angle)], size=(400, 400), seed=trial)
        found = locate_template(
            image, template, angle_range=(-0.7, 0.7), angle_step=math.radians(5)
        )
        assert len(found) == 1
        errors.append(math.hypot(found[0].u - u, found[0].v - v))
        angle_errors.append(abs(found[0].angle - angle))
    print(
        f"template, rotated: median {np.median(errors):.3f} px, p95 "
        f"{np.percentile(errors, 95):.3f} px; angle median {np.median(angle_errors):.4f} rad"
    )
    assert np.median(errors) <= 0.1
    assert np.percentile(errors, 95) <= 0.2
    # Interpolated well below the 0.087 rad step.
    assert np.median(angle_errors) <= 0.01


def test_template_full_turn_on_a_full_frame(spots: NDArray[np.float64]) -> None:
    poses = [(400.3, 300.7, 2.0), (700.1, 500.2, -1.0)]
    image = template_scene(spots, poses, size=(1024, 768), seed=1)
    found = locate_template(
        image,
        make_template(spots),
        angle_range=(-math.pi, math.pi),
        angle_step=math.radians(5),
        max_count=2,
    )
    assert len(found) == 2
    for u, v, angle in poses:
        feature, error = nearest(found, u, v)
        assert error < 0.1
        assert abs(feature.angle - angle) < 0.01


@pytest.mark.parametrize("levels", [0, 1, 2])
def test_template_pyramid_levels_agree(spots: NDArray[np.float64], levels: int) -> None:
    image = template_scene(spots, [(150.6, 160.2, 0.3)], size=(300, 300), seed=2)
    found = locate_template(
        image,
        make_template(spots),
        angle_range=(0.0, 0.6),
        angle_step=math.radians(6),
        pyramid_levels=levels,
    )
    assert len(found) == 1
    assert math.hypot(found[0].u - 150.6, found[0].v - 160.2) < 0.1
    assert abs(found[0].angle - 0.3) < 0.01


def test_template_several_instances_with_nms(spots: NDArray[np.float64]) -> None:
    poses = [(100.3, 120.6, 0.0), (300.8, 110.1, 0.0), (210.5, 290.25, 0.0)]
    image = template_scene(spots, poses, size=(420, 400), seed=4)
    template = make_template(spots)
    found = locate_template(image, template, max_count=10, min_score=0.5)
    assert len(found) == 3
    assert [f.score for f in found] == sorted((f.score for f in found), reverse=True)
    for u, v, _ in poses:
        assert nearest(found, u, v)[1] < 0.1
    assert len(locate_template(image, template, max_count=2, min_score=0.5)) == 2
    # With an ROI around one instance: full-image coordinates.
    found = locate_template(image, template, roi=[240, 40, 120, 140])
    assert len(found) == 1
    assert math.hypot(found[0].u - 300.8, found[0].v - 110.1) < 0.1


def test_template_not_found_and_errors(spots: NDArray[np.float64]) -> None:
    template = make_template(spots)
    noise = finish(np.full((200, 200), 120.0), 10.0, 9)
    assert locate_template(noise, template, min_score=0.7) == []
    with pytest.raises(NotFoundError):
        locate_one(noise, method="template", template=template)
    with pytest.raises(TemplateError, match="larger"):
        locate_template(noise, template, roi=[0, 0, 50, 50])
    with pytest.raises(TemplateError, match="constant"):
        locate_template(noise, np.full((10, 10), 7, np.uint8))
    with pytest.raises(TemplateError):
        locate(noise, method="template")
    with pytest.raises(BadImageError):
        locate_template(noise, template.astype(np.float32))


def test_template_accepts_bgr(spots: NDArray[np.float64]) -> None:
    import cv2

    image = template_scene(spots, [(150.25, 140.75, 0.0)], size=(300, 300), seed=1)
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    found = locate(bgr, method="template", template=make_template(spots))
    assert math.hypot(found[0].u - 150.25, found[0].v - 140.75) < 0.1


# --- blobs ------------------------------------------------------------------------------------


def test_blob_centroid_area_and_angle() -> None:
    h, w = 300, 400
    canvas = np.full((h, w), 40.0)
    a, b, tilt = 30.0, 12.0, 0.4  # an ellipse: semi-axes (px), major axis angle (rad)
    cu, cv = 120.37, 150.81

    def ellipse(x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.bool_]:
        dx, dy = x - cu, y - cv
        p = math.cos(tilt) * dx + math.sin(tilt) * dy
        q = -math.sin(tilt) * dx + math.cos(tilt) * dy
        return (p / a) ** 2 + (q / b) ** 2 <= 1

    paint(canvas, ellipse, (80, 110, 160, 190), 210.0)
    paint(canvas, disc(300.6, 100.2, 15.0), (280, 80, 322, 122), 190.0)
    image = finish(canvas, 2.5, 3)
    found = locate_blobs(image, min_area=50)
    assert len(found) == 2
    big, small = found  # largest first
    assert big.area is not None
    assert small.area is not None
    assert math.hypot(big.u - cu, big.v - cv) < 0.1
    assert abs(big.area - math.pi * a * b) / (math.pi * a * b) < 0.02
    assert abs(big.angle - tilt) < 0.02
    assert math.hypot(small.u - 300.6, small.v - 100.2) < 0.1
    assert big.score == big.area
    # Circularity keeps the disc only; area bounds pick either.
    only_round = locate_blobs(image, min_area=50, min_circularity=0.8)
    assert len(only_round) == 1
    assert abs(only_round[0].u - 300.6) < 0.1
    assert len(locate_blobs(image, min_area=50, max_area=900)) == 1
    assert len(locate_blobs(image, threshold=120, min_area=50)) == 2
    assert len(locate(image, method="blob", threshold="otsu", min_area=50, max_count=1)) == 1


def test_dark_blob_in_roi() -> None:
    canvas = np.full((200, 300), 180.0)
    paint(canvas, disc(200.4, 80.7, 10.0), (185, 65, 216, 96), 30.0)
    paint(canvas, disc(60.0, 60.0, 10.0), (45, 45, 76, 76), 30.0)
    image = finish(canvas, 2.0, 1)
    found = locate_blobs(image, roi=[150, 30, 100, 100], polarity="dark", threshold=100)
    assert len(found) == 1
    assert math.hypot(found[0].u - 200.4, found[0].v - 80.7) < 0.1
    # Bright: only the background around the hole, far larger than the spot.
    bright = locate_blobs(image, roi=[150, 30, 100, 100], polarity="bright", threshold=100)
    assert len(bright) == 1
    assert bright[0].area is not None
    assert bright[0].area > 9000


# --- input checks -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    "image",
    [
        np.zeros((10, 10), np.float32),
        np.zeros((10, 10, 4), np.uint8),
        np.zeros((0, 10), np.uint8),
        np.zeros((10,), np.uint8),
        [[1, 2], [3, 4]],
    ],
)
def test_bad_images(image: object) -> None:
    for method in ("circle", "blob"):
        with pytest.raises(BadImageError):
            locate(image, method=method)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "roi",
    [[-1, 0, 10, 10], [0, 0, 0, 10], [95, 0, 10, 10], [0, 0, 100, 101], [0, 0, 10], [0.5, 0, 9, 9]],
)
def test_bad_rois(roi: list[float]) -> None:
    image = np.zeros((100, 100), np.uint8)
    with pytest.raises(RoiError):
        locate(image, method="blob", roi=roi)


def test_unknown_method() -> None:
    with pytest.raises(ValueError, match="unknown"):
        locate(np.zeros((10, 10), np.uint8), method="sift")  # type: ignore[arg-type]


@settings(max_examples=60, deadline=None)
@given(
    u=st.integers(-5, 60),
    v=st.integers(-5, 40),
    w=st.integers(-2, 70),
    h=st.integers(-2, 50),
)
def test_roi_inside_or_rejected(u: int, v: int, w: int, h: int) -> None:
    image = np.zeros((40, 60), np.uint8)
    inside = u >= 0 and v >= 0 and w > 0 and h > 0 and u + w <= 60 and v + h <= 40
    if inside:
        view, roi = crop_roi(image, [u, v, w, h])
        assert view.shape == (h, w)
        assert roi == (u, v, w, h)
    else:
        with pytest.raises(RoiError):
            crop_roi(image, [u, v, w, h])


@settings(max_examples=15, deadline=None)
@given(du=st.floats(0, 1), dv=st.floats(0, 1), shift_u=st.integers(0, 40))
def test_blob_position_follows_the_roi(du: float, dv: float, shift_u: int) -> None:
    canvas = np.full((120, 160), 30.0)
    u, v = 80.0 + du, 60.0 + dv
    paint(canvas, disc(u, v, 8.0), (70, 50, 92, 72), 220.0)
    image = finish(canvas, 1.0, 0)
    found = locate_blobs(image, roi=[shift_u, 10, 100, 100])
    assert len(found) == 1
    assert math.hypot(found[0].u - u, found[0].v - v) < 0.1
