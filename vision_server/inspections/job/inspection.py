"""``job``: an inspection made of named steps run in order, later steps using earlier results
(locate a part, fixture a frame to it, check presence or read a code in ROIs that move with the
part), and a verdict expression over the steps' values. One request gives one RESULT with every
step's values and one overlay showing them all."""

from __future__ import annotations

import math
import re
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from protocol import DeadlineExceeded
from yamlfile import Node, integer, kind, string

from ...analysis import AnalysisError
from ...cameras import CameraSettings
from ..anomaly import blend_heat
from ..base import (
    GREEN,
    RED,
    Common,
    Configured,
    analysis_failed,
    draw_text,
    draw_verdict,
    overlay_base,
    parse_common,
    text_px,
    verdict_bottom,
)
from ..contract import InspectionInput, InspectionOutcome
from ..kinds import Data, ResultKind, as_number, points
from .expression import Expression, ExpressionError, parse_expression
from .registry import STEP_TYPES, WITHOUT_ROI
from .step import ROI, Chain, Outcome, Shape, Step, StepSkipped

MAX_STEPS = 32
"""Most steps in one job (a job is a short chain, not a program)."""
STEP_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
"""A step's name: an identifier, so that ``name.value`` reads unambiguously in a verdict."""


@dataclass(frozen=True)
class JobInspection(Configured):
    common: Common
    steps: tuple[Step, ...]
    verdict: Expression | None
    """None: the job passes when every step passes."""

    type = "job"
    uses_depth = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        outcomes: dict[str, Outcome] = {}
        for step in self.steps:
            if image.deadline is not None and time.monotonic() > image.deadline:
                # Nobody waits for the rest (the answer was DEADLINE_EXCEEDED): the worker is
                # freed now, not after every step of a search the deadline cut short.
                raise DeadlineExceeded(
                    f"{self.common.name}: the deadline passed before step {step.name!r} "
                    f"({len(outcomes)} of {len(self.steps)} steps ran)"
                )
            try:
                outcome = step.run(image.color, outcomes)
            except StepSkipped as exc:
                values: dict[str, Any] = {key: None for key in step.produces()}
                values["passed"] = False
                outcome = Outcome(False, values, {"reason": str(exc)}, label=f"skipped: {exc}")
            except AnalysisError as exc:
                raise analysis_failed(f"{self.common.name}.{step.name}", exc) from None
            outcomes[step.name] = outcome
        failed = [name for name, o in outcomes.items() if not o.passed]
        if self.verdict is None:
            passed = not failed
        else:
            passed = self.verdict.evaluate({name: o.values for name, o in outcomes.items()})
        fixtures = [o.frame for o in outcomes.values() if o.frame is not None]
        data: dict[str, Any] = {
            "steps": {
                step.name: {"type": step.type, **_plain(outcomes[step.name].values)}
                | _plain(outcomes[step.name].detail)
                for step in self.steps
            },
            "failed": failed,
            "verdict": "every step passes" if self.verdict is None else self.verdict.text,
            "count": len(fixtures),
            "features": [{"u": f.u, "v": f.v, "angle": f.angle_rad} for f in fixtures],
        }
        picture = None
        if overlay:
            picture = overlay_base(image.color, None)
            for o in outcomes.values():
                if o.heat is not None:
                    blend_heat(picture, *o.heat)
            # The legend under the verdict: its boxes, then the shapes (visible through
            # them on a small image, where the legend covers much of the part), its letters.
            for row, (name, o) in enumerate(outcomes.items()):
                _draw_legend(picture, row, name, o, letters=False)
            for o in outcomes.values():
                _draw_step(picture, o)
            for row, (name, o) in enumerate(outcomes.items()):
                _draw_legend(picture, row, name, o, box=False)
            text = f"{len(failed)} of {len(outcomes)} steps failed" if failed else ""
            draw_verdict(picture, passed, text)
        return InspectionOutcome(passed, data, picture)


def _plain(values: Mapping[str, Any]) -> dict[str, Any]:
    """JSON-able values (numpy scalars to floats)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if hasattr(value, "item") and not isinstance(value, bool | int | float | str):
            value = value.item()
        out[key] = value
    return out


def _pixel(point: tuple[float, float]) -> tuple[int, int]:
    return int(round(point[0])), int(round(point[1]))


def _draw_step(picture: Any, outcome: Outcome) -> None:
    """A step's shapes, green when it passed, red when not (its text is in the legend under
    the verdict: steps' shapes often share a point, the legend keeps their text apart)."""
    colour = GREEN if outcome.passed else RED
    for shape in outcome.shapes:
        _draw_shape(picture, shape, colour)


