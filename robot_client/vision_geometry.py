"""Client-side geometry of the vision skills (reusable by benchmarks).

Vision pick (the paper's Table 1, steps 5-10) and its search planning:

- :func:`pixels_to_plane`: detected (distorted) pixels → undistorted rays → intersection with a
  horizontal plane ``z = height_m`` of a frame (the robot's active base frame).
- :class:`AcceptanceSegment`: the taught start-end line; a point is accepted when its
  projection on the line lies between the two ends.
- :class:`Polygon`, :func:`view_footprint`, :func:`plan_search_grid`, :func:`greedy_order`,
  :func:`tool_pose_viewing`: an arbitrary taught search region, covered by a boustrophedon grid
  of camera stations at the camera's footprint with overlap, visited nearest first.
- :func:`line_stations`: camera stations along the taught line, at most ``step_m`` apart.

Checks: :func:`rotation_error_rad` (the angle between two rotations).

Conventions (docs/conventions.md): ``b_from_a`` 4x4 transforms, metres, radians, pixels
``(u, v)``; a "frame" below is whatever frame the caller uses for the robot (normally its active
base frame, z up).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from geometry import CameraIntrinsics, make_transform, rotation_angle, rotation_from_axis_angle

__all__ = [
    "AcceptanceSegment",
    "Footprint",
    "Polygon",
    "greedy_order",
    "interpolate_pose",
    "line_stations",
    "optical_axis_hit",
    "pixels_to_plane",
    "plan_search_grid",
    "rotation_error_rad",
    "tool_pose_viewing",
    "view_footprint",
]

FloatArray = NDArray[np.float64]


# --- pixels -> rays -> plane ------------------------------------------------------------------


def pixels_to_plane(
    intrinsics: CameraIntrinsics,
    frame_from_camera: ArrayLike,
    uv: ArrayLike,
    height_m: float,
) -> FloatArray:
    """Where the rays through the (distorted) pixels ``uv`` (N, 2) meet the horizontal plane
    ``z = height_m`` of the frame the camera pose ``frame_from_camera`` is given in.

    Returns (N, 3) points in that frame; a row is NaN when its ray does not reach the plane
    (parallel to it, or the plane lies behind the camera).
    """
    pose = np.asarray(frame_from_camera, np.float64)
    rays_camera = intrinsics.pixel_rays(uv)  # undistorts: OpenCV's model, unit vectors
    directions = rays_camera @ pose[:3, :3].T
    origin = pose[:3, 3]
    out = np.full((directions.shape[0], 3), np.nan)
    dz = directions[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (height_m - origin[2]) / dz
    ok = np.isfinite(s) & (s > 0) & (np.abs(dz) > 1e-12)
    out[ok] = origin + s[ok, None] * directions[ok]
    return out


def optical_axis_hit(frame_from_camera: ArrayLike, height_m: float) -> FloatArray | None:
    """Where the camera's optical axis meets the plane ``z = height_m`` (None: it does not)."""
    pose = np.asarray(frame_from_camera, np.float64)
    axis = pose[:3, 2]
    if abs(axis[2]) < 1e-12:
        return None
    s = (height_m - pose[2, 3]) / axis[2]
    if s <= 0:
        return None
    hit: FloatArray = pose[:3, 3] + s * axis
    return hit


# --- the taught line ----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class AcceptanceSegment:
    """The paper's acceptance region: the segment from ``start`` to ``end`` (3,) (the camera
    positions at p_cam,start and p_cam,end). A point is projected on the line through them
    (Table 1, step 9) and accepted when the projection lies between the ends (step 10)."""

    start: FloatArray
    end: FloatArray

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", np.asarray(self.start, np.float64).reshape(3))
        object.__setattr__(self, "end", np.asarray(self.end, np.float64).reshape(3))

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    @property
    def direction(self) -> FloatArray:
        length = self.length
        if length == 0:
            return np.zeros(3)
        d: FloatArray = (self.end - self.start) / length
        return d

    def parameter(self, p: ArrayLike) -> float:
        """Signed distance (metres) from ``start`` along the line of the projection of ``p``."""
        return float((np.asarray(p, np.float64).reshape(3) - self.start) @ self.direction)

    def project(self, p: ArrayLike) -> FloatArray:
        """The projection of ``p`` on the line."""
        result: FloatArray = self.start + self.parameter(p) * self.direction
        return result

    def lateral(self, p: ArrayLike) -> float:
        """Distance (metres) of ``p`` from the line."""
        q = np.asarray(p, np.float64).reshape(3)
        return float(np.linalg.norm(q - self.project(q)))

    def contains(
        self, p: ArrayLike, *, tolerance_m: float = 0.0, max_lateral_m: float | None = None
    ) -> bool:
        """Whether the projection of ``p`` lies between the ends (± ``tolerance_m``), and
        ``p`` lies within ``max_lateral_m`` of the line if that is given."""
        t = self.parameter(p)
        if not (-tolerance_m <= t <= self.length + tolerance_m):
            return False
        return max_lateral_m is None or self.lateral(p) <= max_lateral_m


