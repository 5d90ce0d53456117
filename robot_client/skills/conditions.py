"""Pre- and post-conditions: small named objects checked against the world model.

``check(ctx, args)`` returns None when the condition holds, else a :class:`Unmet` with a reason
code and a sentence that says what was expected and what is (with numbers).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .outcome import FailureReason
from .record import ParamType
from .world import distance_to_polyline

if TYPE_CHECKING:
    from .context import Args, SkillContext

__all__ = [
    "CalibrationValid",
    "Condition",
    "GripperEmpty",
    "Holding",
    "NearTaught",
    "Predicate",
    "Unmet",
]


@dataclass(frozen=True)
class Unmet:
    """A condition that does not hold: its name, the reason code and why."""

    condition: str
    reason: FailureReason
    message: str


class Condition(ABC):
    """A named condition on the world model."""

    name: str

    @abstractmethod
    def check(self, ctx: SkillContext, args: Args) -> Unmet | None: ...

    def describe(self) -> str:
        return self.name


@dataclass(frozen=True)
class Holding(Condition):
    """The gripper holds a part (place needs one)."""

    name: str = "holding"

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        if ctx.world.holding:
            return None
        return Unmet(self.name, FailureReason.NOT_HOLDING, "the gripper holds no part")

    def describe(self) -> str:
        return "the gripper holds a part"


@dataclass(frozen=True)
class GripperEmpty(Condition):
    """The gripper holds nothing (pick needs it empty)."""

    name: str = "gripper_empty"

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        if not ctx.world.holding:
            return None
        held = ctx.world.held_part or "a part"
        return Unmet(
            self.name,
            FailureReason.GRIPPER_NOT_EMPTY,
            f"the gripper already holds {held}; place it first",
        )

    def describe(self) -> str:
        return "the gripper is empty"


@dataclass(frozen=True)
class NearTaught(Condition):
    """The tool is within ``tolerance_m`` of the taught region: the polyline through the
    pose/position parameters ``params`` (one: a point; two: a segment, e.g. vision pick's
    start and end), in the record's frame."""

    params: tuple[str, ...]
    tolerance_m: float = 0.25
    name: str = "near_taught_region"

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        points = []
        for p in self.params:
            value = args[p]
            kind = args.spec_param(p).type
            points.append(value[:3, 3] if kind is ParamType.POSE else np.asarray(value))
        tool = ctx.world.tool_pose_in(args.record.frame)[:3, 3]
        distance = distance_to_polyline(tool, points)
        if distance <= self.tolerance_m:
            return None
        return Unmet(
            self.name,
            FailureReason.NOT_NEAR,
            f"the tool is {distance:.3f} m from the taught {'-'.join(self.params)} "
            f"(frame {args.record.frame!r}), more than the {self.tolerance_m:g} m allowed; "
            f"move the robot there first",
        )

    def describe(self) -> str:
        return f"the tool is within {self.tolerance_m:g} m of the taught {'-'.join(self.params)}"


@dataclass(frozen=True)
class CalibrationValid(Condition):
    """The record's frame (or ``frame``) has a valid calibration; always true for ``base``."""

    frame: str | None = None
    name: str = "calibration_valid"

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        frame = self.frame or args.record.frame
        problem = ctx.world.calibration_problem(frame)
        if problem is None:
            return None
        return Unmet(self.name, problem.reason, problem.message)

    def describe(self) -> str:
        return f"frame {self.frame or '(the record’s)'} has a valid calibration"


@dataclass(frozen=True)
class Predicate(Condition):
    """Any other condition: ``test(ctx, args)`` True when it holds; ``explanation`` says what
    was expected when it does not."""

    name: str
    test: Callable[[SkillContext, Args], bool]
    reason: FailureReason
    explanation: str

    def check(self, ctx: SkillContext, args: Args) -> Unmet | None:
        return None if self.test(ctx, args) else Unmet(self.name, self.reason, self.explanation)

    def describe(self) -> str:
        return self.explanation
