"""Calipers and measurement: sub-pixel edges, pairs, fits and distances, in px and in mm.

Ground truth: bars and discs rendered with 8x (pixel frame) or 6x (camera frame, through the
tool camera's lens model) supersampling, a Gaussian blur and camera noise (fixed seeds); the
held-out check is scikit-image's coins photograph against a diameter measured by hand.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from numpy.typing import NDArray

from simulation.flat_parts import bar, disc, plane_point, render_flat_part
from simulation.scene import camera_preset
from tests.helpers.photos import MISSING, sample_gray
from vision_server.analysis import (
    Band,
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    NotFoundError,
    PixelUnits,
    PlaneUnits,
    RoiError,
    ScaleUnits,
    WidthSpec,
    find_edges,
    find_pairs,
    measure,
)
from vision_server.analysis.fit2d import Line, fit_circle, fit_line, line_line, point_line_distance

SUPERSAMPLE = 8
TOOL_CAMERA, _, _ = camera_preset("dmk31bf03")
WORKING_DISTANCE_MM = 350.0
"""The tool camera above the caps' tops when it searches the conveyor (examples/scenes/
grundfos_cell.yaml): 0.25 mm per pixel at fx = 1400 px."""


def render_bar(
    centre: tuple[float, float],
    width: float,
    angle: float,
    *,
    seed: int,
    size: tuple[int, int] = (128, 96),
    blur: float = 1.0,
    noise: float = 1.5,
) -> NDArray[np.uint8]:
    """A bright bar (grey 190 on 60) ``width`` px wide across ``angle`` (its width runs along
    it), infinitely long, through ``centre`` (u, v) in image pixels."""
    w, h = size
    ys, xs = np.mgrid[0 : h * SUPERSAMPLE, 0 : w * SUPERSAMPLE].astype(np.float64)
    xs, ys = (xs + 0.5) / SUPERSAMPLE - 0.5, (ys + 0.5) / SUPERSAMPLE - 0.5
    along = (xs - centre[0]) * math.cos(angle) + (ys - centre[1]) * math.sin(angle)
    inside = (np.abs(along) <= width / 2).astype(np.float32)
    cover = cv2.resize(inside, (w, h), interpolation=cv2.INTER_AREA).astype(np.float64)
    image = cv2.GaussianBlur(60.0 + 130.0 * cover, (0, 0), blur)
    image = image + np.random.default_rng(seed).normal(0.0, noise, image.shape)
    return np.asarray(np.clip(np.rint(image), 0, 255), np.uint8)


def test_edges_are_placed_to_a_twentieth_of_a_pixel() -> None:
    errors: list[float] = []
    for seed in range(12):
        rng = np.random.default_rng(seed)
        centre = (float(rng.uniform(60, 68)), float(rng.uniform(44, 52)))
        angle, width = float(rng.uniform(-0.5, 0.5)), float(rng.uniform(20, 40))
        tilt = float(rng.uniform(-0.1, 0.1))  # the band a little off the bar's normal
        image = render_bar(centre, width, angle, seed=seed)
        edges = find_edges(image, Band(*centre, 80, 9, angle + tilt), min_strength=10)
        assert [e.polarity for e in edges] == ["dark_to_light", "light_to_dark"]
        half = width / 2 / math.cos(tilt)
        errors += [abs(edges[0].offset - (40 - half)), abs(edges[1].offset - (40 + half))]
    assert float(np.median(errors)) <= 0.05, errors
    assert max(errors) <= 0.15, errors


def test_polarity_and_selection_pick_the_edges_asked_for() -> None:
    image = render_bar((64, 48), 30, 0.0, seed=1)
    band = Band(64, 48, 80, 5)
    rising = find_edges(image, band, polarity="dark_to_light")
    falling = find_edges(image, band, polarity="light_to_dark")
    assert len(rising) == 1
    assert rising[0].u == pytest.approx(49.0, abs=0.1)
    assert len(falling) == 1
    assert falling[0].u == pytest.approx(79.0, abs=0.1)
    assert rising[0].strength > 0 > falling[0].strength
    assert find_edges(image, band, select="first") == rising
    assert find_edges(image, band, select="last") == falling
    # 130 grey levels over a ~1.4 px sigma: about 37 grey levels per px at the steepest
    assert find_edges(image, band, min_strength=80) == []
    reverse = find_edges(image, Band(64, 48, 80, 5, math.pi), polarity="dark_to_light")
    assert reverse[0].u == pytest.approx(79.0, abs=0.1)


def test_a_pair_is_chosen_by_its_expected_width() -> None:
    # two bright bars 10 and 24 px wide on one scan line
    image = np.maximum(render_bar((40, 48), 10, 0.0, seed=2), render_bar((90, 48), 24, 0.0, seed=3))
    band = Band(64, 48, 120, 5)
    narrow = find_pairs(image, band, expected_width=11, width_tolerance=3)
    wide = find_pairs(image, band, expected_width=22, width_tolerance=3)
    assert narrow[0].width_px == pytest.approx(10.0, abs=0.1)
    assert wide[0].width_px == pytest.approx(24.0, abs=0.1)
    every = find_pairs(image, band, select="all")
    assert [round(p.width_px) for p in every] == [10, 24]
    with pytest.raises(NotFoundError, match="within 1 px of 40 px"):
        find_pairs(image, band, expected_width=40, width_tolerance=1)


def test_bad_bands_and_options_are_refused_with_their_cause() -> None:
    image = render_bar((64, 48), 30, 0.0, seed=1)
    with pytest.raises(RoiError, match="outside the 128x96 image"):
        find_edges(image, Band(64, 48, 200, 3))
    with pytest.raises(ValueError, match="polarity"):
        find_edges(image, Band(64, 48, 40), polarity="up")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="band length"):
        Band(64, 48, 1.0)
    with pytest.raises(ValueError, match="singular"):
        find_edges(image, Band(0, 0, 40), image_from_part=np.zeros((2, 3)))


def test_a_fixture_moves_the_band_with_the_part() -> None:
    """A band given in the part frame finds the same edges when the part is shifted and
    turned and the fixture (image_from_part) says so."""
    angle, origin = 0.3, (70.4, 41.7)
    image = render_bar(origin, 26, angle, seed=5)
    c, s = math.cos(angle), math.sin(angle)
    image_from_part = np.array([[c, -s, origin[0]], [s, c, origin[1]]])
    pair = find_pairs(image, Band(0, 0, 60, 7), image_from_part=image_from_part)[0]
    assert pair.width_px == pytest.approx(26.0, abs=0.1)
    assert pair.centre == pytest.approx(origin, abs=0.1)


def test_measurements_given_in_the_part_frame_follow_a_turned_part() -> None:
    """A job's caliper step: the same specs (part frame) on a part moved by a sub-pixel
    amount and turned 0.5 rad, with the fixture saying so, measure the same."""
    specs = [
        WidthSpec("bar", Band(0, 12, 50, 7)),  # across the bar, 12 px along it
        CircleSpec("hole", 0, 0, 6, search=4, polarity="dark_to_light"),
    ]
    values = []
    for angle, origin in ((0.0, (64.0, 48.0)), (0.5, (70.3, 44.6))):
        bar_image = render_bar(origin, 24, angle, seed=11)
        hole = np.zeros((96 * SUPERSAMPLE, 128 * SUPERSAMPLE), np.float32)
        centre = ((origin[0] + 0.5) * SUPERSAMPLE - 0.5, (origin[1] + 0.5) * SUPERSAMPLE - 0.5)
        cv2.circle(hole, (int(centre[0] * 16), int(centre[1] * 16)), 6 * SUPERSAMPLE * 16, 1.0,
                   -1, cv2.LINE_8, 4)  # fmt: skip
        cover = cv2.resize(hole, (128, 96), interpolation=cv2.INTER_AREA)
        image = np.asarray(bar_image * (1.0 - cover) + 60.0 * cover, np.uint8)
        c, s = math.cos(angle), math.sin(angle)
        image_from_part = np.array([[c, -s, origin[0]], [s, c, origin[1]]])
        got = measure(image, specs, image_from_part=image_from_part)
        assert all(m.passed for m in got), [m.reason for m in got]
        assert got[1].circle is not None
        assert (got[1].circle.x, got[1].circle.y) == pytest.approx(origin, abs=0.1)
        values.append([m.value for m in got])
    assert values[0][0] == pytest.approx(24.0, abs=0.1)
    assert values[1] == pytest.approx(values[0], abs=0.1)


def test_width_in_millimetres_at_the_tool_camera() -> None:
    """Bars 6..12 mm wide anywhere in the tool camera's 1024x768 image (barrel distortion
    included), 350 mm away: width error p95 <= 0.02 mm (0.08 px)."""
    units = PlaneUnits(TOOL_CAMERA, WORKING_DISTANCE_MM)
    errors = []
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        u, v = float(rng.uniform(100, 900)), float(rng.uniform(100, 660))
        angle, width = float(rng.uniform(-0.6, 0.6)), float(rng.uniform(6, 12))
        part = bar(plane_point(TOOL_CAMERA, WORKING_DISTANCE_MM, (u, v)), width, angle)
        window = (int(u) - 36, int(v) - 36, 72, 72)
        image = render_flat_part(TOOL_CAMERA, WORKING_DISTANCE_MM, part, window, seed=seed)
        (got,) = measure(image, [WidthSpec("w", Band(u, v, 64, 9, angle))], units=units)
        assert got.unit == "mm"
        errors.append(abs(got.value - width))
    assert float(np.percentile(errors, 95)) <= 0.02, errors


def test_circle_diameter_in_millimetres_and_roundness() -> None:
    units = PlaneUnits(TOOL_CAMERA, WORKING_DISTANCE_MM)
    errors = []
    for seed in range(4):
        rng = np.random.default_rng(200 + seed)
        u, v = float(rng.uniform(150, 850)), float(rng.uniform(150, 600))
        diameter = float(rng.uniform(8, 14))
        part = disc(plane_point(TOOL_CAMERA, WORKING_DISTANCE_MM, (u, v)), diameter)
        window = (int(u) - 36, int(v) - 36, 72, 72)
        image = render_flat_part(TOOL_CAMERA, WORKING_DISTANCE_MM, part, window, seed=seed)
        radius_px = diameter / 2 / units.mm_per_px
        spec = CircleSpec("d", u + 1.5, v - 1.0, radius_px, search=8, polarity="light_to_dark")
        (got,) = measure(image, [spec], units=units)
        errors.append(abs(got.value - diameter))
        assert got.extra["roundness"] < 0.05  # mm: a true disc
    assert max(errors) <= 0.02, errors


def test_roundness_is_the_spread_of_the_radius() -> None:
    points = [(10 * math.cos(t) + 50, 8 * math.sin(t) + 40) for t in np.linspace(0, 6.2, 40)]
    assert fit_circle(points).roundness == pytest.approx(2.0, abs=0.05)
    arc = [(20 * math.cos(t) + 5, 20 * math.sin(t) - 3) for t in np.linspace(0.2, 1.2, 12)]
    fit = fit_circle(arc)
    assert (fit.x, fit.y, fit.diameter) == pytest.approx((5, -3, 40), abs=1e-6)


def test_line_to_line_and_point_to_line() -> None:
    first = fit_line([(0, 0), (10, 0.0), (20, 0)])
    second = fit_line([(0, 5), (20, 5 + 20 * math.tan(0.1))])
    distance, angle = line_line(first, second)
    assert angle == pytest.approx(0.1)
    assert distance == pytest.approx(5 + 10 * math.tan(0.1))
    assert point_line_distance((3, -2), first) == pytest.approx(-2.0)
    assert Line(0, 0, -1, 0).angle_rad == pytest.approx(0.0)


def test_measure_chains_lines_into_a_distance_and_an_angle() -> None:
    """Two edges of one bar found as lines: their distance is the bar's width."""
    image = render_bar((64, 48), 30, 0.2, seed=7)
    specs = [
        LineSpec("left", Band(49.3, 45.0, 16, 40, 0.2), polarity="dark_to_light"),
        LineSpec("right", Band(78.7, 51.0, 16, 40, 0.2), polarity="light_to_dark"),
        DistanceSpec("gap", "right", "left", low=29.5, high=30.5),
        DistanceSpec("parallel", "right", "left", value="angle"),
        EdgeSpec("edge", Band(64, 48, 60, 3, 0.2), polarity="light_to_dark"),
        DistanceSpec("edge_to_left", "edge", "left"),
    ]
    got = {m.name: m for m in measure(image, specs)}
    assert abs(got["gap"].value) == pytest.approx(30.0, abs=0.05)
    assert got["gap"].passed is (29.5 <= got["gap"].value <= 30.5)
    assert got["parallel"].value == pytest.approx(0.0, abs=0.01)
    assert got["parallel"].unit == "rad"
    assert abs(got["edge_to_left"].value) == pytest.approx(30.0, abs=0.1)
    assert got["left"].value < 0.1  # straightness, px
    assert got["edge"].value == pytest.approx(45.0, abs=0.1)  # from the band's start


