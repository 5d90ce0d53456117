"""The spec records of :mod:`.measure` (where to look, what to measure, the tolerance) and
the :class:`Measurement` each gives. Geometry in the part frame (image pixels without a
fixture), lengths in the measurement's unit (:mod:`.plane_units`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from .caliper import Band, Polarity
from .fit2d import Circle, Line

__all__ = [
    "CircleSpec",
    "DistanceSpec",
    "EdgeSpec",
    "LineSpec",
    "Measurement",
    "Pick",
    "Spec",
    "WidthSpec",
]

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
