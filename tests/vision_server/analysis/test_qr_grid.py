"""The code's corners from its module grid (issue 18 part 3): where the printed code puts them,
whatever the corner detector's own edge bias, on the simulated RGB-D camera's colour image."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from vision_server.analysis.qr import gray_for_code, read_qr
from vision_server.analysis.qr_grid import grid_corners

from .conftest import qr_cell, random_view


def _mean_side(corners: Any) -> float:
    return float(np.mean(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))


@pytest.fixture(scope="module")
def frames() -> list[Any]:
    cell = qr_cell(5)
    rng = np.random.default_rng(2)
    out = []
    for _ in range(4):
        cell.world.base_from_tool = random_view(rng)
        out.append(cell.render("rgbd"))
    return out


def test_the_grid_gives_the_codes_size_without_the_corners_bias(frames: list[Any]) -> None:
    # the detector's corners read the side short (-0.03 px on this camera); the grid's
    # corners are within 0.02 px of the true side on every view
    corner_errors, grid_errors = [], []
    for frame in frames:
        code = read_qr(frame.color)[0]
        assert code.modules == 25  # the decoder's version, passed on
        truth = _mean_side(frame.truth.qr_codes["qr"].corners_uv)
        found = grid_corners(gray_for_code(frame.color), code.corners, code.modules)
        assert found is not None
        grid_errors.append(_mean_side(found) - truth)
        corner_errors.append(_mean_side(code.corners) - truth)
    assert max(np.abs(grid_errors)) < 0.02
    assert float(np.mean(corner_errors)) < -0.015  # what the grid is for


def test_the_corners_edge_bias_does_not_move_the_grid(frames: list[Any]) -> None:
    # corners read 0.1 px inwards on every side (three times the detector's bias on this
    # camera) shrink the side by 0.2 px; the grid's corners stay where they were
    frame = frames[0]
    code = read_qr(frame.color)[0]
    gray = gray_for_code(frame.color)
    centre = code.corners.mean(axis=0)
    diagonal = code.corners - centre
    shrunk = code.corners - 0.1 * np.sqrt(2.0) * diagonal / np.linalg.norm(
        diagonal, axis=1, keepdims=True
    )
    found = grid_corners(gray, code.corners, 25)
    moved = grid_corners(gray, shrunk, 25)
    assert found is not None
    assert moved is not None
    assert abs(_mean_side(moved) - _mean_side(found)) < 0.01


def test_a_wrong_module_count_finds_no_grid(frames: list[Any]) -> None:
    code = read_qr(frames[0].color)[0]
    gray = gray_for_code(frames[0].color)
    assert grid_corners(gray, code.corners, 29) is None
    with pytest.raises(ValueError, match="modules"):
        grid_corners(gray, code.corners, 24)
    with pytest.raises(ValueError, match="px_per_module"):
        grid_corners(gray, code.corners, 25, px_per_module=2)