def _draw_legend(
    picture: Any, row: int, name: str, outcome: Outcome, *, box: bool = True, letters: bool = True
) -> None:
    """A step's line of the legend under the verdict, in its colour on a dark box (``box``
    and ``letters``: which layers, see :func:`draw_text`)."""
    size = text_px(picture)
    line = round(size * 1.6)
    text = f"{name}: {outcome.label}"
    baseline = verdict_bottom(picture) + round(size * 0.3) + line * row + round(size)
    colour = GREEN if outcome.passed else RED
    draw_text(picture, text, (14, baseline), colour, px=size, box=box, letters=letters)


def _draw_shape(picture: Any, shape: Shape, colour: tuple[int, int, int]) -> None:
    if shape.kind == "polygon":
        pts = np.round(np.asarray(shape.points)).astype(np.int32)
        cv2.polylines(picture, [pts], True, colour, 1, cv2.LINE_AA)
    elif shape.kind == "circle":
        cv2.circle(picture, _pixel(shape.points[0]), int(round(shape.radius)), colour, 1)
    elif shape.kind == "marker":
        for point in shape.points:
            cv2.drawMarker(picture, _pixel(point), colour, cv2.MARKER_CROSS, 10, 1)
    elif shape.kind == "axes":
        u, v = shape.points[0]
        c, s = math.cos(shape.angle_rad), math.sin(shape.angle_rad)
        for length, (du, dv) in ((40, (c, s)), (25, (-s, c))):
            tip = _pixel((u + length * du, v + length * dv))
            cv2.arrowedLine(picture, _pixel((u, v)), tip, colour, 2, cv2.LINE_AA, tipLength=0.2)


# --------------------------------------------------------------------------- reading


def _step_name(value: Any) -> str:
    text = string(value)
    if not STEP_NAME.fullmatch(text):
        raise ValueError(
            f"bad step name {text!r}: use letters, digits and '_', starting with a letter "
            "(a verdict reads it as name.value)"
        )
    return text


def _frame_roi(value: Any) -> ROI:
    """``[x, y, width, height]`` in a part frame (x, y may be negative: beside the origin)."""
    if not isinstance(value, list) or len(value) != 4:
        raise ValueError(f"expected [x, y, width, height], got {kind(value)}")
    x, y, w, h = (integer(item) for item in value)
    if w <= 0 or h <= 0:
        raise ValueError(f"an ROI needs a positive width and height, got {value!r}")
    return x, y, w, h


def _image_roi(value: Any) -> ROI:
    x, y, w, h = _frame_roi(value)
    if x < 0 or y < 0:
        raise ValueError(
            f"an ROI in the image needs u, v >= 0, got {value!r} (only an ROI in a fixture's "
            "frame may start left of or above its origin)"
        )
    return x, y, w, h


def _step_names(node: Node) -> tuple[str, ...]:
    raw = node.data.get("steps")
    if not isinstance(raw, list) or not raw:
        raise node.error("a job needs a non-empty list of steps", "steps")
    if len(raw) > MAX_STEPS:
        raise node.error(f"{len(raw)} steps; at most {MAX_STEPS}", "steps")
    return tuple(str(item.get("name")) for item in raw if isinstance(item, dict) and "name" in item)


def parse_job(node: Node, base_dir: Path, cameras: Mapping[str, CameraSettings]) -> JobInspection:
    common = parse_common(node, "job", cameras)
    if common.roi is not None:
        raise node.error("a job has no ROI of its own: give each step its roi", "roi")
    chain = Chain(_step_names(node), base_dir, common)
    for step_node in node.items("steps"):
        name = step_node.take("name", _step_name)
        if name in chain.earlier:
            raise step_node.error(f"a second step named {name!r}", "name")
        step_type = step_node.take("type", _one_of_steps)
        fixture = step_node.take("fixture", string, None)
        if fixture is not None:
            chain.refer(step_node, "fixture", fixture, types=("fixture",))
        if fixture is not None:
            region = step_node.take("roi", _frame_roi, None)
            if region is None and step_type not in WITHOUT_ROI:  # which say what they take
                raise step_node.error(
                    "a step in a fixture's frame needs an roi [x, y, width, height] in that frame",
                    "fixture",
                )
        else:
            region = step_node.take("roi", _image_roi, None)
            _check_inside(step_node, common, region)
        head = Step(name, fixture, region)
        step = STEP_TYPES[step_type](step_node, head, chain)
        step_node.finish()
        chain.earlier[name] = step
    verdict = None
    text = node.take("verdict", string, None)
    if text is not None:
        declared = {name: step.produces() for name, step in chain.earlier.items()}
        try:
            verdict = parse_expression(text, declared)
        except ExpressionError as exc:
            raise node.error(str(exc), "verdict") from None
    return JobInspection(common, tuple(chain.earlier.values()), verdict)


