"""The keys of a caliper's measurements and units (docs/configuration.md, "caliper"): read
into the spec records of :mod:`vision_server.analysis.measure`, every error naming its key.

A job's caliper step needs one entry: read its keys with :func:`parse_units` and
:func:`parse_measurements` (without ``image_size``: its geometry is in the part frame), and run
:func:`vision_server.analysis.measure.measure` with the fixture's 2x3 ``image_from_part``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from yamlfile import Node, name, number, numbers, one_of, positive, positive_int

from ..analysis import (
    POLARITIES,
    Band,
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    PixelUnits,
    PlaneUnits,
    ScaleUnits,
    Spec,
    Units,
    WidthSpec,
)
from ..cameras import Intrinsics

__all__ = ["KINDS", "PICKS", "parse_measurements", "parse_units"]

KINDS = ("edge", "width", "circle", "line", "distance")
PICKS = ("first", "last", "strongest")


def _polarity(value: object) -> Any:
    return one_of(*POLARITIES)(value)


def _pick(value: object) -> Any:
    return one_of(*PICKS)(value)


def _band(node: Node) -> Band:
    sub = node.sub("band", required=True)
    centre = sub.take("center", numbers(2))
    try:
        band = Band(
            centre[0],
            centre[1],
            sub.take("length", positive),
            sub.take("width", positive, 1.0),
            sub.take("angle_rad", number, 0.0),
        )
    except ValueError as exc:
        raise sub.error(str(exc)) from None
    sub.finish()
    return band


def _limits(node: Node) -> tuple[float | None, float | None]:
    low = node.take("min", number, None)
    high = node.take("max", number, None)
    if low is not None and high is not None and low > high:
        raise node.error(f"min ({low:g}) is above max ({high:g})", "min")
    return low, high


def _edge_options(node: Node) -> tuple[float, float]:
    """``min_strength`` and ``smoothing``."""
    strength = node.take("min_strength", positive, 5.0)
    smoothing = node.take("smoothing", positive, 1.0)
    if not 0.3 <= smoothing <= 20.0:
        raise node.error(f"expected a sigma in 0.3..20 px, got {smoothing:g}", "smoothing")
    return strength, smoothing


def _spec(node: Node, kind: str, measured: Mapping[str, str]) -> Spec:
    label = node.take("name", name)
    if label in measured:
        raise node.error(f"a second measurement named {label!r}", "name")
    if kind == "distance":
        source = node.take("from", name)
        to = node.take("to", name)
        value = node.take("value", one_of("distance", "angle"), "distance")
        for key, other in (("from", source), ("to", to)):
            if other not in measured:
                raise node.error(
                    f"{other!r} is not a measurement above this one (above: "
                    f"{', '.join(measured) or 'none'})",
                    key,
                )
        if measured[to] != "line":
            raise node.error(f"{to!r} is a {measured[to]}; a distance is to a line", "to")
        if value == "angle" and measured[source] != "line":
            raise node.error(
                f"an angle is between two lines; {source!r} is a {measured[source]}", "value"
            )
        return DistanceSpec(label, source, to, value, *_limits(node))  # type: ignore[arg-type]
    if kind == "circle":
        centre = node.take("center", numbers(2))
        arc = node.take("arc_rad", numbers(2), (0.0, 2.0 * math.pi))
        low, high = _limits(node)
        strength, smoothing = _edge_options(node)
        return CircleSpec(
            label,
            centre[0],
            centre[1],
            node.take("radius", positive),
            node.take("search", positive, 10.0),
            node.take("rays", _rays, 32),
            node.take("band_width", positive, 3.0),
            arc[0],
            arc[1],
            node.take("polarity", _polarity, "any"),
            node.take("select", _pick, "strongest"),
            value="roundness"
            if node.take("value", _circle_value, "diameter") == "roundness"
            else "diameter",
            low=low,
            high=high,
            min_strength=strength,
            smoothing=smoothing,
        )
    band = _band(node)
    strength, smoothing = _edge_options(node)
    low, high = _limits(node)
    if kind == "edge":
        return EdgeSpec(
            label,
            band,
            node.take("polarity", _polarity, "any"),
            node.take("select", _pick, "strongest"),
            min_strength=strength,
            smoothing=smoothing,
            low=low,
            high=high,
        )
    if kind == "width":
        expected = node.take("expected", positive, None)
        tolerance = node.take("tolerance", positive, None)
        if tolerance is not None and expected is None:
            raise node.error("tolerance is around expected, which is not given", "tolerance")
        return WidthSpec(
            label,
            band,
            node.take("first", _polarity, "dark_to_light"),
            node.take("second", _polarity, "light_to_dark"),
            expected,
            tolerance,
            node.take("select", _pick, "strongest"),
            min_strength=strength,
            smoothing=smoothing,
            low=low,
            high=high,
        )
    segments = node.take("segments", positive_int, 8)
    if segments < 2 or band.width / segments < 1.0:
        raise node.error(
            f"{segments} segments across a {band.width:g} px band: need 2 or more, each at "
            "least 1 px wide",
            "segments",
        )
    return LineSpec(
        label,
        band,
        segments,
        node.take("polarity", _polarity, "any"),
        node.take("select", _pick, "strongest"),
        min_strength=strength,
        smoothing=smoothing,
        low=low,
        high=high,
    )


def _circle_value(value: object) -> str:
    return one_of("diameter", "roundness")(value)


def _rays(value: object) -> int:
    count = positive_int(value)
    if not 3 <= count <= 720:
        raise ValueError(f"expected 3..720 rays, got {count}")
    return count


def _reach(spec: Spec) -> tuple[float, float, float, float] | None:
    """The part of the image a measurement reads: (u_min, v_min, u_max, v_max), px."""
    if isinstance(spec, CircleSpec):
        r = spec.radius + spec.search + spec.band_width
        return spec.u - r, spec.v - r, spec.u + r, spec.v + r
    if isinstance(spec, DistanceSpec):
        return None
    band = spec.band
    half = band.width / 2.0
    corners = [band.point(t, a) for t in (0.0, band.length) for a in (-half, half)]
    us, vs = [c[0] for c in corners], [c[1] for c in corners]
    return min(us), min(vs), max(us), max(vs)


def parse_measurements(
    node: Node, key: str = "measurements", *, image_size: tuple[int, int] | None = None
) -> tuple[Spec, ...]:
    """The list of measurements at ``key``, each checked (a distance refers to measurements
    above it; with ``image_size`` = (width, height), every band lies inside the image)."""
    specs: list[Spec] = []
    measured: dict[str, str] = {}
    for item in node.items(key):
        kind = item.take("kind", one_of(*KINDS))
        spec = _spec(item, kind, measured)
        item.finish()
        reach = _reach(spec)
        if image_size is not None and reach is not None:
            width, height = image_size
            if reach[0] < 0 or reach[1] < 0 or reach[2] > width - 1 or reach[3] > height - 1:
                raise item.error(
                    f"reaches u {reach[0]:.0f}..{reach[2]:.0f}, v {reach[1]:.0f}..{reach[3]:.0f}, "
                    f"outside the camera's {width}x{height} image"
                )
        measured[spec.name] = kind
        specs.append(spec)
    if not specs:
        raise node.error("a caliper needs at least one measurement", key)
    return tuple(specs)


def parse_units(node: Node, camera: str, intrinsics: Intrinsics | None) -> Units:
    """``units: px`` (default), or ``units: mm`` with ``plane_distance_m`` (through
    ``intrinsics``, camera ``camera``'s) or ``mm_per_px`` (a reference's scale)."""
    unit = node.take("units", one_of("px", "mm"), "px")
    distance = node.take("plane_distance_m", positive, None)
    scale = node.take("mm_per_px", positive, None)
    if unit == "px":
        for key, value in (("plane_distance_m", distance), ("mm_per_px", scale)):
            if value is not None:
                raise node.error(f"{key} is for units: mm (units is px)", key)
        return PixelUnits()
    if (distance is None) == (scale is None):
        raise node.error(
            "units: mm needs one calibration of the measuring plane: plane_distance_m (with "
            "the camera's intrinsics) or mm_per_px (from a reference of known size)",
            "units",
        )
    if scale is not None:
        return ScaleUnits(scale)
    assert distance is not None
    if intrinsics is None:
        raise node.error(
            f"plane_distance_m needs the intrinsics of camera {camera!r}: set "
            f"cameras.{camera}.intrinsics, or give mm_per_px instead",
            "plane_distance_m",
        )
    try:
        lens = intrinsics.to_geometry()
    except ValueError as exc:
        raise node.error(f"camera {camera!r}: {exc}", "plane_distance_m") from None
    return PlaneUnits(lens, distance * 1000.0)
