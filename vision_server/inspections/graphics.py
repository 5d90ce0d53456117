"""An inspection's result as shapes for a viewer to draw over the camera's image: the online
view of the console draws them on a canvas, sized in screen pixels (docs/console.md, "Online").

:func:`result_shapes` turns an inspection's configuration and the ``data`` of one of its
results (the RESULT's values, as the result log stores them) into a list of plain JSON shapes in
**image pixels** (``u`` = column, ``v`` = row, of the image the inspection ran on; a pixel's
centre is at whole numbers). Every shape has a ``kind`` and a ``role``:

- ``rect``: ``x, y, w, h`` (an ROI: ``x .. x + w`` by pixel edges, as in the configuration);
- ``polygon``: ``points`` ``[[u, v], ...]``, closed (a fixtured ROI, a code's corners, a band);
- ``line``: ``points``, open (a width's span, a fitted line);
- ``circle``: ``u, v, r``; ``point``: ``u, v`` (a marker: a feature, an edge point);
- ``axes``: origin ``u, v`` and the tips ``x``, ``y`` (and ``z`` for a pose) ``[u, v]``;
- ``text``: ``u, v, text`` (a label anchored at an image point, drawn at screen size).

Roles: ``roi`` (where an inspection looks), ``search`` (a caliper's band or ring), ``feature``
(what a locate found), ``pass`` / ``fail`` (what a check measured, by its own outcome),
``frame`` (a fixture's part frame, a pose's axes), ``rejected`` (a candidate a locate turned
down), ``label`` (text).

The number of shapes of one result is capped at :data:`MAX_SHAPES` and texts at
:data:`MAX_TEXT` characters: the online board holds the last result of every inspection.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..analysis import CircleSpec, DistanceSpec, Spec
from .calibration_board import CalibrationBoardInspection
from .caliper import CaliperInspection
from .code import CodeInspection
from .job import JobInspection, PartFrame
from .job.caliper_step import CaliperStep
from .job.frame import IDENTITY, Affine, apply, outline, roi_transform
from .job.step import Step
from .job.tools import CodeStep, FixtureStep, LocateStep, PresenceStep
from .locate import LocateInspection
from .presence import PresenceInspection
from .qr import QRInspection
from .qr_pose import QRPoseInspection

Shape = dict[str, Any]
MAX_SHAPES = 256
"""Most shapes one result gives (the rest are dropped, the most important drawn first)."""
MAX_TEXT = 48
"""Longest text of a label, characters (a decoded code can be long)."""
AXIS_PX = 40.0
"""Length of a fixture frame's x axis in image pixels (its y axis: 25 px, as the overlay)."""


def _r(value: Any) -> float:
    """A coordinate rounded for JSON (0.01 px is far below what a screen shows)."""
    return round(float(value), 2)


def _finite(*values: Any) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in values)
    except (TypeError, ValueError):
        return False


def _number(value: Any) -> float | None:
    """``value`` as a finite float, else None (not measured, or not a number)."""
    return float(value) if _finite(value) else None


def _text(value: Any) -> str:
    text = str(value)
    return text if len(text) <= MAX_TEXT else text[: MAX_TEXT - 1] + "…"


class _Shapes:
    """A capped list of shapes, each checked for finite coordinates as it is added."""

    def __init__(self) -> None:
        self.items: list[Shape] = []

    def add(self, shape: Shape) -> None:
        if len(self.items) < MAX_SHAPES:
            self.items.append(shape)

    def rect(self, roi: Any, role: str) -> None:
        if roi is not None and len(roi) == 4 and _finite(*roi):
            x, y, w, h = (int(v) for v in roi)
            self.add({"kind": "rect", "role": role, "x": x, "y": y, "w": w, "h": h})

    def polygon(self, points: Any, role: str, *, closed: bool = True) -> None:
        pts = [[_r(p[0]), _r(p[1])] for p in points if len(p) >= 2 and _finite(p[0], p[1])]
        if len(pts) >= 2:
            self.add({"kind": "polygon" if closed else "line", "role": role, "points": pts})

    def circle(self, u: Any, v: Any, r: Any, role: str) -> None:
        if _finite(u, v, r) and float(r) > 0:
            self.add({"kind": "circle", "role": role, "u": _r(u), "v": _r(v), "r": _r(r)})

    def point(self, u: Any, v: Any, role: str) -> None:
        if _finite(u, v):
            self.add({"kind": "point", "role": role, "u": _r(u), "v": _r(v)})

    def text(self, u: Any, v: Any, text: Any, role: str = "label") -> None:
        if _finite(u, v):
            self.add({"kind": "text", "role": role, "u": _r(u), "v": _r(v), "text": _text(text)})

    def axes(self, u: float, v: float, angle: float, role: str = "frame") -> None:
        if not _finite(u, v, angle):
            return
        c, s = math.cos(angle), math.sin(angle)
        self.add(
            {
                "kind": "axes",
                "role": role,
                "u": _r(u),
                "v": _r(v),
                "x": [_r(u + AXIS_PX * c), _r(v + AXIS_PX * s)],
                "y": [_r(u - 25.0 * s), _r(v + 25.0 * c)],
            }
        )


