"""The server-drawn overlay's text (vision_server/inspections/base.py): about 1/30 of the image's
height and never below 14 px, on a dark box, the verdict in green or red with a black outline;
what a try shows and the result log stores (here: magnet_check's real overlay)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from vision_server.commands.golden import load_case
from vision_server.inspections import InspectionInput
from vision_server.inspections.base import (
    GREEN,
    LABEL_BACKING,
    MIN_TEXT_PX,
    RED,
    draw_text,
    draw_verdict,
    text_px,
    verdict_bottom,
)

CASES = Path(__file__).resolve().parents[2] / "test_inspections"


def _rows_of(canvas: np.ndarray, colour: tuple[int, int, int], box: tuple[int, ...]) -> int:
    """How many rows of ``box`` (left, top, right, bottom) hold ``colour`` (the text's height)."""
    left, top, right, bottom = box
    patch = canvas[top:bottom, left:right].astype(int)
    hits = np.nonzero((np.abs(patch - np.array(colour)).max(axis=2) <= 30).any(axis=1))[0]
    return int(hits[-1] - hits[0] + 1) if hits.size else 0


@pytest.mark.parametrize(
    ("rows", "expected"), [(120, 14.0), (240, 14.0), (768, 25.6), (2048, 68.3)]
)
def test_text_is_a_thirtieth_of_the_image_and_never_below_14_px(rows: int, expected: float) -> None:
    assert text_px(np.zeros((rows, rows, 3), np.uint8)) == pytest.approx(expected, abs=0.05)


@pytest.mark.parametrize("rows", [240, 768, 2048])
def test_a_label_is_as_tall_as_promised_on_a_dark_box(rows: int) -> None:
    canvas = np.full((rows, rows * 4 // 3, 3), 200, np.uint8)  # a bright part
    box = draw_text(canvas, "HOLE 1", (20, rows // 2), GREEN)
    tall = _rows_of(canvas, GREEN, box)
    # capitals without descenders: about the promised height (antialiasing adds a pixel)
    assert tall == pytest.approx(text_px(canvas), rel=0.2)
    assert tall >= MIN_TEXT_PX - 1
    # the box behind the letters is dark: the label reads on a bright part
    left, top, right, bottom = box
    corner = canvas[top + 1, left + 1].astype(int)
    assert corner.max() < 100
    assert abs(int(corner[0]) - (LABEL_BACKING[0] * 0.7 + 200 * 0.3)) <= 2


def test_a_label_stays_inside_the_image_and_is_cut_to_its_width() -> None:
    canvas = np.full((120, 160, 3), 128, np.uint8)
    left, top, right, bottom = draw_text(
        canvas, "a reason far longer than this small image is wide", (150, 5), (255, 255, 255)
    )
    assert 0 <= left < right <= 160
    assert 0 <= top < bottom <= 120


@pytest.mark.parametrize(("passed", "colour"), [(True, GREEN), (False, RED)])
def test_the_verdict_is_large_in_its_colour_with_a_black_outline_on_a_solid_box(
    passed: bool, colour: tuple[int, int, int]
) -> None:
    canvas = np.full((768, 1024, 3), 128, np.uint8)
    draw_verdict(canvas, passed, "dark_fraction = 0.000")
    bottom = verdict_bottom(canvas)
    word = (10, 10, 150, bottom)
    assert _rows_of(canvas, colour, word) >= 1.3 * text_px(canvas)  # 1.5x a label's height
    region = canvas[10:bottom, 10:100].reshape(-1, 3)  # the box around the word
    assert (region.max(axis=1) <= 5).sum() > 50  # the outline: black around the letters
    assert not (np.abs(region.astype(int) - 128).max(axis=1) <= 2).any()  # nothing grey shows
    # the detail in white beside the word
    assert _rows_of(canvas, (255, 255, 255), (150, 10, 1000, bottom)) >= text_px(canvas)


def test_magnet_checks_stored_overlay_says_fail_in_red_in_large_type() -> None:
    case = load_case(CASES / "example_cell_magnet_check")
    image = cv2.imread(str(case.images_dir / "empty.png"), cv2.IMREAD_UNCHANGED)
    outcome = case.inspection.run(InspectionInput(image), overlay=True)
    assert not outcome.passed
    overlay = outcome.overlay
    assert overlay is not None
    tall = _rows_of(overlay, RED, (10, 10, 160, verdict_bottom(overlay)))
    assert tall >= 32  # 768 rows: the verdict is about 38 px tall, the old one 14