def _log_rotation(rotation: FloatArray) -> FloatArray:
    """Axis * angle of a rotation matrix (the rotation vector)."""
    angle = rotation_angle(rotation)
    if angle < 1e-12:
        return np.zeros(3)
    if math.pi - angle < 1e-6:
        # near pi: the axis is the eigenvector of the symmetric part
        w, v = np.linalg.eigh((rotation + rotation.T) / 2.0)
        axis = v[:, int(np.argmax(w))]
        return np.asarray(axis * angle, np.float64)
    skew = np.array(
        [
            rotation[2, 1] - rotation[1, 2],
            rotation[0, 2] - rotation[2, 0],
            rotation[1, 0] - rotation[0, 1],
        ]
    )
    return np.asarray(skew / (2.0 * math.sin(angle)) * angle, np.float64)


def rotation_error_rad(a_rotation: ArrayLike, b_rotation: ArrayLike) -> float:
    """The angle (radians) of the rotation between two rotations (3x3 or the 3x3 of 4x4)."""
    a = np.asarray(a_rotation, np.float64)[:3, :3]
    b = np.asarray(b_rotation, np.float64)[:3, :3]
    return rotation_angle(a.T @ b)


def interpolate_pose(a: ArrayLike, b: ArrayLike, s: float) -> FloatArray:
    """The pose a fraction ``s`` of the way from ``a`` to ``b``: translation linearly,
    rotation along the shortest arc."""
    pa, pb = np.asarray(a, np.float64), np.asarray(b, np.float64)
    rel = _log_rotation(pa[:3, :3].T @ pb[:3, :3])
    angle = float(np.linalg.norm(rel))
    rot = pa[:3, :3]
    if angle > 0:
        rot = rot @ rotation_from_axis_angle(rel / angle, s * angle)
    return make_transform(rot, (1.0 - s) * pa[:3, 3] + s * pb[:3, 3])


def line_stations(start: ArrayLike, end: ArrayLike, step_m: float) -> list[FloatArray]:
    """Poses from ``start`` to ``end`` (both included), evenly spaced at most ``step_m``
    apart: where the robot stops to capture while searching along the taught line."""
    if not step_m > 0:
        raise ValueError(f"step_m must be positive, got {step_m}")
    pa, pb = np.asarray(start, np.float64), np.asarray(end, np.float64)
    length = float(np.linalg.norm(pb[:3, 3] - pa[:3, 3]))
    n = max(1, math.ceil(length / step_m - 1e-9))
    if length == 0:
        return [pa.copy()]
    return [interpolate_pose(pa, pb, i / n) for i in range(n + 1)]


