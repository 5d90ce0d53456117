"""Presence measures on rendered present/absent cases; the overlay's drawing."""

from __future__ import annotations

import _vision_render as render
import numpy as np
import pytest

from vision_server.vision import (
    Feature,
    ParameterError,
    draw_overlay,
    measure_presence,
)

ROI = [200, 120, 120, 100]


def _case(present: bool, rng: np.random.Generator) -> np.ndarray:
    """A rotor core (bright disc) with, when present, a dark magnet (bar) in the ROI beside it.

    Lighting varies (gain 0.75-1.25, offset -20..20, a gradient), the part shifts by up to
    6 px, noise sigma 3.
    """
    h, w = 300, 480
    uu, vv = np.meshgrid(np.arange(w), np.arange(h))
    img = np.full((h, w), 150.0)
    du, dv = rng.uniform(-6, 6, 2)
    core = render.disc_coverage((150 + du, 170 + dv), 70.0, width=w, height=h, s=2)
    img = img * (1 - core) + 210 * core
    if present:
        magnet = np.zeros((h, w))
        magnet[int(150 + dv) : int(190 + dv), int(235 + du) : int(285 + du)] = 1.0
        img = img * (1 - magnet) + 35 * magnet
    gain, offset = rng.uniform(0.75, 1.25), rng.uniform(-20, 20)
    gradient = rng.uniform(-0.05, 0.05) * (uu - w / 2)
    return render.to_uint8(img * gain + offset + gradient, rng, 3.0)


@pytest.fixture(scope="module")
def cases() -> list[tuple[np.ndarray, bool]]:
    """200 rendered cases, half with the magnet."""
    rng = np.random.default_rng(42)
    return [(_case(k % 2 == 0, rng), k % 2 == 0) for k in range(200)]


@pytest.mark.parametrize(
    ("measure", "options", "lo", "hi"),
    [
        ("dark_fraction", {"threshold": 90}, 0.1, 1.0),
        ("edge_density", {}, 0.02, 1.0),
        ("blob_count", {"threshold": 90, "area_range": (300, 5000)}, 1, 1),
        ("template_score", {}, 0.6, 1.0),
    ],
)
def test_presence_is_right_on_99_percent(
    cases: list, measure: str, options: dict, lo: float, hi: float
) -> None:
    if measure == "template_score":
        options = {"template": _case(True, np.random.default_rng(0))[140:200, 225:295]}
    right = 0
    for image, present in cases:
        m = measure_presence(image, measure=measure, roi=ROI, **options)
        right += (lo <= m.value <= hi) == present
    assert right >= 0.99 * len(cases)


def test_measures_values_and_errors() -> None:
    img = np.zeros((10, 20), np.uint8)
    img[:, 10:] = 200
    m = measure_presence(img, measure="mean_intensity")
    assert m.value == pytest.approx(100.0)
    assert m.roi == (0, 0, 20, 10)
    assert measure_presence(img, measure="bright_fraction", roi=[5, 0, 10, 10]).value == 0.5
    assert measure_presence(img, measure="dark_fraction", threshold=50).value == 0.5
    with pytest.raises(ParameterError, match="measure"):
        measure_presence(img, measure="colour")  # type: ignore[arg-type]


def test_overlay_draws_roi_detections_and_verdict() -> None:
    img = np.full((200, 300), 128, np.uint8)
    out = draw_overlay(
        img,
        roi=[50, 40, 100, 80],
        features=[Feature(u=100.3, v=80.6, radius=20.0), Feature(u=20, v=150, angle=0.5)],
        quads=[[[200, 100], [260, 100], [260, 160], [200, 160]]],
        verdict="PASS",
        passed=True,
    )
    assert out.shape == (200, 300, 3)
    assert out.dtype == np.uint8
    assert tuple(out[40, 100]) == (0, 200, 0)  # ROI edge in green
    assert out[80, 120, 2] > 200  # circle in red
    assert out[80, 120, 1] < 100
    assert img.max() == 128  # input untouched
