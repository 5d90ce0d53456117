"""Measurements from spec records: what a ``caliper`` inspection (and a job's caliper step)
runs. A spec is a frozen record of where to look and what to measure; :func:`measure` runs a
list of them on one image, in order, so that a ``distance`` can use the lines and points
measured before it.

Geometry in the specs is in the *part frame* (image pixels without a fixture; with one, the
2x3 ``image_from_part`` of :mod:`.caliper` maps it to the image). Every value is computed
between image points mapped to the measuring plane by ``units`` (:mod:`.plane_units`) and is
reported in its unit (``px`` or ``mm``; angles in ``rad``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from .caliper import (
    Affine,
    Band,
    Edge,
    Polarity,
    find_edges,
    find_edges_in_bands,
    find_pairs,
    gray_float,
)
from .errors import NotFoundError
from .fit2d import Circle, Line, fit_circle, fit_line, line_line, point_line_distance
from .plane_units import PixelUnits, Units

__all__ = [
    "CircleSpec",
    "DistanceSpec",
    "EdgeSpec",
    "LineSpec",
    "Measurement",
    "Spec",
    "WidthSpec",
    "measure",
]

FloatArray = NDArray[np.float64]
Pick = Literal["first", "last", "strongest"]


@dataclass(frozen=True)
class EdgeSpec:
    """One edge across ``band``; its value is the distance from the band's start to it."""

    name: str
    band: Band
    polarity: Polarity = "any"
    select: Pick = "strongest"
    min_strength: float = 5.0
    smoothing: float = 1.0
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class WidthSpec:
    """The width between a ``first``-polarity edge and a following ``second``-polarity edge
    across ``band``. ``expected`` and ``tolerance`` (in the measurement's unit) choose among
    candidate pairs."""

    name: str
    band: Band
    first: Polarity = "dark_to_light"
    second: Polarity = "light_to_dark"
    expected: float | None = None
    tolerance: float | None = None
    select: Pick = "strongest"
    min_strength: float = 5.0
    smoothing: float = 1.0
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class CircleSpec:
    """A circle (or arc) found on ``rays`` radial scans from ``(u, v)``, each ``2 search`` px
    long around ``radius`` and ``band_width`` wide, spread from ``arc_from_rad`` to
    ``arc_to_rad`` (from +u towards +v). ``polarity`` is along the outward scan (a bright
    disc on a dark ground: light_to_dark). Its value is the ``diameter`` or the
    ``roundness`` (max - min radius)."""

    name: str
    u: float
    v: float
    radius: float
    search: float = 10.0
    rays: int = 32
    band_width: float = 3.0
    arc_from_rad: float = 0.0
    arc_to_rad: float = 2.0 * math.pi
    polarity: Polarity = "any"
    select: Pick = "strongest"
    min_strength: float = 5.0
    smoothing: float = 1.0
    value: Literal["diameter", "roundness"] = "diameter"
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class LineSpec:
    """A straight edge: one edge in each of ``segments`` strips across ``band`` (each as long
    as the band, ``width / segments`` wide), a line fitted through them. Its value is the
    straightness (max - min distance of the edge points from the line)."""

    name: str
    band: Band
    segments: int = 8
    polarity: Polarity = "any"
    select: Pick = "strongest"
    min_strength: float = 5.0
    smoothing: float = 1.0
    low: float | None = None
    high: float | None = None


@dataclass(frozen=True)
class DistanceSpec:
    """Distance from an earlier measurement ``source`` (an edge point, a width's midpoint, a
    circle's centre, or a line) to the earlier line ``to``; ``value``: ``distance`` (signed,
    see :func:`.fit2d.point_line_distance`; a line's centre for a line) or ``angle`` between
    two lines (rad)."""

    name: str
    source: str
    to: str
    value: Literal["distance", "angle"] = "distance"
    low: float | None = None
    high: float | None = None


Spec = EdgeSpec | WidthSpec | CircleSpec | LineSpec | DistanceSpec


@dataclass(frozen=True)
class Measurement:
    """One measured value, ``unit`` stated (``px``, ``mm`` or ``rad``). ``points``: the image
    points (px) it was measured from (for the overlay); ``circle``/``line``: the fitted shape
    in image pixels, where there is one."""

    name: str
    kind: str
    value: float
    unit: str
    passed: bool
    low: float | None = None
    high: float | None = None
    points: tuple[tuple[float, float], ...] = ()
    circle: Circle | None = None
    line: Line | None = None
    extra: dict[str, float] = field(default_factory=dict)
    reason: str = ""
    """Why nothing was measured (``value`` NaN, not passed); empty when it was."""