def _verdict_role(passed: Any) -> str:
    return "pass" if passed else "fail"


# --------------------------------------------------------------------------- each type


def _presence(inspection: PresenceInspection, data: Mapping[str, Any], passed: bool) -> _Shapes:
    out = _Shapes()
    roi = inspection.common.roi
    out.rect(roi, _verdict_role(passed))
    value = _number(data.get("value"))
    if roi is not None and value is not None:
        out.text(roi[0], roi[1], f"{data.get('measure', inspection.measure)} = {value:.3f}")
    return out


def _feature_shapes(
    out: _Shapes, features: Any, method: str, template: Any, *, role: str = "feature"
) -> None:
    """A locate's features: circle (radius) or a template's turned outline, a marker, a rank."""
    if not isinstance(features, list):
        return
    size = getattr(template, "shape", None)
    for rank, f in enumerate(features, start=1):
        if not isinstance(f, Mapping) or not _finite(f.get("u"), f.get("v")):
            continue
        u, v = float(f["u"]), float(f["v"])
        angle = float(f.get("angle") or 0.0) if _finite(f.get("angle") or 0.0) else 0.0
        if f.get("radius") is not None:
            out.circle(u, v, f["radius"], role)
        elif method == "template" and size is not None:
            scale = float(f.get("scale") or 1.0)
            h, w = size[0] * scale, size[1] * scale
            frame = PartFrame(u, v, angle)
            corners = apply(frame.image_from_part(), _centred_box(w, h))
            out.polygon(corners, role)
        elif method == "blob" and _finite(f.get("area")) and float(f["area"]) > 0:
            out.circle(u, v, math.sqrt(float(f["area"]) / math.pi), role)
        out.point(u, v, role)
        if method != "circle" and angle:
            out.polygon(
                [(u, v), (u + 25 * math.cos(angle), v + 25 * math.sin(angle))], role, closed=False
            )
        out.text(u + 6, v - 6, str(rank))


def _centred_box(w: float, h: float) -> list[tuple[float, float]]:
    return [(-w / 2, -h / 2), (w / 2, -h / 2), (w / 2, h / 2), (-w / 2, h / 2)]


def _locate(inspection: LocateInspection, data: Mapping[str, Any], passed: bool) -> _Shapes:
    out = _Shapes()
    out.rect(inspection.common.roi, "roi")
    template = inspection.options.get("template")
    _feature_shapes(out, data.get("features"), inspection.method, template)
    if inspection.show_rejected:
        for r in data.get("rejected") or []:
            if isinstance(r, Mapping):
                out.circle(r.get("u"), r.get("v"), r.get("radius"), "rejected")
    return out


def _codes(
    inspection: QRInspection | CodeInspection, data: Mapping[str, Any], passed: bool
) -> _Shapes:
    out = _Shapes()
    out.rect(inspection.common.roi, "roi")
    role = _verdict_role(passed)
    codes = data.get("codes")
    if not isinstance(codes, list):
        codes = [{"corners": data.get("corners"), "text": data.get("text")}]
    for index, code in enumerate(codes):
        corners = code.get("corners") if isinstance(code, Mapping) else None
        if not isinstance(corners, list) or len(corners) < 3:
            continue
        out.polygon(corners, role if index == 0 else "feature")
        out.point(corners[0][0], corners[0][1], role)
        label = code.get("text_hri") or code.get("text") or ""
        if code.get("symbology"):
            label = f"{code['symbology']}: {label}"
        top = min(corners, key=lambda p: p[1])
        out.text(top[0], top[1] - 4, label)
    return out


