"""The step types of a job: ``locate``, ``fixture``, ``presence``, ``code`` (``caliper``: its own
module, :mod:`.caliper_step`).

Each reuses the analysis of the inspection of the same name (:mod:`vision_server.analysis`)
and that inspection's key reading; a step run in a fixture's frame analyses the ROI sampled in
that frame and maps what it finds back to image pixels.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from yamlfile import Node, string

from ...analysis import (
    Expect,
    Feature,
    NotFoundError,
    Polarity,
    Rejection,
    circle_margin_px,
    locate,
    measure_presence,
    read_codes,
)
from ..code import below_grade, parse_min_grade, parse_symbologies
from ..locate import parse_locate_settings
from ..presence import parse_presence_settings
from ..qr import parse_expect
from .expression import ValueType
from .frame import Image, PartFrame, apply
from .step import Chain, Outcome, Shape, Step

StepParser = Callable[[Node, Step, Chain], Step]
"""Reads a step type's own keys; gets the common keys already read (as a plain :class:`Step`)
and the chain of earlier steps."""


def _in_range(value: float, low: float | None, high: float | None) -> bool:
    return (low is None or value >= low) and (high is None or value <= high)


# --------------------------------------------------------------------------- locate


@dataclass(frozen=True)
class LocateStep(Step):
    method: str = "circle"
    min_count: int = 1
    max_count: int = 10
    min_score: float | None = None
    options: Mapping[str, Any] = field(default_factory=dict)

    type = "locate"

    def produces(self) -> dict[str, ValueType]:
        out: dict[str, ValueType] = {"passed": "bool", "count": "number", "u": "number"}
        out.update({"v": "number", "score": "number"})
        if self.method == "circle":
            out["radius"] = "number"
        else:
            out["angle"] = "number"
        if self.method == "blob":
            out["area"] = "number"
        return out

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        margin = 0
        if self.method == "circle":  # its rays read beyond the ROI (see locate_circles)
            high = self.options.get("radius_range", (5.0, 200.0))[1]
            margin = circle_margin_px(high, self.options.get("max_edge_sigma_px", 6.0))
        region = self.region(image, earlier, margin=margin)
        kwargs: dict[str, Any] = dict(self.options)
        if self.min_score is not None:
            kwargs["min_score"] = self.min_score
        rejected: list[Rejection] = []
        if self.method == "circle":
            kwargs["rejected"] = rejected
        found = locate(
            region.image, method=self.method, roi=region.roi, max_count=self.max_count, **kwargs
        )
        if region.fixtured:
            turn = math.atan2(region.to_image[1, 0], region.to_image[0, 0])
            moved = []
            for f in found:
                ((u, v),) = apply(region.to_image, [(f.u, f.v)])
                angle = 0.0 if self.method == "circle" else f.angle + turn
                moved.append(Feature(float(u), float(v), angle, f.score, f.radius, f.area))
            found = moved
            rejected = [
                Rejection(float(u), float(v), r.radius, r.reason)
                for r, (u, v) in zip(
                    rejected, apply(region.to_image, [(r.u, r.v) for r in rejected]), strict=True
                )
            ]
        first = found[0] if found else None
        values: dict[str, Any] = {k: None for k in self.produces()}
        values.update(passed=len(found) >= self.min_count, count=len(found))
        if first is not None:
            values.update(u=first.u, v=first.v, score=first.score)
            for key in ("radius", "angle", "area"):
                if key in values:
                    values[key] = getattr(first, key)
        shapes = [Shape("polygon", region.outline)] if region.outline else []
        for f in found:
            if f.radius is not None:
                shapes.append(Shape("circle", ((f.u, f.v),), radius=f.radius))
            shapes.append(Shape("marker", ((f.u, f.v),)))
        detail: dict[str, Any] = {
            "method": self.method,
            "features": [_feature(f) for f in found],
        }
        label = f"{len(found)} found"
        if self.method == "circle":
            detail["rejected"] = [_rejection(r) for r in rejected[:MAX_STEP_REJECTED]]
        if not values["passed"]:
            # why, as a standalone locate's rejected list says it: a step that finds nothing
            # must not leave the integrator with "count 0" alone
            detail["reason"] = _why_too_few(len(found), self.min_count, rejected)
            label = f"{len(found)} found: {detail['reason']}"
        return Outcome(values["passed"], values, detail, shapes, label=label)


MAX_STEP_REJECTED = 5
"""Most rejected candidates a locate step reports (the strongest first): a job's RESULT holds
every step, so fewer than a standalone locate's."""


