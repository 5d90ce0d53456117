"""``caliper``: measurements with tolerances: edges, widths between edge pairs, circles
(diameter, roundness), straight edges and the distances and angles between them, in pixels or
millimetres on the measuring plane; passes when every measurement is within its ``min`` and
``max`` (docs/configuration.md, "caliper").

The keys are read by :mod:`.caliper_config` (which a job's caliper step uses as well); the
analysis is :func:`vision_server.analysis.measure.measure`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from yamlfile import Node

from ..analysis import (
    AnalysisError,
    CircleSpec,
    EdgeSpec,
    LineSpec,
    Measurement,
    Spec,
    Units,
    WidthSpec,
    measure,
)
from ..cameras import CameraSettings
from .base import (
    GREEN,
    RED,
    Common,
    Configured,
    Image,
    analysis_failed,
    draw_text,
    draw_verdict,
    overlay_base,
    parse_common,
    text_px,
)
from .caliper_config import parse_measurements, parse_units
from .contract import InspectionInput, InspectionOutcome
from .kinds import Data, ResultKind, as_number

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
            "measurements": [measurement_dict(m) for m in results],
        }
        picture = None
        if overlay:
            picture = overlay_base(image.color, None)
            # The legend's boxes first, then the shapes (visible through them), its letters.
            _draw_legend(picture, results, letters=False)
            for spec in self.specs:
                _draw_spec(picture, spec)
            for number, m in enumerate(results, start=1):
                _draw_measurement(picture, m, number)
            _draw_legend(picture, results, box=False)
            failed = [m.name for m in results if not m.passed]
            draw_verdict(picture, passed, f"out: {', '.join(failed)}" if failed else "")
        return InspectionOutcome(passed, data, picture)


def _number(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def measurement_dict(m: Measurement) -> dict[str, Any]:
    """One measurement as the RESULT gives it (a caliper inspection's and a job's caliper
    step's): name, kind, value in its unit, tolerance, and where it was found (image px)."""
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


def _draw_measurement(canvas: Image, m: Measurement, number: int) -> None:
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
    if tag is not None and m.kind != "distance":
        u, v = _px(tag)
        draw_text(canvas, str(number), (u + 4, v - 4), colour)


def _draw_legend(
    canvas: Image, results: list[Measurement], *, box: bool = True, letters: bool = True
) -> None:
    """Each measurement's number, name and value at the bottom left, a line each, in green or
    red on dark boxes (``box`` and ``letters``: which layers, see :func:`.base.draw_text`)."""
    spacing = round(text_px(canvas) * 1.6)
    for number, m in enumerate(results, start=1):
        text = f"{number} {m.name} = " + (
            f"{m.value:.3f} {m.unit}" if math.isfinite(m.value) else "not measured"
        )
        v = canvas.shape[0] - 8 - spacing * (len(results) - number)
        colour = GREEN if m.passed else RED
        draw_text(canvas, text, (6, v), colour, box=box, letters=letters)


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