def _within(value: float, low: float | None, high: float | None) -> bool:
    return (low is None or value >= low) and (high is None or value <= high)


def _length(units: Units, a: tuple[float, float], b: tuple[float, float]) -> float:
    pa, pb = units.to_plane([a, b])
    return float(np.hypot(*(pb - pa)))


def _unit_per_px(units: Units, near: tuple[float, float]) -> float:
    """The local scale of ``units`` at an image point (unit per image px)."""
    p = units.to_plane([near, (near[0] + 1.0, near[1]), (near[0], near[1] + 1.0)])
    return float((np.hypot(*(p[1] - p[0])) + np.hypot(*(p[2] - p[0]))) / 2.0)


def _apply(matrix: Affine | None, point: tuple[float, float]) -> tuple[float, float]:
    if matrix is None:
        return point
    m = np.asarray(matrix, np.float64)
    return (
        float(m[0, 0] * point[0] + m[0, 1] * point[1] + m[0, 2]),
        float(m[1, 0] * point[0] + m[1, 1] * point[1] + m[1, 2]),
    )


def _part_from_image(matrix: Affine | None, point: tuple[float, float]) -> tuple[float, float]:
    if matrix is None:
        return point
    m = np.asarray(matrix, np.float64)
    u, v = np.linalg.solve(m[:, :2], np.asarray(point) - m[:, 2])
    return float(u), float(v)


def _one(edges: list[Edge], what: str) -> Edge:
    if not edges:
        raise NotFoundError(f"no edge {what}")
    return edges[0]


def _edge(
    image: NDArray[np.generic], spec: EdgeSpec, m: Affine | None, units: Units
) -> Measurement:
    edge = _one(
        find_edges(
            image,
            spec.band,
            polarity=spec.polarity,
            min_strength=spec.min_strength,
            smoothing=spec.smoothing,
            select=spec.select,
            image_from_part=m,
        ),
        f"of polarity {spec.polarity} and strength >= {spec.min_strength:g} across "
        f"{spec.name!r}'s band",
    )
    start = _apply(m, spec.band.point(0.0))
    value = _length(units, start, (edge.u, edge.v))
    return Measurement(
        spec.name,
        "edge",
        value,
        units.unit,
        _within(value, spec.low, spec.high),
        spec.low,
        spec.high,
        ((edge.u, edge.v),),
        extra={"strength": edge.strength},
    )


def _width(
    image: NDArray[np.generic], spec: WidthSpec, m: Affine | None, units: Units
) -> Measurement:
    scale = _unit_per_px(units, _apply(m, (spec.band.u, spec.band.v)))
    pair = find_pairs(
        image,
        spec.band,
        first=spec.first,
        second=spec.second,
        expected_width=None if spec.expected is None else spec.expected / scale,
        width_tolerance=None if spec.tolerance is None else spec.tolerance / scale,
        min_strength=spec.min_strength,
        smoothing=spec.smoothing,
        select=spec.select,
        image_from_part=m,
    )[0]
    a, b = (pair.first.u, pair.first.v), (pair.second.u, pair.second.v)
    value = _length(units, a, b)
    return Measurement(
        spec.name,
        "width",
        value,
        units.unit,
        _within(value, spec.low, spec.high),
        spec.low,
        spec.high,
        (a, b),
    )


