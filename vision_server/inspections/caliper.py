"""``caliper``: measurements with tolerances: edges, widths between edge pairs, circles
(diameter, roundness), straight edges and the distances and angles between them, in pixels or
millimetres on the measuring plane; passes when every measurement is within its ``min`` and
``max`` (docs/configuration.md, "caliper").

A job's caliper step needs one entry: read its keys with :func:`parse_units` and
:func:`parse_measurements` (without ``image_size``: its geometry is in the part frame), and run
:func:`vision_server.analysis.measure.measure` with the fixture's 2x3 ``image_from_part``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..analysis import AnalysisError
from ..analysis.caliper import POLARITIES, Band
from ..analysis.measure import (
    CircleSpec,
    DistanceSpec,
    EdgeSpec,
    LineSpec,
    Measurement,
    Spec,
    WidthSpec,
    measure,
)
from ..analysis.plane_units import PixelUnits, PlaneUnits, ScaleUnits, Units
from ..cameras import CameraSettings, Intrinsics
from ..catalog import InspectionInput, InspectionOutcome
from ..configfile import Node, name, number, numbers, one_of, positive, positive_int
from .base import (
    GREEN,
    RED,
    Common,
    Configured,
    Image,
    analysis_failed,
    draw_verdict,
    overlay_base,
    parse_common,
)
from .kinds import Data, ResultKind, as_number

KINDS = ("edge", "width", "circle", "line", "distance")
PICKS = ("first", "last", "strongest")
SUMMARY_VALUES = 8
"""Measurements whose values a narrow reader (Modbus, line protocol) gets, in order."""

YELLOW = (0, 200, 255)


@dataclass(frozen=True)
class CaliperInspection(Configured):
    common: Common
    specs: tuple[Spec, ...]
    units: Units

    type = "caliper"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        try:
            results = measure(image.color, self.specs, units=self.units)
        except AnalysisError as exc:
            raise analysis_failed(self.common.name, exc) from None
        passed = all(m.passed for m in results)
        data: dict[str, Any] = {
            "units": self.units.unit,
            "failed": sum(not m.passed for m in results),
            "value": _number(results[0].value),
            "measurements": [_measurement_dict(m) for m in results],
        }
        picture = None
        if overlay:
            picture = overlay_base(image.color, None)
            for spec in self.specs:
                _draw_spec(picture, spec)
            for number, m in enumerate(results, start=1):
                _draw_measurement(picture, m, number, len(results))
            failed = [m.name for m in results if not m.passed]
            draw_verdict(picture, passed, f"out: {', '.join(failed)}" if failed else "")
        return InspectionOutcome(passed, data, picture)


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def _measurement_dict(m: Measurement) -> dict[str, Any]:
    out: dict[str, Any] = {
        "name": m.name,
        "kind": m.kind,
        "value": _number(m.value),
        "unit": m.unit,
        "passed": m.passed,
        "min": m.low,
        "max": m.high,
    }
    if len(m.points) <= 2:  # an edge or a pair; a circle or line says where in its fit
        out["points"] = [[round(u, 3), round(v, 3)] for u, v in m.points]
    for key, value in m.extra.items():
        out[key] = _number(value)
    if m.circle is not None:
        out["circle_px"] = [m.circle.x, m.circle.y, m.circle.radius]
        out["edge_points"] = len(m.points)
    if m.line is not None:
        out["line_px"] = [m.line.x, m.line.y, m.line.dx, m.line.dy]
        out["edge_points"] = len(m.points)
    if m.reason:
        out["reason"] = m.reason
    return out


# --------------------------------------------------------------------------- overlay


def _px(point: tuple[float, float]) -> tuple[int, int]:
    return int(round(point[0])), int(round(point[1]))


def _draw_spec(canvas: Image, spec: Spec) -> None:
    """Where a measurement looks: its band's outline, or a circle's search ring."""
    if isinstance(spec, EdgeSpec | WidthSpec | LineSpec):
        band = spec.band
        half = band.width / 2.0
        corners = [
            band.point(0.0, -half),
            band.point(band.length, -half),
            band.point(band.length, half),
            band.point(0.0, half),
        ]
        cv2.polylines(canvas, [np.array([_px(c) for c in corners], np.int32)], True, YELLOW, 1)
    elif isinstance(spec, CircleSpec):
        for r in (spec.radius - spec.search, spec.radius + spec.search):
            cv2.circle(canvas, _px((spec.u, spec.v)), max(1, int(round(r))), YELLOW, 1)


def _draw_measurement(canvas: Image, m: Measurement, number: int, count: int) -> None:
    """Edge points, the pair's span, the fitted circle or line, in green (within its
    tolerance) or red, tagged with its number; the legend lists the values."""
    colour = GREEN if m.passed else RED
    if m.kind in ("edge", "width"):
        for point in m.points:
            cv2.drawMarker(canvas, _px(point), colour, cv2.MARKER_CROSS, 7, 1)
    else:
        for point in m.points:
            cv2.circle(canvas, _px(point), 1, colour, -1)
    if m.kind == "width" and len(m.points) == 2:
        cv2.line(canvas, _px(m.points[0]), _px(m.points[1]), colour, 1, cv2.LINE_AA)
    tag = m.points[-1] if m.points else None
    if m.circle is not None:
        centre = _px((m.circle.x, m.circle.y))
        cv2.circle(canvas, centre, max(1, int(round(m.circle.radius))), colour, 1, cv2.LINE_AA)
        tag = (m.circle.x + m.circle.radius * 0.7, m.circle.y - m.circle.radius * 0.7)
    if m.line is not None:
        line = m.line
        a = (line.x - line.dx * line.extent / 2, line.y - line.dy * line.extent / 2)
        b = (line.x + line.dx * line.extent / 2, line.y + line.dy * line.extent / 2)
        cv2.line(canvas, _px(a), _px(b), colour, 1, cv2.LINE_AA)
    font = cv2.FONT_HERSHEY_SIMPLEX
    if tag is not None and m.kind != "distance":
        u, v = _px(tag)
        cv2.putText(canvas, str(number), (u + 4, v - 4), font, 0.4, colour, 1, cv2.LINE_AA)
    text = f"{number} {m.name} = " + (
        f"{m.value:.3f} {m.unit}" if math.isfinite(m.value) else "not measured"
    )
    row = canvas.shape[0] - 8 - 14 * (count - number)  # the legend, bottom left
    cv2.putText(canvas, text, (6, row), font, 0.4, colour, 1, cv2.LINE_AA)


# --------------------------------------------------------------------------- configuration


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


def parse_caliper(
    node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]
) -> CaliperInspection:
    if node.has("roi"):
        raise node.error("a caliper reads where its measurements' bands are; it has no roi", "roi")
    common = parse_common(node, "caliper", cameras)
    units = parse_units(node, common.camera, common.intrinsics)
    specs = parse_measurements(node, image_size=common.image_size)
    return CaliperInspection(common, specs, units)


def _caliper_expected(data: Data) -> dict[str, Any]:
    value = data.get("value")
    return {} if value is None else {"value": round(float(value), 4)}


def _caliper_summary(data: Data) -> dict[str, float]:
    values = [m.get("value") for m in data.get("measurements", [])]
    out = {"failed": as_number(data, "failed")}
    for i in range(SUMMARY_VALUES):
        value = values[i] if i < len(values) else None
        out[f"value_{i + 1}"] = math.nan if value is None else float(value)
    return out


RESULTS = ResultKind(("value",), _caliper_expected, _caliper_summary)
"""A caliper result: the first measurement's value (golden ``value``); the summary: how many
measurements failed and the first eight values in order (each in its measurement's unit)."""