def _rejection(r: Rejection) -> dict[str, Any]:
    return {"u": r.u, "v": r.v, "radius": r.radius, "reason": r.reason}


def _why_too_few(found: int, needed: int, rejected: list[Rejection]) -> str:
    """A failed locate step's reason: the count, and the strongest rejected candidate's."""
    head = f"found {found}, needs {needed}"
    if not rejected:
        return head + ("" if found else ": no candidate in the ROI")
    first = rejected[0]
    more = f" (and {len(rejected) - 1} more rejected)" if len(rejected) > 1 else ""
    return f"{head}: candidate at ({first.u:.1f}, {first.v:.1f}) rejected: {first.reason}{more}"


def _feature(f: Feature) -> dict[str, Any]:
    out: dict[str, Any] = {"u": f.u, "v": f.v, "angle": f.angle, "score": f.score}
    if f.radius is not None:
        out["radius"] = f.radius
    if f.area is not None:
        out["area"] = f.area
    return out


def parse_locate_step(node: Node, head: Step, chain: Chain) -> Step:
    region = chain.region_of(head)
    method, low, high, score, options, show = parse_locate_settings(node, chain.base_dir, region)
    if show:
        raise node.error("show_rejected is not offered in a job's locate step", method)
    options.pop("rejected", None)
    return LocateStep(head.name, head.fixture, head.roi, method, low, high, score, options)


# --------------------------------------------------------------------------- fixture


@dataclass(frozen=True)
class FixtureStep(Step):
    """A part frame at the first feature of ``origin``; its x axis at that feature's angle
    (``angle_from`` = ``origin``), towards the first feature of ``x_towards``, or along +u."""

    origin: str = ""
    x_towards: str | None = None
    angle_from: str | None = None

    type = "fixture"

    def produces(self) -> dict[str, ValueType]:
        return {"passed": "bool", "u": "number", "v": "number", "angle": "number"}

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        values: dict[str, Any] = {"passed": False, "u": None, "v": None, "angle": None}
        origin = earlier[self.origin].values
        if origin.get("u") is None:
            return Outcome(False, values, {"reason": f"step {self.origin!r} found nothing"})
        u, v = float(origin["u"]), float(origin["v"])
        angle = 0.0
        if self.angle_from is not None:
            angle = float(earlier[self.angle_from].values.get("angle") or 0.0)
        if self.x_towards is not None:
            towards = earlier[self.x_towards].values
            if towards.get("u") is None:
                reason = f"step {self.x_towards!r} found nothing"
                return Outcome(False, values, {"reason": reason})
            angle = math.atan2(float(towards["v"]) - v, float(towards["u"]) - u)
        frame = PartFrame(u, v, angle)
        values.update(passed=True, u=u, v=v, angle=angle)
        shape = Shape("axes", ((u, v),), angle_rad=angle)
        label = f"({u:.1f}, {v:.1f}) {math.degrees(angle):.1f} deg"
        return Outcome(True, values, {}, [shape], frame, label)


