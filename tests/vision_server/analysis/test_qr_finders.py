"""The finder patterns' centres (issue 18 part 3): where the printed code puts them, whatever
the corners' own edge bias, on the simulated RGB-D camera's colour image."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from vision_server.analysis.qr import gray_for_code, read_qr
from vision_server.analysis.qr_finders import finder_centres

from .conftest import qr_cell, random_view


def _true_centres(corners_uv: np.ndarray, modules: int) -> np.ndarray:
    """The finders' centres (modules 3.5 from the code's edges) through the homography of the
    code's true corners."""
    n = modules
    square = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)
    h = cv2.getPerspectiveTransform(square, corners_uv.astype(np.float32))
    centres = np.array([[[3.5, 3.5]], [[n - 3.5, 3.5]], [[3.5, n - 3.5]]], np.float32)
    return np.asarray(cv2.perspectiveTransform(centres, h).reshape(-1, 2), np.float64)


@pytest.fixture(scope="module")
def frame():  # type: ignore[no-untyped-def]
    cell = qr_cell(5)
    cell.world.base_from_tool = random_view(np.random.default_rng(2))
    return cell.render("rgbd")


def test_the_centres_are_where_the_code_puts_them(frame) -> None:  # type: ignore[no-untyped-def]
    code = read_qr(frame.color)[0]
    assert code.modules == 25  # the decoder's version, passed on
    truth = _true_centres(frame.truth.qr_codes["qr"].corners_uv, code.modules)
    found = finder_centres(gray_for_code(frame.color), code.corners, code.modules)
    assert found is not None
    np.testing.assert_allclose(found, truth, atol=0.05)


def test_the_corners_edge_bias_does_not_move_the_centres(frame) -> None:  # type: ignore[no-untyped-def]
    # corners read 0.1 px inwards on every side (three times the detector's bias on this
    # camera) shrink the code's side by 0.2 px but leave the finders where they are
    code = read_qr(frame.color)[0]
    gray = gray_for_code(frame.color)
    centre = code.corners.mean(axis=0)
    diagonal = code.corners - centre
    shrunk = code.corners - 0.1 * np.sqrt(2.0) * diagonal / np.linalg.norm(
        diagonal, axis=1, keepdims=True
    )
    found = finder_centres(gray, code.corners, 25)
    moved = finder_centres(gray, shrunk, 25)
    assert found is not None
    assert moved is not None
    np.testing.assert_allclose(moved, found, atol=0.01)


def test_a_wrong_module_count_finds_no_finders(frame) -> None:  # type: ignore[no-untyped-def]
    code = read_qr(frame.color)[0]
    gray = gray_for_code(frame.color)
    assert finder_centres(gray, code.corners, 29) is None
    with pytest.raises(ValueError, match="modules"):
        finder_centres(gray, code.corners, 24)
    with pytest.raises(ValueError, match="px_per_module"):
        finder_centres(gray, code.corners, 25, px_per_module=3)