def _one_of_steps(value: Any) -> str:
    if value not in STEP_TYPES:
        raise ValueError(f"expected one of {', '.join(STEP_TYPES)}, got {value!r}")
    return str(value)


def _check_inside(node: Node, common: Common, region: ROI | None) -> None:
    """An image ROI must fit the camera's declared image (when it declares one)."""
    if region is None or common.image_size is None:
        return
    u, v, w, h = region
    width, height = common.image_size
    if u + w > width or v + h > height:
        raise node.error(
            f"ROI [u={u}, v={v}, width={w}, height={h}] reaches past the {width}x{height} "
            f"image of camera {common.camera!r}",
            "roi",
        )


# --------------------------------------------------------------------------- results


def _job_expected(data: Data) -> dict[str, Any]:
    frames = data.get("features") or []
    out: dict[str, Any] = {
        "count": int(data["count"]),
        "features": points((f["u"], f["v"]) for f in frames),
    }
    if frames and frames[-1].get("angle") is not None:
        out["angle"] = round(float(frames[-1]["angle"]), 4) + 0.0
    out["failed"] = list(data.get("failed") or [])
    measured = _measured(data.get("steps") or {})
    if measured:
        out["steps"] = measured
    return out


def _measured(steps: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """What a new golden entry records of the steps: what they measure or read (a caliper's
    measurements, a presence value, a code's text), not the positions the frames hold."""
    out: dict[str, dict[str, Any]] = {}
    for name, step in steps.items():
        if step.get("type") == "caliper":
            keys = [m["name"] for m in step.get("measurements") or []]
        else:
            keys = {"presence": ["value"], "code": ["text"]}.get(step.get("type"), [])
        values = {key: step.get(key) for key in keys if step.get(key) is not None}
        if values:
            out[name] = {
                k: round(v, 4) + 0.0 if isinstance(v, float) else v for k, v in values.items()
            }
    return out


def _job_summary(data: Data) -> dict[str, float]:
    # the last frame made: a chain of fixtures refines the part frame step by step
    last = data["features"][-1] if data.get("features") else {}
    failed = data.get("failed")
    out = {
        "failed": float("nan") if failed is None else float(len(failed)),
        "u": as_number(last, "u"),
        "v": as_number(last, "v"),
        "angle": as_number(last, "angle"),
    }
    # Each step's numbers as STEP.VALUE (a boolean as 1 or 0; not measured: NaN); an output
    # names those it sends, checked against the chain at load (step_summary_values).
    for step_name, step in (data.get("steps") or {}).items():
        for key, value in step.items():
            if value is None or isinstance(value, int | float):
                out[f"{step_name}.{key}"] = as_number(step, key)
    return out


def step_summary_values(job: JobInspection) -> dict[str, str | None]:
    """The summary values a job's ``output:`` may name besides its type's: ``STEP.VALUE`` for
    each value its steps declare, mapped to None when it can be sent, else to why it cannot
    (text: the line protocol and Modbus carry numbers only)."""
    out: dict[str, str | None] = {}
    for step in job.steps:
        for key, value_type in step.produces().items():
            out[f"{step.name}.{key}"] = (
                None
                if value_type != "text"
                else "it is text, and the line protocol and Modbus carry numbers only "
                "(read it from the RESULT over the TCP protocol or HTTP)"
            )
    return out


class _JobUnits(Mapping[str, str]):
    """The units of a job's summary values: the part frame's, and a step value's by its name
    (``u``, ``v``, ``radius``: px; ``angle``: rad; ``passed``, ``found``: 1/0). A caliper
    measurement's unit is its step's (px or mm), which the type does not know: none."""

    BASE = {"failed": "steps", "u": "px", "v": "px", "angle": "rad"}
    BY_VALUE = {
        "u": "px",
        "v": "px",
        "radius": "px",
        "module_px": "px",
        "angle": "rad",
        "passed": "1/0",
        "found": "1/0",
        "count": "found",
        "failed": "measurements",
    }

    def __getitem__(self, name: str) -> str:
        if name in self.BASE:
            return self.BASE[name]
        _step, dot, value = name.partition(".")
        if dot and value in self.BY_VALUE:
            return self.BY_VALUE[value]
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter(self.BASE)

    def __len__(self) -> int:
        return len(self.BASE)


RESULTS = ResultKind(
    ("count", "features", "angle", "failed", "steps"),
    _job_expected,
    _job_summary,
    units=_JobUnits(),
)
"""A job result: how many fixtures were made and their origins (the part's position), the
last frame's angle, the failed steps and the step values (golden ``count``, ``features``,
``angle``, ``failed``, ``steps``); the last fixture's origin and angle, the number of failed
steps and each step's numbers as ``STEP.VALUE`` in the summary."""

__all__ = ["MAX_STEPS", "RESULTS", "JobInspection", "parse_job", "step_summary_values"]
