"""detect_board: corners in full-image pixels, with an ROI too; bad input named."""

from __future__ import annotations

import numpy as np
import pytest

from simulation import SimCell, load_scene
from vision_server.analysis import BadImageError, BoardSpec, NotFoundError, RoiError, detect_board

BOARD = BoardSpec("charuco", 11, 8, 0.03, 0.0225)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    return SimCell(load_scene("examples/scenes/intrinsics_cell.yaml")).render("fixed_camera").color


def test_an_roi_gives_the_same_corners_in_full_image_pixels(image: np.ndarray) -> None:
    whole = detect_board(image, BOARD)
    part = detect_board(image, BOARD, roi=(200, 40, 620, 700))
    assert part.ids.tolist() == whole.ids.tolist()
    assert np.abs(part.uv - whole.uv).max() < 0.01


def test_a_board_cut_by_the_roi_gives_the_corners_inside(image: np.ndarray) -> None:
    half = detect_board(image, BOARD, roi=(0, 0, 1024, 384))
    assert 10 < len(half.ids) < 70
    assert (half.uv[:, 1] < 384).all()


def test_colour_and_gray_give_the_same_corners(image: np.ndarray) -> None:
    colour = np.repeat(image[:, :, None], 3, axis=2)
    assert np.abs(detect_board(colour, BOARD).uv - detect_board(image, BOARD).uv).max() < 1e-9


@pytest.mark.parametrize(
    ("bad", "error", "message"),
    [
        (np.zeros((10, 10), np.float32), BadImageError, "8-bit"),
        (np.zeros((10, 10, 4), np.uint8), BadImageError, "1 or 3 channels"),
        (np.zeros((0, 10), np.uint8), BadImageError, "non-empty"),
    ],
)
def test_bad_images_are_named(bad: np.ndarray, error: type[Exception], message: str) -> None:
    with pytest.raises(error, match=message):
        detect_board(bad, BOARD)


def test_an_roi_outside_the_image_is_named(image: np.ndarray) -> None:
    with pytest.raises(RoiError, match="does not lie inside the 1024x768 image"):
        detect_board(image, BOARD, roi=(900, 0, 200, 100))


def test_a_board_of_another_dictionary_is_not_found(image: np.ndarray) -> None:
    wrong = BoardSpec("charuco", 11, 8, 0.03, 0.0225, "DICT_6X6_250")
    with pytest.raises(NotFoundError, match="ArUco markers decoded"):
        detect_board(image, wrong)
