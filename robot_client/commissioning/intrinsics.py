"""Camera intrinsics from views of a calibration board: solve, judge each view, report.

:func:`solve_intrinsics` takes the corners of several :class:`BoardView` s (image pixels
``(u, v)`` and board-frame points in metres, as the ``calibration_board`` inspection returns
them) and solves the pinhole intrinsics and the distortion ``(k1, k2, p1, p2, k3)`` with
OpenCV's ``calibrateCameraExtended``. Views whose reprojection error stands out are dropped
with a reason and the rest solved again. The parameters' standard deviations come from the
Jacobian at the solution (OpenCV's estimate, scaled by the residual).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from geometry import CameraIntrinsics

from .board_view import BoardView
from .coverage import Coverage, board_coverage

__all__ = [
    "PARAMETERS",
    "BoardView",
    "CalibrationError",
    "IntrinsicsSolution",
    "ViewError",
    "solve_intrinsics",
]

FloatArray = NDArray[np.float64]
PARAMETERS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
MIN_VIEWS = 4
MIN_CORNERS = 8  # a view with fewer corners hardly constrains its own pose
OUTLIER_FACTOR = 3.0  # a view is an outlier at this many times the median view RMS ...
OUTLIER_FLOOR_PX = 0.3  # ... but never below this (a clean set has medians near 0.05 px)


class CalibrationError(ValueError):
    """The views cannot give intrinsics (too few usable views); the message says why."""


@dataclass(frozen=True)
class ViewError:
    """A view's RMS reprojection error in pixels at the solution (NaN when it was not
    solved); ``used`` False with a ``reason`` when it was left out."""

    label: str
    corners: int
    rms_px: float
    used: bool
    reason: str | None = None


@dataclass(frozen=True)
class IntrinsicsSolution:
    """The intrinsics solved; ``rms_px`` the RMS reprojection error over every corner of the
    views used; ``std`` one standard deviation per parameter of ``PARAMETERS`` (pixels for
    fx, fy, cx, cy; none for the distortion coefficients); ``views`` one entry per view given."""

    intrinsics: CameraIntrinsics
    rms_px: float
    std: dict[str, float]
    views: tuple[ViewError, ...]
    coverage: Coverage

    @property
    def used(self) -> int:
        return sum(1 for v in self.views if v.used)


def _calibrate(
    views: Sequence[BoardView], size: tuple[int, int]
) -> tuple[float, FloatArray, FloatArray, FloatArray, list[FloatArray], list[FloatArray]]:
    objects = [v.object_points.astype(np.float32).reshape(-1, 1, 3) for v in views]
    images = [v.uv.astype(np.float32).reshape(-1, 1, 2) for v in views]
    width, height = size
    # Start from a pinhole guess (focal length about the image width, centred): OpenCV's own
    # start from homographies is fine for most boards, but a guess keeps a few views stable.
    guess = np.array([[width, 0.0, (width - 1) / 2], [0.0, width, (height - 1) / 2], [0, 0, 1.0]])
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, k, dist, rvecs, tvecs, std_intr, _, per_view = cv2.calibrateCameraExtended(
        objects,
        images,
        size,
        guess,
        np.zeros(5),
        flags=cv2.CALIB_USE_INTRINSIC_GUESS,
        criteria=criteria,
    )
    return (
        float(rms),
        np.asarray(k, np.float64),
        np.asarray(dist, np.float64).reshape(-1)[:5],
        np.asarray(std_intr, np.float64).reshape(-1)[: len(PARAMETERS)],
        [np.asarray(r, np.float64) for r in rvecs],
        [np.asarray(per_view, np.float64).reshape(-1)],
    )


def solve_intrinsics(
    views: Sequence[BoardView],
    image_size: tuple[int, int],
    *,
    outlier_factor: float = OUTLIER_FACTOR,
    outlier_floor_px: float = OUTLIER_FLOOR_PX,
) -> IntrinsicsSolution:
    """Solve the intrinsics of a camera whose images are ``image_size`` = (width, height) px.

    Views with fewer than ``MIN_CORNERS`` corners are left out; after a first solution, views
    whose RMS error exceeds ``max(outlier_factor * median, outlier_floor_px)`` are dropped (a
    moved board, motion blur, a misdetection) and the rest solved again. Raises
    :class:`CalibrationError` when fewer than ``MIN_VIEWS`` views are left.
    """
    reasons: dict[int, str] = {}
    for i, view in enumerate(views):
        if len(view.uv) < MIN_CORNERS:
            reasons[i] = f"only {len(view.uv)} corners (at least {MIN_CORNERS} needed)"
    errors: dict[int, float] = {}
    for _ in range(2):
        kept = [i for i in range(len(views)) if i not in reasons]
        if len(kept) < MIN_VIEWS:
            raise CalibrationError(
                f"{len(kept)} usable views of {len(views)}; at least {MIN_VIEWS} are needed "
                f"(left out: {'; '.join(f'{views[i].label}: {r}' for i, r in reasons.items())})"
                if reasons
                else f"{len(kept)} views; at least {MIN_VIEWS} are needed"
            )
        rms, k, dist, std, _, (per_view,) = _calibrate([views[i] for i in kept], image_size)
        errors = dict(zip(kept, (float(e) for e in per_view), strict=True))
        median = float(np.median(per_view))
        limit = max(outlier_factor * median, outlier_floor_px)
        outliers = {i: e for i, e in errors.items() if e > limit}
        if not outliers or len(kept) - len(outliers) < MIN_VIEWS:
            break
        for i, e in outliers.items():
            reasons[i] = (
                f"RMS {e:.3f} px is above {limit:.3f} px ({outlier_factor:g} x the median "
                f"{median:.3f} px): the board moved, blurred or was misdetected"
            )
    width, height = image_size
    intrinsics = CameraIntrinsics(
        width,
        height,
        k[0, 0],
        k[1, 1],
        k[0, 2],
        k[1, 2],
        (dist[0], dist[1], dist[2], dist[3], dist[4]),
    )
    report = tuple(
        ViewError(
            view.label,
            len(view.uv),
            errors.get(i, math.nan) if i not in reasons else _view_rms(view, intrinsics),
            i not in reasons,
            reasons.get(i),
        )
        for i, view in enumerate(views)
    )
    used = [views[i] for i in range(len(views)) if i not in reasons]
    return IntrinsicsSolution(
        intrinsics,
        rms,
        dict(zip(PARAMETERS, (float(s) for s in std), strict=True)),
        report,
        board_coverage(used, intrinsics),
    )


def _view_rms(view: BoardView, intrinsics: CameraIntrinsics) -> float:
    """A left-out view's RMS error in pixels with its own pose solved under ``intrinsics``."""
    if len(view.uv) < 4:
        return math.nan
    k, dist = intrinsics.matrix, np.asarray(intrinsics.dist)
    ok, rvec, tvec = cv2.solvePnP(view.object_points, view.uv, k, dist)
    if not ok:
        return math.nan
    projected, _ = cv2.projectPoints(view.object_points, rvec, tvec, k, dist)
    return float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - view.uv) ** 2, axis=1))))
