"""The ``caliper`` step of a job: the measurements of ``type: caliper`` (read by
:mod:`..caliper_config`, run by :func:`vision_server.analysis.measure.measure`) with their
geometry in a fixture's part frame, so that bands and circles move and turn with the part.

Each measurement's value is a value of the step, by the measurement's name, in the step's unit
(``px`` or ``mm``; an angle in ``rad``): ``gauge.plate_width <= 80.5`` in a verdict.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from yamlfile import Node

from ...analysis import (
    CircleSpec,
    DistanceSpec,
    Measurement,
    PixelUnits,
    RoiError,
    Spec,
    Units,
    measure,
)
from ..caliper import measurement_dict
from ..caliper_config import parse_measurements, parse_units
from .expression import ValueType
from .frame import IDENTITY, Affine, Image, apply
from .step import Chain, Outcome, Shape, Step, StepSkipped

VALUE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
"""A measurement's name in a job: an identifier, as the verdict reads ``step.name``."""
RESERVED = ("passed", "failed", "units", "measurements", "reason", "type")
"""Names a measurement cannot take: the step's other values and RESULT keys."""


@dataclass(frozen=True)
class CaliperStep(Step):
    """Measurements with tolerances; passes when every one is within its ``min``/``max``."""

    specs: tuple[Spec, ...] = ()
    units: Units = PixelUnits()

    type = "caliper"

    def produces(self) -> dict[str, ValueType]:
        out: dict[str, ValueType] = {"passed": "bool", "failed": "number"}
        out.update({spec.name: "number" for spec in self.specs})
        return out

    def image_from_part(self, earlier: Mapping[str, Outcome]) -> Affine | None:
        """The fixture's 2x3 part-to-image matrix (None: the specs are in image pixels)."""
        if self.fixture is None:
            return None
        made = earlier[self.fixture].frame
        if made is None:
            raise StepSkipped(f"fixture {self.fixture!r} was not made")
        return made.image_from_part()

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        matrix = self.image_from_part(earlier)
        try:
            results = measure(image, self.specs, units=self.units, image_from_part=matrix)
        except RoiError as exc:
            where = "" if self.fixture is None else f" in fixture {self.fixture!r}'s frame"
            raise StepSkipped(f"a measurement{where} leaves the image: {exc}") from None
        failed = [m for m in results if not m.passed]
        values: dict[str, Any] = {"passed": not failed, "failed": len(failed)}
        for m in results:
            values[m.name] = float(m.value) if math.isfinite(m.value) else None
        shapes = [s for spec in self.specs for s in _where(spec, matrix)]
        for m in results:
            shapes.extend(_found(m))
        detail = {
            "units": self.units.unit,
            "measurements": [measurement_dict(m) for m in results],
        }
        return Outcome(not failed, values, detail, shapes, label=_label(results))


def _label(results: list[Measurement]) -> str:
    first = results[0]
    text = f"{first.name} = " + (
        f"{first.value:.3f} {first.unit}" if math.isfinite(first.value) else "not measured"
    )
    out = [m.name for m in results if not m.passed]
    return text + (f"; out: {', '.join(out)}" if out else "")


def _where(spec: Spec, matrix: Affine | None) -> list[Shape]:
    """Where a measurement looks, in image pixels: its band's outline, or a circle's search
    ring (two circles), moved by the fixture."""
    m = IDENTITY if matrix is None else matrix
    if isinstance(spec, DistanceSpec):
        return []
    if isinstance(spec, CircleSpec):
        ((u, v),) = apply(m, [(spec.u, spec.v)])
        centre = ((float(u), float(v)),)
        return [
            Shape("circle", centre, radius=max(1.0, r))
            for r in (spec.radius - spec.search, spec.radius + spec.search)
        ]
    band, half = spec.band, spec.band.width / 2.0
    corners = [
        band.point(0.0, -half),
        band.point(band.length, -half),
        band.point(band.length, half),
        band.point(0.0, half),
    ]
    return [Shape("polygon", tuple((float(a), float(b)) for a, b in apply(m, corners)))]


def _found(m: Measurement) -> list[Shape]:
    """What a measurement found (image pixels): edge points, a width's span, a fitted circle
    or line."""
    out: list[Shape] = []
    if m.kind == "distance":
        return out
    if m.points and m.kind in ("edge", "width"):
        out.append(Shape("marker", m.points))
    if m.kind == "width" and len(m.points) == 2:
        out.append(Shape("polygon", m.points))  # two points: the span as a line
    if m.circle is not None:
        circle = m.circle
        out.append(Shape("circle", ((circle.x, circle.y),), radius=circle.radius))
    if m.line is not None:
        line = m.line
        half = line.extent / 2.0
        ends = np.array(
            [
                (line.x - line.dx * half, line.y - line.dy * half),
                (line.x + line.dx * half, line.y + line.dy * half),
            ]
        )
        out.append(Shape("polygon", tuple((float(a), float(b)) for a, b in ends)))
    return out


def parse_caliper_step(node: Node, head: Step, chain: Chain) -> Step:
    """A caliper step's keys: those of ``type: caliper`` (``units``, ``plane_distance_m``,
    ``mm_per_px``, ``measurements``). Without a fixture every band must lie inside the camera's
    declared image; in a fixture's frame, a band that the part's pose moves out of the image
    fails the step at run time with its reason."""
    if head.roi is not None:
        raise node.error(
            "a caliper step reads where its measurements' bands are; it has no roi", "roi"
        )
    common = chain.common
    units = parse_units(node, common.camera, common.intrinsics)
    size = common.image_size if head.fixture is None else None
    specs = parse_measurements(node, image_size=size)
    items = node.items("measurements")
    for item, spec in zip(items, specs, strict=True):
        if not VALUE_NAME.fullmatch(spec.name):
            raise item.error(
                f"bad name {spec.name!r} in a job: use letters, digits and '_', starting with a "
                "letter (a verdict reads it as step.name)",
                "name",
            )
        if spec.name in RESERVED:
            raise item.error(
                f"a measurement cannot be named {spec.name!r} in a job (the step's own keys: "
                f"{', '.join(RESERVED)})",
                "name",
            )
    return CaliperStep(head.name, head.fixture, None, specs, units)


__all__ = ["CaliperStep", "parse_caliper_step"]
