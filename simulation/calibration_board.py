"""Calibration boards of the simulated cell: ChArUco (OpenCV's aruco layout) or chessboard.

The print is laid out on a grid of cells (a chessboard square is 1 cell; a ChArUco square is
``CHARUCO_CELLS`` cells so that a 4x4 marker with its one-bit border, 6 bits wide, covers 6
cells exactly), drawn by OpenCV at one pixel per cell; its dark runs become the quads the
renderer draws, exact to the metre.

Board frame of the spec (as for QR boards): origin at the centre of the print, x to the right,
y up the print, z out of it. OpenCV's board frame (the one corner positions are given in:
origin at the print's top-left corner, x right, y down, z into the print) is
``world_from_board @ spec_from_opencv(spec)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "CHARUCO_CELLS",
    "CalibrationBoardSpec",
    "board_dark_quads",
    "dark_cells",
    "spec_from_opencv",
]

FloatArray = NDArray[np.float64]
CHARUCO_CELLS = 8  # cells per ChArUco square; markers are 6 cells (marker_m = 0.75 square_m)
CHARUCO_MARKER_CELLS = 6


@dataclass(frozen=True)
class CalibrationBoardSpec:
    """A flat calibration board: ``kind`` 'charuco' (dictionary DICT_4X4_50, markers 0.75 of
    a square) or 'chessboard'; ``columns`` x ``rows`` squares of ``square_m`` metres; a white
    ``margin_m`` around the squares. ``mount`` 'fixed': ``world_from_board`` is the board's
    pose in the cell; 'tool': the board is bolted to the flange (for eye-to-hand calibration)
    and the same field holds ``tool_from_board`` (use :meth:`world_pose`)."""

    name: str
    kind: str
    columns: int
    rows: int
    square_m: float
    margin_m: float
    world_from_board: FloatArray
    dark: tuple[float, float, float] = (20.0, 20.0, 20.0)
    light: tuple[float, float, float] = (235.0, 235.0, 235.0)
    mount: str = "fixed"

    def world_pose(self, world_from_tool: FloatArray) -> FloatArray:
        """``world_from_board`` (spec frame) with the tool at ``world_from_tool``."""
        if self.mount == "tool":
            pose: FloatArray = world_from_tool @ self.world_from_board
            return pose
        return self.world_from_board.copy()

    @property
    def marker_m(self) -> float:
        """The side of a ChArUco marker in metres."""
        return self.square_m * CHARUCO_MARKER_CELLS / CHARUCO_CELLS

    @property
    def size_m(self) -> tuple[float, float]:
        """Width and height of the squares' area (without the margin), metres."""
        return self.columns * self.square_m, self.rows * self.square_m


@lru_cache(maxsize=8)
def _dark_cells(kind: str, columns: int, rows: int) -> bytes:
    if kind == "charuco":
        dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
        board = cv2.aruco.CharucoBoard((columns, rows), 1.0, 0.75, dictionary)
        size = (columns * CHARUCO_CELLS, rows * CHARUCO_CELLS)
        image = board.generateImage(size, marginSize=0, borderBits=1)
    elif kind == "chessboard":
        # OpenCV's chessboard detector needs no particular colour at the top-left square.
        yy, xx = np.mgrid[0:rows, 0:columns]
        image = np.where((xx + yy) % 2 == 0, 0, 255).astype(np.uint8)
    else:
        raise ValueError(f"unknown board kind {kind!r} (known: charuco, chessboard)")
    dark = np.asarray(image) < 128
    return int(dark.shape[1]).to_bytes(4, "little") + bytes(np.packbits(dark).tobytes())


def dark_cells(kind: str, columns: int, rows: int) -> NDArray[np.bool_]:
    """The print as cells (rows, columns of cells), True = dark, row 0 at the top."""
    raw = _dark_cells(kind, columns, rows)
    width = int.from_bytes(raw[:4], "little")
    bits = np.unpackbits(np.frombuffer(raw[4:], dtype=np.uint8))
    height = (columns * rows * (CHARUCO_CELLS**2 if kind == "charuco" else 1)) // width
    return bits[: width * height].reshape(height, width).astype(bool)


def board_dark_quads(spec: CalibrationBoardSpec) -> FloatArray:
    """Spec-frame quads (R, 4, 3) of the horizontal runs of dark cells, metres."""
    cells = dark_cells(spec.kind, spec.columns, spec.rows)
    cell_m = spec.square_m / (CHARUCO_CELLS if spec.kind == "charuco" else 1)
    width_m, height_m = spec.size_m
    quads = []
    for i, row in enumerate(cells):
        padded = np.concatenate([[False], row, [False]])
        edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
        y_top, y_bottom = height_m / 2 - i * cell_m, height_m / 2 - (i + 1) * cell_m
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            x0, x1 = -width_m / 2 + start * cell_m, -width_m / 2 + stop * cell_m
            quads.append(
                [[x0, y_bottom, 0.0], [x1, y_bottom, 0.0], [x1, y_top, 0.0], [x0, y_top, 0.0]]
            )
    return np.array(quads, dtype=np.float64)


def spec_from_opencv(spec: CalibrationBoardSpec) -> FloatArray:
    """The 4x4 transform from OpenCV's board frame (origin at the top-left corner of the
    squares, x right, y down, z into the print) to the spec's frame, metres."""
    width_m, height_m = spec.size_m
    result: FloatArray = np.array(
        [
            [1.0, 0.0, 0.0, -width_m / 2],
            [0.0, -1.0, 0.0, height_m / 2],
            [0.0, 0.0, -1.0, 0.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    return result