def _qr_pose(inspection: QRPoseInspection, data: Mapping[str, Any], passed: bool) -> _Shapes:
    out = _Shapes()
    out.rect(inspection.common.roi, "roi")
    corners = data.get("corners")
    if isinstance(corners, list) and len(corners) >= 3:
        out.polygon(corners, _verdict_role(passed))
    pose = data.get("camera_from_qr")
    intrinsics = inspection.common.intrinsics
    if pose is not None and intrinsics is not None:
        try:
            matrix = np.asarray(pose, dtype=float).reshape(4, 4)
            length = inspection.side_m or 0.05
            origin = matrix[:3, 3]
            points = np.array([origin] + [origin + matrix[:3, i] * length for i in range(3)])
            uv = intrinsics.to_geometry().project(points)
        except (ValueError, TypeError):
            uv = None
        if uv is not None and np.isfinite(uv).all():
            out.add(
                {
                    "kind": "axes",
                    "role": "frame",
                    "u": _r(uv[0][0]),
                    "v": _r(uv[0][1]),
                    "x": [_r(uv[1][0]), _r(uv[1][1])],
                    "y": [_r(uv[2][0]), _r(uv[2][1])],
                    "z": [_r(uv[3][0]), _r(uv[3][1])],
                }
            )
            out.text(uv[0][0] + 6, uv[0][1] + 18, f"z = {matrix[2, 3]:.3f} m")
    return out


def _calibration_board(
    inspection: CalibrationBoardInspection, data: Mapping[str, Any], passed: bool
) -> _Shapes:
    out = _Shapes()
    out.rect(inspection.common.roi, "roi")
    corners = data.get("corners")
    if isinstance(corners, list) and corners:
        first = corners[0]
        out.text(first[0], first[1] - 8, f"{data.get('count')}/{data.get('of')} corners")
        for corner in corners:
            if isinstance(corner, list) and len(corner) >= 2:
                out.point(corner[0], corner[1], "feature")
    return out


def _spec_shapes(out: _Shapes, spec: Spec, matrix: Affine) -> None:
    """Where a caliper measurement looks (image px): its band, or a circle's search ring."""
    if isinstance(spec, DistanceSpec):
        return
    if isinstance(spec, CircleSpec):
        ((u, v),) = apply(matrix, [(spec.u, spec.v)])
        for r in (spec.radius - spec.search, spec.radius + spec.search):
            out.circle(u, v, max(1.0, r), "search")
        return
    band, half = spec.band, spec.band.width / 2.0
    corners = [
        band.point(0.0, -half),
        band.point(band.length, -half),
        band.point(band.length, half),
        band.point(0.0, half),
    ]
    out.polygon(apply(matrix, corners), "search")


def _measurement_shapes(
    out: _Shapes, measurements: Any, specs: Mapping[str, Spec], *, labels: bool = True
) -> None:
    """What each measurement found (image px), in pass/fail, tagged with its name and value."""
    if not isinstance(measurements, list):
        return
    for m in measurements:
        if not isinstance(m, Mapping):
            continue
        role = _verdict_role(m.get("passed"))
        tag: tuple[float, float] | None = None
        points = m.get("points") or []
        for p in points:
            out.point(p[0], p[1], role)
        if m.get("kind") == "width" and len(points) == 2:
            out.polygon(points, role, closed=False)
        if points:
            tag = (float(points[-1][0]), float(points[-1][1]))
        circle = m.get("circle_px")
        if isinstance(circle, list) and len(circle) == 3 and _finite(*circle):
            out.circle(circle[0], circle[1], circle[2], role)
            tag = (circle[0] + circle[2] * 0.7, circle[1] - circle[2] * 0.7)
        line = m.get("line_px")
        if isinstance(line, list) and len(line) == 4 and _finite(*line):
            spec = specs.get(str(m.get("name")))
            half = getattr(getattr(spec, "band", None), "length", 40.0) / 2.0
            x, y, dx, dy = (float(a) for a in line)
            out.polygon(
                [(x - dx * half, y - dy * half), (x + dx * half, y + dy * half)], role, closed=False
            )
            tag = (x, y)
        if labels and tag is not None and m.get("kind") != "distance":
            value = _number(m.get("value"))
            shown = "not measured" if value is None else f"{value:.3f} {m.get('unit', '')}"
            out.text(tag[0] + 4, tag[1] - 4, f"{m.get('name')} = {shown}".strip())


def _caliper(inspection: CaliperInspection, data: Mapping[str, Any], passed: bool) -> _Shapes:
    out = _Shapes()
    for spec in inspection.specs:
        _spec_shapes(out, spec, IDENTITY)
    _measurement_shapes(out, data.get("measurements"), {s.name: s for s in inspection.specs})
    return out


# --------------------------------------------------------------------------- job


