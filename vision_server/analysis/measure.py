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
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from .caliper import Affine, Edge, find_edges, find_pairs, gray_float
from .errors import NotFoundError
from .fit2d import Line, fit_circle, fit_line, line_line, point_line_distance
from .measure_specs import (
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    Measurement,
    Spec,
    WidthSpec,
)
from .plane_units import PixelUnits, Units
from .shape_edges import circle_points, line_points, unbias_circle

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
        extra={"strength_grey_per_px": edge.strength},
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
