"""What every step of a job shares: its name, type, ROI and fixture; the outcome of running it;
how it refers to earlier steps (checked at load: a missing or later step is a config error).

A step's ROI is ``[x, y, width, height]`` in whole pixels: in the image when the step has no
``fixture``, else in the part frame of that fixture step (:mod:`.frame`), where it moves and
turns with the part.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from yamlfile import Node

from ..base import Common
from .expression import ValueType
from .frame import IDENTITY, Affine, Image, PartFrame, inside, outline, roi_transform, sample

ROI = tuple[int, int, int, int]


class StepSkipped(Exception):
    """A step that cannot run on this image (its fixture was not made, its ROI leaves the
    image): it fails, and says why."""


@dataclass(frozen=True)
class Shape:
    """Something an overlay draws, in image pixels: ``kind`` ``polygon`` (``points``, closed),
    ``circle`` (one point and ``radius``), ``marker`` (points) or ``axes`` (one point and
    ``angle_rad``)."""

    kind: str
    points: tuple[tuple[float, float], ...]
    radius: float = 0.0
    angle_rad: float = 0.0


@dataclass
class Outcome:
    """One step's result: pass or fail, its declared values (None: not measured), more data
    for the RESULT (``detail``), what the overlay draws, and the part frame a fixture made."""

    passed: bool
    values: dict[str, Any]
    detail: dict[str, Any] = field(default_factory=dict)
    shapes: list[Shape] = field(default_factory=list)
    frame: PartFrame | None = None
    label: str = ""
    heat: tuple[Image, Affine, float] | None = None
    """A heat map to blend into the overlay: the map (its pixels' values), the 2x3 matrix from
    its pixels to the image's, and the value drawn red (an anomaly step's threshold)."""


@dataclass(frozen=True)
class Region:
    """The pixels a step analyses and where they are: ``image`` with ``roi`` (image pixels;
    None: the whole image) when unfixtured, else the sampled patch (``roi`` None) and
    ``to_image`` mapping its pixels to image pixels."""

    image: Image
    roi: ROI | None
    to_image: Affine
    fixtured: bool
    outline: tuple[tuple[float, float], ...] | None


@dataclass(frozen=True)
class Step:
    """A step's common keys. Subclasses add their settings, ``type``, :meth:`produces` and
    :meth:`run`."""

    name: str
    fixture: str | None
    roi: ROI | None

    type: ClassVar[str] = ""

    def produces(self) -> dict[str, ValueType]:
        """The values this step gives (``passed`` always), by name, with their types."""
        return {"passed": "bool"}

    def run(self, image: Image, earlier: Mapping[str, Outcome]) -> Outcome:
        raise NotImplementedError

    def region(self, image: Image, earlier: Mapping[str, Outcome], *, margin: int = 0) -> Region:
        """The pixels to analyse: the image ROI, or the ROI sampled in the fixture's frame.
        ``margin`` (px): in a fixture's frame, sample that much around the ROI too (as much
        of it as the image holds), with ``roi`` the ROI inside the patch, for an analysis
        that looks for features in the ROI but reads their edges beyond it."""
        if self.fixture is None:
            if self.roi is None:
                return Region(image, None, IDENTITY, False, None)
            u, v, w, h = self.roi
            if u + w > image.shape[1] or v + h > image.shape[0]:
                raise StepSkipped(
                    f"ROI [{u}, {v}, {w}, {h}] lies outside the "
                    f"{image.shape[1]}x{image.shape[0]} image"
                )
            box = _points(outline(_shift(u, v), w, h))
            return Region(image, self.roi, IDENTITY, False, box)
        made = earlier[self.fixture].frame
        if made is None:
            raise StepSkipped(f"fixture {self.fixture!r} was not made")
        roi = self.roi if self.roi is not None else (0, 0, 1, 1)
        x, y, w, h = roi
        matrix = roi_transform(made, roi)
        corners = _points(outline(matrix, w, h))
        if not inside(matrix, w, h, image.shape):
            raise StepSkipped(
                f"ROI [{x}, {y}, {w}, {h}] in fixture {self.fixture!r}'s frame leaves the image"
            )
        for m in (margin, margin // 2, margin // 4):
            if m <= 0:
                break
            wide = roi_transform(made, (x - m, y - m, w + 2 * m, h + 2 * m))
            if inside(wide, w + 2 * m, h + 2 * m, image.shape):
                patch = sample(image, wide, w + 2 * m, h + 2 * m)
                return Region(patch, (m, m, w, h), wide, True, corners)
        return Region(sample(image, matrix, w, h), None, matrix, True, corners)


def _shift(u: int, v: int) -> Affine:
    return np.array([[1.0, 0.0, float(u)], [0.0, 1.0, float(v)]])


def _points(values: Any) -> tuple[tuple[float, float], ...]:
    return tuple((float(a), float(b)) for a, b in values)


class Chain:
    """The steps of a job as its parser reads them: each step may refer only to steps before
    it. Errors name the referring key (file, line, key path) and what is wrong."""

    def __init__(self, names: tuple[str, ...], base_dir: Path, common: Common) -> None:
        self.names = names
        self.base_dir = base_dir
        self.common = common
        self.earlier: dict[str, Step] = {}

    def region_of(self, head: Step) -> Common:
        """The job's common keys with the step's ROI (its size bounds a template's)."""
        return replace(self.common, roi=head.roi)

    def refer(self, node: Node, key: str, name: str, *, types: tuple[str, ...]) -> Step:
        """The earlier step ``name`` that ``node``'s ``key`` names, of one of ``types``."""
        if name not in self.names:
            raise node.error(
                f"no step named {name!r} (the steps are: {', '.join(self.names)})", key
            )
        if name not in self.earlier:
            before = ", ".join(self.earlier) or "none"
            raise node.error(
                f"step {name!r} runs later than this one: a step can use only the steps "
                f"before it (here: {before})",
                key,
            )
        step = self.earlier[name]
        if step.type not in types:
            raise node.error(
                f"step {name!r} is a {step.type} step; {key} needs a {' or '.join(types)} step",
                key,
            )
        return step


__all__ = ["ROI", "Chain", "Outcome", "Region", "Shape", "Step", "StepSkipped"]
