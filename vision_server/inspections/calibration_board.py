"""``calibration_board``: the inner corners of a ChArUco board or a chessboard, sub-pixel,
with their ids and board positions: the views that camera calibration is solved from."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from yamlfile import Node, one_of, positive, positive_int

from ..analysis import (
    BOARD_KINDS,
    DICTIONARIES,
    AnalysisError,
    BoardSpec,
    NotFoundError,
    detect_board,
)
from ..cameras import CameraSettings
from .base import Common, Configured, analysis_failed, draw_verdict, overlay_base, parse_common
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number

RED = (0, 0, 255)


@dataclass(frozen=True)
class CalibrationBoardInspection(Configured):
    """``board``: the printed board; ``min_corners``: corners needed for a pass."""

    common: Common
    board: BoardSpec
    min_corners: int

    type = "calibration_board"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        try:
            found = detect_board(
                image.color, self.board, roi=self.common.roi, min_corners=self.min_corners
            )
        except NotFoundError as exc:
            picture = None
            if overlay:
                picture = draw_verdict(overlay_base(image.color, self.common.roi), False, str(exc))
            return InspectionOutcome(
                False, {"found": False, "count": 0, "reason": str(exc)}, picture
            )
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        height, width = image.color.shape[:2]
        data: dict[str, Any] = {
            "found": True,
            "board": self.board.kind,
            "squares": [self.board.columns, self.board.rows],
            "square_m": self.board.square_m,
            "count": len(found.ids),
            "of": self.board.corner_count,
            "markers": found.markers,
            "image_size": [width, height],
            "ids": [int(i) for i in found.ids],
            "corners": [[float(u), float(v)] for u, v in found.uv],
            "object_points": [[float(c) for c in p] for p in found.object_points],
        }
        picture = None
        if overlay:
            picture = overlay_base(image.color, self.common.roi)
            for u, v in np.round(found.uv).astype(int):
                cv2.drawMarker(picture, (int(u), int(v)), RED, cv2.MARKER_CROSS, 10, 1)
            draw_verdict(picture, True, f"{len(found.ids)}/{self.board.corner_count} corners")
        return InspectionOutcome(True, data, picture)


def parse_board(node: Node) -> BoardSpec:
    """The ``board:`` mapping: kind, columns, rows, square_m (and marker_m, dictionary)."""
    sub = node.sub("board")
    kind = sub.take("kind", one_of(*BOARD_KINDS))
    columns = sub.take("columns", positive_int)
    rows = sub.take("rows", positive_int)
    for key, count in (("columns", columns), ("rows", rows)):
        if count < 3:  # named here: the board's own check names no key
            raise sub.error(f"a board needs at least 3 x 3 squares, got {count} {key}", key)
    square = sub.take("square_m", positive)
    marker = sub.take("marker_m", positive) if kind == "charuco" else 0.0
    dictionary = (
        sub.take("dictionary", one_of(*DICTIONARIES), "DICT_4X4_50")
        if kind == "charuco"
        else "DICT_4X4_50"
    )
    sub.finish()
    try:
        return BoardSpec(kind, columns, rows, square, marker, dictionary)
    except ValueError as exc:
        raise sub.error(str(exc)) from None


def parse_calibration_board(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> CalibrationBoardInspection:
    common = parse_common(node, "calibration_board", cameras)
    board = parse_board(node)
    return CalibrationBoardInspection(common, board, node.take("min_corners", positive_int, 6))


def _expected(data: Data) -> dict[str, Any]:
    return {"count": data["count"]} if data.get("found") else {}


def _summary(data: Data) -> dict[str, float]:
    return {"count": as_number(data, "count")}


RESULTS = ResultKind(("count",), _expected, _summary)
"""A calibration-board result: how many corners were found (a golden case checks the count;
the corners' accuracy is the simulated cell's test, tests/robot_client/test_intrinsics.py)."""
