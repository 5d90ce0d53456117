"""One image of a calibration board as the solvers take it (shared by the intrinsics solver and
the coverage report, which must not import each other)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BoardView:
    """One image of the board: ``uv`` (N, 2) pixels, ``object_points`` (N, 3) board frame in
    metres (z = 0), ``label`` a name for reports (e.g. ``"view 3"`` or a file name)."""

    uv: FloatArray
    object_points: FloatArray
    label: str


__all__ = ["BoardView"]