def circle_points(
    image: NDArray[np.generic], spec: CircleSpec, m: Affine | None = None
) -> tuple[FloatArray, float]:
    """Image points (px) of the circle's edge, one per radial scan that found one, and how
    far (px) the strongest slope of a curved edge lies inside the true edge at radius 1 px
    (divide by the radius): see :func:`unbias_circle`."""
    if spec.rays < 3:
        raise ValueError(f"a circle needs 3 rays or more, got {spec.rays}")
    if not spec.search > 0 or not spec.radius > 0:
        raise ValueError("a circle's radius and search must be > 0 px")
    full = abs(spec.arc_to_rad - spec.arc_from_rad) >= 2.0 * math.pi - 1e-9
    angles = np.linspace(spec.arc_from_rad, spec.arc_to_rad, spec.rays, endpoint=not full)
    bands = [
        Band(
            spec.u + spec.radius * math.cos(angle),
            spec.v + spec.radius * math.sin(angle),
            max(3.0, 2.0 * spec.search),
            spec.band_width,
            float(angle),
        )
        for angle in angles
    ]
    found = find_edges_in_bands(
        image,
        bands,
        polarity=spec.polarity,
        min_strength=spec.min_strength,
        smoothing=spec.smoothing,
        select=spec.select,
        image_from_part=m,
    )
    points = [(edges[0].u, edges[0].v) for edges in found if edges]
    blur2 = [edges[0].spread ** 2 - spec.smoothing**2 for edges in found if edges]
    lanes = max(1, int(round(spec.band_width)))
    across = (lanes * lanes - 1) / 12.0 if lanes > 1 else 0.0
    finite = [b for b in blur2 if math.isfinite(b)]
    blur = max(float(np.median(finite)), 0.0) if finite else 0.0
    return np.asarray(points, np.float64).reshape(-1, 2), (blur + across) / 2.0


def unbias_circle(points: FloatArray, inset: float) -> FloatArray:
    """``points`` of a curved edge moved outwards by ``inset / r`` px from the fitted centre.

    On an edge of radius ``r`` blurred by a Gaussian of ``sigma`` px the slope is steepest
    about ``sigma**2 / (2 r)`` inside the true edge, and a scan band ``w`` px wide across a
    ray sees the circle ``(w**2 - 1) / (24 r)`` px nearer on average: ``inset`` is their sum
    times r (:func:`circle_points`). Left alone, a 40 px disc blurred by 1 px reads about
    0.07 px small in diameter.
    """
    if inset <= 0 or len(points) < 3:
        return points
    rough = fit_circle(points)
    offset = points - np.array([rough.x, rough.y])
    distance = np.hypot(offset[:, 0], offset[:, 1])
    moved: FloatArray = points + offset / distance[:, None] * (inset / rough.radius)
    return moved