# --- a taught search region -------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Polygon:
    """A simple polygon in the horizontal plane: ``vertices`` (N, 2), N >= 3, x-y in metres."""

    vertices: FloatArray

    def __post_init__(self) -> None:
        v = np.asarray(self.vertices, np.float64)
        if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"a polygon needs at least 3 finite (x, y) vertices, got {v.shape}")
        object.__setattr__(self, "vertices", v)
        if self.area <= 0:
            raise ValueError("the polygon has no area (collinear vertices?)")

    @classmethod
    def from_flat(cls, values: Sequence[float]) -> Polygon:
        """From ``[x0, y0, x1, y1, ...]`` (how a skill parameter stores it)."""
        if len(values) % 2 or len(values) < 6:
            raise ValueError(
                f"a region is x0, y0, x1, y1, ... with at least 3 vertices, got {len(values)} "
                f"numbers"
            )
        return cls(np.asarray(values, np.float64).reshape(-1, 2))

    @property
    def area(self) -> float:
        x, y = self.vertices[:, 0], self.vertices[:, 1]
        return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2.0)

    @property
    def centroid(self) -> FloatArray:
        c: FloatArray = self.vertices.mean(axis=0)
        return c

    def contains(self, xy: ArrayLike) -> bool:
        """Whether the point ``xy`` (2,) (or (3,), z ignored) lies inside (even-odd rule)."""
        p = np.asarray(xy, np.float64).reshape(-1)[:2]
        inside = False
        v = self.vertices
        n = len(v)
        for i in range(n):
            (x1, y1), (x2, y2) = v[i], v[(i + 1) % n]
            if (y1 > p[1]) != (y2 > p[1]):
                x_cross = x1 + (p[1] - y1) * (x2 - x1) / (y2 - y1)
                if p[0] < x_cross:
                    inside = not inside
        return inside

    def distance(self, xy: ArrayLike) -> float:
        """Distance (metres) from ``xy`` to the polygon (0 inside)."""
        p = np.asarray(xy, np.float64).reshape(-1)[:2]
        if self.contains(p):
            return 0.0
        best = math.inf
        v = self.vertices
        for a, b in zip(v, np.roll(v, -1, axis=0), strict=True):
            ab = b - a
            t = float(np.clip((p - a) @ ab / max(float(ab @ ab), 1e-300), 0.0, 1.0))
            best = min(best, float(np.linalg.norm(p - (a + t * ab))))
        return best

    def overlaps_rectangle(
        self, centre: ArrayLike, half: tuple[float, float], angle: float
    ) -> bool:
        """Whether the rectangle (``centre`` (2,), half extents along its own axes, rotated by
        ``angle`` about z) and the polygon share area (or touch)."""
        c = np.asarray(centre, np.float64).reshape(2)
        ca, sa = math.cos(angle), math.sin(angle)
        axes = np.array([[ca, sa], [-sa, ca]])  # rows: the rectangle's x and y axes
        corners = np.array(
            [c + axes.T @ np.array([sx * half[0], sy * half[1]]) for sx, sy in _CORNER_SIGNS]
        )
        if any(self.contains(p) for p in corners) or self.contains(c):
            return True
        local = (self.vertices - c) @ axes.T
        if np.any((np.abs(local[:, 0]) <= half[0]) & (np.abs(local[:, 1]) <= half[1])):
            return True
        rect = Polygon(corners)
        return any(
            _segments_cross(a, b, p, q)
            for a, b in _edges(self.vertices)
            for p, q in _edges(rect.vertices)
        )


_CORNER_SIGNS = ((-1, -1), (1, -1), (1, 1), (-1, 1))


def _edges(v: FloatArray) -> list[tuple[FloatArray, FloatArray]]:
    return [(v[i], v[(i + 1) % len(v)]) for i in range(len(v))]


def _segments_cross(a: FloatArray, b: FloatArray, p: FloatArray, q: FloatArray) -> bool:
    def orient(o: FloatArray, x: FloatArray, y: FloatArray) -> float:
        return float((x[0] - o[0]) * (y[1] - o[1]) - (x[1] - o[1]) * (y[0] - o[0]))

    d1, d2 = orient(p, q, a), orient(p, q, b)
    d3, d4 = orient(a, b, p), orient(a, b, q)
    return (d1 * d2 <= 0) and (d3 * d4 <= 0)


@dataclass(frozen=True)
class Footprint:
    """What one camera station sees of a horizontal plane: the axis-aligned (in the image)
    rectangle ``half_u`` x ``half_v`` (metres, along the image's u and v directions projected
    on the plane) around the optical axis's hit point; ``angle`` (radians) of the image's u
    direction about the frame's z axis."""

    half_u: float
    half_v: float
    angle: float


