"""How well views of a calibration board cover a camera's image and the tilts of the board.

Intrinsics are only as good as the views behind them: the distortion is known where corners
were seen (so the corners of the image must be covered) and the focal length is told apart
from the distance only by views in which the board is tilted. :func:`board_coverage` counts
corners per cell of a ``GRID`` over the image and sorts each view's board tilt into one of
``TILTS``, with the board's pose solved under the intrinsics given (a nominal guess will do).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from geometry import CameraIntrinsics

if TYPE_CHECKING:
    from .board_view import BoardView

__all__ = ["GRID", "MIN_CELL_CORNERS", "TILTS", "Coverage", "board_coverage", "view_tilt"]

GRID = (3, 3)  # (columns, rows) of image regions
MIN_CELL_CORNERS = 10  # corners a region needs over all views to count as covered
TILT_MIN_DEG = 15.0  # a board tilted less than this is "frontal"
TILTS = ("frontal", "tilted left", "tilted right", "tilted up", "tilted down")
REGION_NAMES = (
    ("top left", "top", "top right"),
    ("left", "centre", "right"),
    ("bottom left", "bottom", "bottom right"),
)


@dataclass(frozen=True)
class Coverage:
    """``corners``: corner counts per image region, ``(rows, columns)`` of ``GRID``;
    ``tilts``: how many views of each of ``TILTS``; ``missing_regions`` and ``missing_tilts``:
    what still has to be shown (regions named as in ``REGION_NAMES``)."""

    corners: tuple[tuple[int, ...], ...]
    tilts: dict[str, int]
    missing_regions: tuple[str, ...]
    missing_tilts: tuple[str, ...]

    @property
    def complete(self) -> bool:
        return not self.missing_regions and not self.missing_tilts

    def describe(self) -> str:
        """One line for people: what is covered and what is missing."""
        covered = sum(1 for row in self.corners for n in row if n >= MIN_CELL_CORNERS)
        total = GRID[0] * GRID[1]
        text = f"image regions covered {covered}/{total}; tilts " + ", ".join(
            f"{name} {count}" for name, count in self.tilts.items()
        )
        if self.complete:
            return text + "; coverage complete"
        missing = [*self.missing_regions, *self.missing_tilts]
        return text + "; missing: " + ", ".join(missing)


def view_tilt(view: BoardView, intrinsics: CameraIntrinsics) -> tuple[str, float]:
    """The tilt class of ``TILTS`` of a view and the tilt angle in degrees (the angle between
    the board's normal and the camera's optical axis)."""
    k, dist = intrinsics.matrix, np.asarray(intrinsics.dist)
    ok, rvec, _ = cv2.solvePnP(view.object_points, view.uv, k, dist)
    if not ok:
        return "frontal", math.nan
    rotation, _ = cv2.Rodrigues(rvec)
    normal = rotation[:, 2]  # the board's z in the camera frame (into the board)
    if normal[2] < 0:
        normal = -normal  # the board seen from its back: only the axis matters
    angle = math.degrees(math.acos(min(1.0, float(normal[2]))))
    if angle < TILT_MIN_DEG:
        return "frontal", angle
    # The normal leans towards +x when the board's right side is farther than its left.
    if abs(normal[0]) >= abs(normal[1]):
        return ("tilted right" if normal[0] > 0 else "tilted left"), angle
    return ("tilted down" if normal[1] > 0 else "tilted up"), angle


def board_coverage(views: Sequence[BoardView], intrinsics: CameraIntrinsics) -> Coverage:
    """The coverage of the image and of the tilts by ``views`` (pixels of images of
    ``intrinsics.width`` x ``intrinsics.height``)."""
    columns, rows = GRID
    counts = np.zeros((rows, columns), dtype=np.int64)
    tilts = dict.fromkeys(TILTS, 0)
    for view in views:
        col = np.clip((view.uv[:, 0] * columns / intrinsics.width).astype(int), 0, columns - 1)
        row = np.clip((view.uv[:, 1] * rows / intrinsics.height).astype(int), 0, rows - 1)
        np.add.at(counts, (row, col), 1)
        if len(view.uv) >= 4:
            tilts[view_tilt(view, intrinsics)[0]] += 1
    missing_regions = tuple(
        REGION_NAMES[r][c]
        for r in range(rows)
        for c in range(columns)
        if counts[r, c] < MIN_CELL_CORNERS
    )
    missing_tilts = tuple(name for name, n in tilts.items() if n == 0)
    return Coverage(
        tuple(tuple(int(n) for n in row) for row in counts), tilts, missing_regions, missing_tilts
    )