def parse_fixture_step(node: Node, head: Step, chain: Chain) -> Step:
    if head.roi is not None:
        raise node.error("a fixture step has no ROI (it uses its origin step's feature)", "roi")
    if head.fixture is not None:
        raise node.error(
            "a fixture step is not in another's frame: its origin's feature is in image pixels",
            "fixture",
        )
    origin = node.take("origin", string)
    chain.refer(node, "origin", origin, types=("locate",))
    towards = node.take("x_towards", string, None)
    angle_from = node.take("angle_from", string, None)
    if towards is not None and angle_from is not None:
        raise node.error("give x_towards or angle_from, not both", "angle_from")
    if towards is not None:
        chain.refer(node, "x_towards", towards, types=("locate",))
    if angle_from is not None:
        step = chain.refer(node, "angle_from", angle_from, types=("locate",))
        if "angle" not in step.produces():
            raise node.error(
                f"step {angle_from!r} gives no angle (a circle has none): use x_towards with a "
                "second feature, or a template or blob locate",
                "angle_from",
            )
    return FixtureStep(head.name, head.fixture, None, origin, towards, angle_from)


# --------------------------------------------------------------------------- presence


@dataclass(frozen=True)
class PresenceStep(Step):
    measure: str = "dark_fraction"
    low: float | None = None
    high: float | None = None
    threshold: float | None = None
    template: Image | None = None
    min_blob_area: int = 20
    polarity: Polarity = "dark"

    type = "presence"

    def produces(self) -> dict[str, ValueType]:
        return {"passed": "bool", "value": "number"}

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        region = self.region(image, earlier)
        value = measure_presence(
            region.image,
            measure=self.measure,
            roi=region.roi,
            threshold=self.threshold,
            template=self.template,
            min_blob_area=self.min_blob_area,
            polarity=self.polarity,
        )
        passed = _in_range(value, self.low, self.high)
        shapes = [Shape("polygon", region.outline)] if region.outline else []
        detail = {"measure": self.measure, "min": self.low, "max": self.high}
        label = f"{self.measure} = {value:.3f}"
        return Outcome(passed, {"passed": passed, "value": value}, detail, shapes, label=label)


def parse_presence_step(node: Node, head: Step, chain: Chain) -> Step:
    settings = parse_presence_settings(node, chain.base_dir, chain.region_of(head))
    return PresenceStep(head.name, head.fixture, head.roi, *settings)


# --------------------------------------------------------------------------- code


@dataclass(frozen=True)
class CodeStep(Step):
    symbologies: tuple[str, ...] = ()
    expect: Expect = None
    min_grade: tuple[tuple[str, float], ...] = ()

    type = "code"

    def produces(self) -> dict[str, ValueType]:
        return {
            "passed": "bool",
            "found": "bool",
            "text": "text",
            "symbology": "text",
            "module_px": "number",
            "decode_margin": "number",
        }

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        region = self.region(image, earlier)
        values: dict[str, Any] = {k: None for k in self.produces()}
        values.update(passed=False, found=False)
        shapes = [Shape("polygon", region.outline)] if region.outline else []
        try:
            codes = read_codes(
                region.image, symbologies=self.symbologies, roi=region.roi, expect=self.expect
            )
        except NotFoundError as exc:
            return Outcome(False, values, {"reason": str(exc)}, shapes, label="no code")
        best = codes[0]
        corners = apply(region.to_image, best.corners) if region.fixtured else best.corners
        low = below_grade(best.grade, self.min_grade)
        values.update(
            passed=not low,
            found=True,
            text=best.text,
            symbology=best.symbology,
            module_px=best.grade.module_px,
            decode_margin=best.grade.decode_margin,
        )
        shapes.append(Shape("polygon", tuple((float(u), float(v)) for u, v in corners)))
        detail: dict[str, Any] = {
            "text_hri": best.text_hri,
            "corners": [[float(u), float(v)] for u, v in corners],
        }
        if low:
            detail["reason"] = "grade below the minimum: " + "; ".join(low)
        return Outcome(not low, values, detail, shapes, label=best.text_hri[:40])


def parse_code_step(node: Node, head: Step, chain: Chain) -> Step:
    symbologies = parse_symbologies(node)
    expect = parse_expect(node)
    return CodeStep(head.name, head.fixture, head.roi, symbologies, expect, parse_min_grade(node))


__all__ = [
    "CodeStep",
    "FixtureStep",
    "LocateStep",
    "PresenceStep",
    "StepParser",
    "parse_code_step",
    "parse_fixture_step",
    "parse_locate_step",
    "parse_presence_step",
]