def view_footprint(
    intrinsics: CameraIntrinsics, frame_from_camera: ArrayLike, height_m: float
) -> Footprint:
    """The footprint on the plane ``z = height_m`` of a camera at ``frame_from_camera``
    (looking down at it): the rectangle through the projections of the image's edge midpoints,
    which lies inside the image's view for pinhole and barrel-distorted lenses."""
    w, h = intrinsics.width, intrinsics.height
    mids = np.array(
        [[-0.5, (h - 1) / 2], [w - 0.5, (h - 1) / 2], [(w - 1) / 2, -0.5], [(w - 1) / 2, h - 0.5]]
    )
    pts = pixels_to_plane(intrinsics, frame_from_camera, mids, height_m)
    centre = optical_axis_hit(frame_from_camera, height_m)
    if centre is None or not np.all(np.isfinite(pts)):
        raise ValueError("the camera does not look at the plane")
    u_dir = pts[1, :2] - pts[0, :2]
    angle = math.atan2(u_dir[1], u_dir[0])
    ca, sa = math.cos(angle), math.sin(angle)
    ax_u, ax_v = np.array([ca, sa]), np.array([-sa, ca])
    rel = pts[:, :2] - centre[:2]
    half_u = float(min(abs(rel[0] @ ax_u), abs(rel[1] @ ax_u)))
    half_v = float(min(abs(rel[2] @ ax_v), abs(rel[3] @ ax_v)))
    return Footprint(half_u, half_v, angle)


def plan_search_grid(
    region: Polygon, footprint: Footprint, *, overlap: float = 0.25, margin_m: float = 0.0
) -> FloatArray:
    """Camera stations (M, 2): the optical axis's hit points on the plane, a boustrophedon grid
    in the image-aligned directions whose footprints (shrunk by ``margin_m`` so an object at
    the edge of one view is whole in the next, and overlapping by ``overlap`` of their size)
    cover the region; only stations whose footprint overlaps the region are kept."""
    if not 0.0 <= overlap < 1.0:
        raise ValueError(f"overlap must be in [0, 1), got {overlap}")
    hu, hv = footprint.half_u - margin_m, footprint.half_v - margin_m
    if hu <= 0 or hv <= 0:
        raise ValueError("the margin is larger than the camera's footprint")
    ca, sa = math.cos(footprint.angle), math.sin(footprint.angle)
    axes = np.array([[ca, sa], [-sa, ca]])
    local = region.vertices @ axes.T  # vertices in (u, v) coordinates
    lo, hi = local.min(axis=0), local.max(axis=0)
    steps = (2 * hu * (1 - overlap), 2 * hv * (1 - overlap))
    centres_1d = []
    for k, half in enumerate((hu, hv)):
        extent = hi[k] - lo[k]
        n = 1 if extent <= 2 * half else 1 + math.ceil((extent - 2 * half) / steps[k] - 1e-9)
        span = (n - 1) * steps[k]
        mid = (lo[k] + hi[k]) / 2
        centres_1d.append(mid - span / 2 + steps[k] * np.arange(n))
    stations = []
    for row, v in enumerate(centres_1d[1]):
        us = centres_1d[0] if row % 2 == 0 else centres_1d[0][::-1]
        for u in us:
            xy = axes.T @ np.array([u, v])
            if region.overlaps_rectangle(xy, (hu, hv), footprint.angle):
                stations.append(xy)
    return np.array(stations, np.float64).reshape(-1, 2)


def greedy_order(points: ArrayLike, start: ArrayLike) -> list[int]:
    """Indices of ``points`` (M, 2 or 3) in visiting order: always the nearest unvisited
    point next, starting from ``start`` (nearest-neighbour tour)."""
    pts = np.asarray(points, np.float64)
    if pts.size == 0:
        return []
    here = np.asarray(start, np.float64).reshape(-1)[: pts.shape[1]]
    left = list(range(len(pts)))
    order: list[int] = []
    while left:
        d = [float(np.linalg.norm(pts[i] - here)) for i in left]
        k = left.pop(int(np.argmin(d)))
        order.append(k)
        here = pts[k]
    return order


def tool_pose_viewing(
    view_pose: ArrayLike, tool_from_camera: ArrayLike, height_m: float, target_xy: ArrayLike
) -> FloatArray:
    """The tool pose with ``view_pose``'s orientation and height whose camera's optical axis
    hits the plane ``z = height_m`` at ``target_xy``."""
    pose = np.asarray(view_pose, np.float64).copy()
    hit = optical_axis_hit(pose @ np.asarray(tool_from_camera, np.float64), height_m)
    if hit is None:
        raise ValueError("at the view pose, the camera does not look at the plane")
    pose[:2, 3] += np.asarray(target_xy, np.float64).reshape(-1)[:2] - hit[:2]
    return pose