def _frames(job: JobInspection, steps: Mapping[str, Any]) -> dict[str, PartFrame]:
    """The part frames the job's fixture steps made, from their values (u, v, angle)."""
    frames: dict[str, PartFrame] = {}
    for step in job.steps:
        values = steps.get(step.name)
        if (
            isinstance(step, FixtureStep)
            and isinstance(values, Mapping)
            and values.get("passed")
            and _finite(values.get("u"), values.get("v"), values.get("angle"))
        ):
            frames[step.name] = PartFrame(
                float(values["u"]), float(values["v"]), float(values["angle"])
            )
    return frames


def _step_outline(step: Step, frames: Mapping[str, PartFrame]) -> Any:
    """The step's ROI in image pixels: its rectangle's corners, turned with its fixture's frame
    (docs/configuration.md, "The fixture frame"); None without an ROI or when the fixture
    was not made."""
    if step.roi is None:
        return None
    x, y, w, h = step.roi
    if step.fixture is None:
        return [
            (x - 0.5, y - 0.5),
            (x + w - 0.5, y - 0.5),
            (x + w - 0.5, y + h - 0.5),
            (x - 0.5, y + h - 0.5),
        ]
    frame = frames.get(step.fixture)
    if frame is None:
        return None
    return outline(roi_transform(frame, step.roi), w, h)


def _job(job: JobInspection, data: Mapping[str, Any], passed: bool) -> _Shapes:
    out = _Shapes()
    steps = data.get("steps")
    if not isinstance(steps, Mapping):
        return out
    frames = _frames(job, steps)
    for step in job.steps:
        values = steps.get(step.name)
        if not isinstance(values, Mapping):
            continue
        role = _verdict_role(values.get("passed"))
        corners = _step_outline(step, frames)
        if corners is not None:
            out.polygon(corners, "roi" if isinstance(step, LocateStep) else role)
            top = min(corners, key=lambda p: p[1])
            out.text(top[0], top[1] - 4, step.name)
        if isinstance(step, FixtureStep) and step.name in frames:
            frame = frames[step.name]
            out.axes(frame.u, frame.v, frame.angle_rad)
            out.text(frame.u + 6, frame.v + 16, step.name)
        elif isinstance(step, LocateStep):
            template = step.options.get("template")
            _feature_shapes(out, values.get("features"), step.method, template, role=role)
        elif isinstance(step, CodeStep):
            code = values.get("corners")
            if isinstance(code, list) and len(code) >= 3:
                out.polygon(code, role)
                out.text(code[0][0], code[0][1] - 4, values.get("text_hri") or "")
        elif isinstance(step, CaliperStep):
            made = frames.get(step.fixture) if step.fixture is not None else None
            if step.fixture is None or made is not None:
                matrix = IDENTITY if made is None else made.image_from_part()
                for spec in step.specs:
                    _spec_shapes(out, spec, matrix)
            _measurement_shapes(out, values.get("measurements"), {s.name: s for s in step.specs})
        elif isinstance(step, PresenceStep) and corners is not None:
            value = _number(values.get("value"))
            if value is not None:
                out.text(corners[3][0], corners[3][1] + 16, f"{step.measure} = {value:.3f}")
    return out


# --------------------------------------------------------------------------- the entry

_BY_TYPE: dict[type, Callable[[Any, Mapping[str, Any], bool], _Shapes]] = {
    PresenceInspection: _presence,
    LocateInspection: _locate,
    QRInspection: _codes,
    CodeInspection: _codes,
    QRPoseInspection: _qr_pose,
    CalibrationBoardInspection: _calibration_board,
    CaliperInspection: _caliper,
    JobInspection: _job,
}


def result_shapes(inspection: Any, data: Mapping[str, Any], passed: bool) -> list[Shape]:
    """The shapes of one result of ``inspection`` (its configured object, as run: with the
    request's options) from the result's ``data`` and verdict, in image pixels (see the
    module). An inspection of a type without graphics, or data it cannot read (an error
    row's empty data), gives what it can: the ROI at least, never an exception."""
    draw = _BY_TYPE.get(type(inspection))
    if draw is None:
        return []
    try:
        return draw(inspection, data, passed).items
    except (KeyError, IndexError, TypeError, ValueError):
        # A result written by another version of the inspection: draw its ROI only.
        out = _Shapes()
        common = getattr(inspection, "common", None)
        out.rect(getattr(common, "roi", None), _verdict_role(passed))
        return out.items


__all__ = ["MAX_SHAPES", "MAX_TEXT", "Shape", "result_shapes"]
