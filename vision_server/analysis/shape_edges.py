"""Edge points of a circle (radial scans) and of a straight edge (strips across a band), and
the correction of a curved edge's pull towards its centre of curvature. Image pixels out; the
specs' geometry in the part frame, mapped by the fixture ``m`` (2x3, or None)."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .caliper import Affine, Band, find_edges_in_bands
from .fit2d import fit_circle
from .measure_specs import CircleSpec, LineSpec

__all__ = ["circle_points", "line_points", "unbias_circle"]

FloatArray = NDArray[np.float64]


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