def _circle(
    image: NDArray[np.generic], spec: CircleSpec, m: Affine | None, units: Units
) -> Measurement:
    needed = max(5, spec.rays // 2)
    points, inset = circle_points(image, spec, m)
    if len(points) < needed:
        raise NotFoundError(
            f"circle {spec.name!r}: an edge on {len(points)} of {spec.rays} rays (needs {needed})"
        )
    # Scan again along true radii: a ray that misses the centre meets a blurred edge
    # obliquely and reads it a little off, which would show as out-of-roundness.
    rough = fit_circle(points)
    u, v = _part_from_image(m, (rough.x, rough.y))
    again = replace(spec, u=u, v=v, radius=rough.radius, search=min(spec.search, 4.0))
    redone, redone_inset = circle_points(image, again, m)
    if len(redone) >= needed:
        points, inset = redone, redone_inset
    points = unbias_circle(points, inset)
    in_image = fit_circle(points)
    on_plane = fit_circle(units.to_plane(points))
    value = on_plane.diameter if spec.value == "diameter" else on_plane.roundness
    return Measurement(
        spec.name,
        "circle",
        value,
        units.unit,
        _within(value, spec.low, spec.high),
        spec.low,
        spec.high,
        tuple((float(u), float(v)) for u, v in points),
        circle=in_image,
        extra={"diameter": on_plane.diameter, "roundness": on_plane.roundness},
    )


def line_points(image: NDArray[np.generic], spec: LineSpec, m: Affine | None = None) -> FloatArray:
    """Image points (px) of the straight edge, one per strip that found one."""
    if spec.segments < 2:
        raise ValueError(f"a line needs 2 segments or more, got {spec.segments}")
    band = spec.band
    strip = band.width / spec.segments
    if strip < 1.0:
        raise ValueError(
            f"line {spec.name!r}: {spec.segments} strips across a {band.width:g} px band are "
            "narrower than 1 px"
        )
    strips = []
    for k in range(spec.segments):
        across = (k + 0.5) * strip - band.width / 2.0
        u, v = band.point(band.length / 2.0, across)
        strips.append(Band(u, v, band.length, strip, band.angle_rad))
    found = find_edges_in_bands(
        image,
        strips,
        polarity=spec.polarity,
        min_strength=spec.min_strength,
        smoothing=spec.smoothing,
        select=spec.select,
        image_from_part=m,
    )
    points = [(edges[0].u, edges[0].v) for edges in found if edges]
    return np.asarray(points, np.float64).reshape(-1, 2)


def _line(
    image: NDArray[np.generic], spec: LineSpec, m: Affine | None, units: Units
) -> Measurement:
    points = line_points(image, spec, m)
    if len(points) < 2:
        raise NotFoundError(
            f"line {spec.name!r}: an edge in {len(points)} of {spec.segments} strips (needs 2)"
        )
    on_plane = fit_line(units.to_plane(points))
    value = on_plane.straightness
    return Measurement(
        spec.name,
        "line",
        value,
        units.unit,
        _within(value, spec.low, spec.high),
        spec.low,
        spec.high,
        tuple((float(u), float(v)) for u, v in points),
        line=fit_line(points),
        extra={"angle_rad": on_plane.angle_rad},
    )


def _anchor(done: dict[str, Measurement], name: str, units: Units) -> tuple[float, float] | Line:
    """An earlier measurement as a point or a line on the measuring plane."""
    earlier = done[name]
    if earlier.kind == "line":
        return fit_line(units.to_plane(earlier.points))
    if earlier.kind == "circle" and earlier.circle is not None:
        centre = fit_circle(units.to_plane(earlier.points))
        return centre.x, centre.y
    plane = units.to_plane(earlier.points)
    mid = plane.mean(axis=0)
    return float(mid[0]), float(mid[1])


def _distance(spec: DistanceSpec, done: dict[str, Measurement], units: Units) -> Measurement:
    for key, name in (("source", spec.source), ("to", spec.to)):
        if name not in done:
            raise ValueError(
                f"distance {spec.name!r}: {key} {name!r} is not an earlier measurement"
            )
    if done[spec.to].kind != "line":
        raise ValueError(
            f"distance {spec.name!r}: to {spec.to!r} is a {done[spec.to].kind}, not a line"
        )
    for name in (spec.source, spec.to):
        if done[name].reason:
            raise NotFoundError(f"{name!r} was not measured ({done[name].reason})")
    line = _anchor(done, spec.to, units)
    source = _anchor(done, spec.source, units)
    assert isinstance(line, Line)
    if isinstance(source, Line):
        distance, angle = line_line(line, source)
    else:
        if spec.value == "angle":
            raise ValueError(
                f"distance {spec.name!r}: an angle needs two lines; {spec.source!r} is a point"
            )
        distance, angle = point_line_distance(source, line), math.nan
    value = angle if spec.value == "angle" else distance
    unit = "rad" if spec.value == "angle" else units.unit
    return Measurement(
        spec.name,
        "distance",
        value,
        unit,
        _within(value, spec.low, spec.high),
        spec.low,
        spec.high,
        done[spec.source].points[:1] + done[spec.to].points[:1],
    )


def measure(
    image: NDArray[np.generic],
    specs: Sequence[Spec],
    *,
    units: Units | None = None,
    image_from_part: Affine | None = None,
) -> list[Measurement]:
    """Run ``specs`` in order on ``image`` (gray or BGR), geometry in the part frame mapped by
    ``image_from_part`` (None: the image's pixels), values in ``units`` (default: px).

    A measurement that finds no edge, pair, circle or line (or uses one that found none)
    comes back with a NaN value, not passed, and the ``reason``.

    Raises
    ------
    RoiError
        A band leaves the image.
    """
    chosen: Units = units if units is not None else PixelUnits()
    image = gray_float(image)  # once, not once per scan
    done: dict[str, Measurement] = {}
    for spec in specs:
        try:
            if isinstance(spec, EdgeSpec):
                result = _edge(image, spec, image_from_part, chosen)
            elif isinstance(spec, WidthSpec):
                result = _width(image, spec, image_from_part, chosen)
            elif isinstance(spec, CircleSpec):
                result = _circle(image, spec, image_from_part, chosen)
            elif isinstance(spec, LineSpec):
                result = _line(image, spec, image_from_part, chosen)
            else:
                result = _distance(spec, done, chosen)
        except NotFoundError as exc:
            kind = type(spec).__name__.removesuffix("Spec").lower()
            unit = (
                "rad" if isinstance(spec, DistanceSpec) and spec.value == "angle" else chosen.unit
            )
            result = Measurement(
                spec.name, kind, math.nan, unit, False, spec.low, spec.high, reason=str(exc)
            )
        done[spec.name] = result
    return list(done.values())
