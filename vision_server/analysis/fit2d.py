"""Plane geometry on measured points: line and circle fits, point-to-line and line-to-line
distances and angles.

Pure functions on ``(N, 2)`` arrays in one frame and unit, whatever they are (image pixels,
or millimetres on the measuring plane after :mod:`.plane_units`): the results are in the
same. Angles in radians, from the first axis towards the second (+u towards +v in image
pixels: clockwise on the screen).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import NotFoundError
from .locate import _fit_circle_algebraic, _fit_circle_geometric

__all__ = [
    "Circle",
    "Line",
    "fit_circle",
    "fit_line",
    "line_line",
    "point_line_distance",
]

FloatArray = NDArray[np.float64]

_OUTLIER_MADS = 3.0  # a point further than this many robust sigmas from the fit is dropped


@dataclass(frozen=True)
class Line:
    """A fitted line: through ``(x, y)`` (the points' centroid) along the unit ``(dx, dy)``;
    ``extent``: the points' span along it; ``straightness``: max - min signed distance of the
    points used from the line (0 for a perfect line)."""

    x: float
    y: float
    dx: float
    dy: float
    extent: float = 0.0
    straightness: float = 0.0

    @property
    def angle_rad(self) -> float:
        """Direction from the first axis towards the second, in (-pi/2, pi/2]."""
        angle = math.atan2(self.dy, self.dx)
        if angle <= -math.pi / 2:
            angle += math.pi
        elif angle > math.pi / 2:
            angle -= math.pi
        return angle


@dataclass(frozen=True)
class Circle:
    """A fitted circle: centre ``(x, y)``, ``radius``; ``roundness``: max - min distance of
    the points used from the centre (0 for a perfect circle); ``used``: how many points."""

    x: float
    y: float
    radius: float
    roundness: float = 0.0
    used: int = 0

    @property
    def diameter(self) -> float:
        return 2.0 * self.radius


def _points(points: object, needed: int, what: str) -> FloatArray:
    array = np.asarray(points, np.float64).reshape(-1, 2)
    array = array[np.isfinite(array).all(axis=1)]
    if len(array) < needed:
        raise NotFoundError(f"a {what} needs {needed} points or more, got {len(array)}")
    return array


def fit_line(points: object) -> Line:
    """Total least squares line through ``points`` (N >= 2, (N, 2)), points further than
    three robust sigmas from it dropped once (e.g. a burr or a speck of dust).

    Raises NotFoundError with fewer than 2 points.
    """
    array = _points(points, 2, "line")

    def solve(pts: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        centre = pts.mean(axis=0)
        _, _, vt = np.linalg.svd(pts - centre)
        direction = vt[0]
        normal = np.array([-direction[1], direction[0]])
        return centre, direction, (pts - centre) @ normal

    centre, direction, residual = solve(array)
    spread = 1.4826 * float(np.median(np.abs(residual)))
    keep = np.abs(residual) <= max(_OUTLIER_MADS * spread, 1e-9)
    if 2 <= int(keep.sum()) < len(array):
        array = array[keep]
        centre, direction, residual = solve(array)
    if direction[0] < 0 or (direction[0] == 0 and direction[1] < 0):
        direction = -direction  # one orientation for one line: along +x
        residual = -residual
    along = (array - centre) @ direction
    return Line(
        float(centre[0]),
        float(centre[1]),
        float(direction[0]),
        float(direction[1]),
        float(along.max() - along.min()),
        float(residual.max() - residual.min()),
    )


def fit_circle(points: object) -> Circle:
    """Least squares circle through ``points`` (N >= 3; an arc is enough), points further
    than three robust sigmas from it dropped (twice at most).

    Raises NotFoundError with fewer than 3 points or points on a line.
    """
    array = _points(points, 3, "circle")
    start = _fit_circle_algebraic(array)
    if not (math.isfinite(start[2]) and start[2] > 0):
        raise NotFoundError("the points lie on a line: no circle through them")
    fit = _fit_circle_geometric(array, start)
    for _ in range(2):
        residual = np.hypot(array[:, 0] - fit[0], array[:, 1] - fit[1]) - fit[2]
        spread = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
        keep = np.abs(residual) <= max(_OUTLIER_MADS * spread, 1e-9)
        if int(keep.sum()) < 3 or keep.all():
            break
        array = array[keep]
        fit = _fit_circle_geometric(array, fit)
    if not all(math.isfinite(x) for x in fit) or fit[2] <= 0:
        raise NotFoundError("the circle fit diverged (points too few or too scattered)")
    radial = np.hypot(array[:, 0] - fit[0], array[:, 1] - fit[1])
    return Circle(fit[0], fit[1], fit[2], float(radial.max() - radial.min()), len(array))


def point_line_distance(point: tuple[float, float], line: Line) -> float:
    """Signed distance of ``point`` from ``line``: positive on the side its direction turned
    by +90 degrees points to (+v of a line along +u)."""
    return (point[0] - line.x) * -line.dy + (point[1] - line.y) * line.dx


def line_line(first: Line, second: Line) -> tuple[float, float]:
    """Distance and angle between two lines: the distance of ``second``'s centre from
    ``first`` (signed as :func:`point_line_distance`; for nearly parallel edges, the gap
    between them) and the angle from ``first`` to ``second`` in (-pi/2, pi/2] (0: parallel)."""
    angle = math.atan2(
        first.dx * second.dy - first.dy * second.dx, first.dx * second.dx + first.dy * second.dy
    )
    if angle <= -math.pi / 2:
        angle += math.pi
    elif angle > math.pi / 2:
        angle -= math.pi
    return point_line_distance((second.x, second.y), first), angle