def test_units_state_their_unit_and_scale() -> None:
    assert PixelUnits().to_plane([(3, 4)]).tolist() == [[3, 4]]
    assert ScaleUnits(0.1).to_plane([(3, 4)]) == pytest.approx(np.array([[0.3, 0.4]]))
    assert PlaneUnits(TOOL_CAMERA, WORKING_DISTANCE_MM).mm_per_px == pytest.approx(0.25)
    with pytest.raises(ValueError, match="mm_per_px"):
        ScaleUnits(0.0)


# Coin diameters in scikit-image's coins.png (384x303), measured by hand: grey levels printed
# along the row and the column through each coin's centre (for the row, the longest of the
# chords one row either side), each rim edge read where the level crosses halfway between
# the dark ground (about 30-75) and the rim (about 150-210), interpolating linearly between the
# two pixels either side. The coins are worn and struck off-round, so the horizontal and
# vertical diameters differ; the manual diameter is their mean, its uncertainty half their
# difference plus 0.5 px for the reading. (centre u, v; horizontal, vertical diameter; px)
COINS_BY_HAND = {
    "top right": ((334.1, 43.5), 59.5, 56.1),
    "third row right": ((346.7, 186.5), 64.1, 61.2),
    "second row right": ((336.3, 124.7), 39.0, 39.3),
}


@pytest.mark.parametrize("coin", sorted(COINS_BY_HAND))
def test_coin_diameters_match_a_manual_measurement(coin: str) -> None:
    image = sample_gray("coins.png")
    if image is None:
        pytest.skip(MISSING)
    (u, v), across, down = COINS_BY_HAND[coin]
    by_hand = (across + down) / 2
    uncertainty = abs(across - down) / 2 + 0.5
    spec = CircleSpec(
        coin,
        u,
        v,
        by_hand / 2,
        search=4,
        rays=64,
        polarity="light_to_dark",
        select="last",
        min_strength=15,
    )
    (got,) = measure(image, [spec])
    assert got.unit == "px"
    assert got.value == pytest.approx(by_hand, abs=uncertainty)
    # off-round as measured by hand: the radius spreads at least by the axes' difference / 2
    assert got.extra["roundness"] >= abs(across - down) / 2 - 0.5
