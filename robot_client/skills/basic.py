"""The basic skills tasks need besides the vision skills: ``move_to``, ``place`` and ``press``.

Poses are ``frame_from_tool`` in the record's frame; the tool's z axis is its approach
direction (docs/conventions.md), so "above" a pose is back along the tool's z.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from geometry import make_transform

from .base import Args, Skill, SkillContext, SkillSpec, register_skill
from .conditions import CalibrationValid, GripperEmpty, Holding
from .outcome import Outcome
from .record import Param, ParamType

__all__ = ["MoveTo", "Place", "Press", "along_tool_z"]

FloatArray = NDArray[np.float64]

SPEED = Param(
    "speed_m_s",
    ParamType.FLOAT,
    "linear speed (none: the robot's default)",
    "m/s",
    default=None,
    minimum=1e-4,
    maximum=2.0,
)


def along_tool_z(frame_from_tool: FloatArray, distance_m: float) -> FloatArray:
    """The pose moved ``distance_m`` along its own z axis (negative: back, "above")."""
    result: FloatArray = frame_from_tool @ make_transform(np.eye(3), [0.0, 0.0, distance_m])
    return result


def _speed(args: Args) -> float | None:
    value = args["speed_m_s"]
    return None if value is None else float(value)


def _xyz(pose: FloatArray) -> list[float]:
    return [round(float(v), 6) for v in pose[:3, 3]]


@register_skill
class MoveTo(Skill):
    spec = SkillSpec(
        name="move_to",
        doc="move the tool linearly to a taught pose",
        params=(Param("pose", ParamType.POSE, "the tool pose to go to", "m, rad"), SPEED),
    )

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        pose = args.pose("pose")
        ctx.report(f"moving to {_xyz(pose)} ({args.record.frame})", 0.0)
        ctx.robot.move_linear(pose, speed_m_s=_speed(args))
        ctx.report("arrived", 1.0)
        return Outcome.success({"pose_xyz": _xyz(pose), "frame": args.record.frame})


@register_skill
class Place(Skill):
    spec = SkillSpec(
        name="place",
        doc="put the held part down: above the taught pose, down, open the gripper, up",
        params=(
            Param("pose", ParamType.POSE, "the tool pose at which the part is released", "m, rad"),
            Param(
                "approach_m",
                ParamType.FLOAT,
                "distance back along the tool's z to approach from and retreat to",
                "m",
                default=0.1,
                minimum=0.0,
                maximum=0.5,
            ),
            SPEED,
        ),
        pre=(Holding(),),
        post=(GripperEmpty(),),
    )

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        pose = args.pose("pose")
        above = along_tool_z(pose, -args.number("approach_m"))
        speed = _speed(args)
        part = ctx.world.held_part
        ctx.report("moving above the place pose", 0.0)
        ctx.robot.move_linear(above, speed_m_s=speed)
        ctx.report("moving down", 0.3)
        ctx.robot.move_linear(pose, speed_m_s=speed)
        ctx.report("releasing", 0.6)
        ctx.gripper.open()
        ctx.world.held_part = None
        ctx.report("moving up", 0.8)
        ctx.robot.move_linear(above, speed_m_s=speed)
        ctx.report("placed", 1.0)
        return Outcome.success({"part": part, "pose_xyz": _xyz(pose)})


@register_skill
class Press(Skill):
    spec = SkillSpec(
        name="press",
        doc="operate a switch: approach, press along the tool's z by the taught depth, retract",
        params=(
            Param(
                "pose",
                ParamType.POSE,
                "the tool pose touching the switch, tool z pointing into it",
                "m, rad",
            ),
            Param(
                "depth_m",
                ParamType.FLOAT,
                "how far to push beyond the touching pose",
                "m",
                default=0.005,
                minimum=0.0,
                maximum=0.05,
            ),
            Param(
                "approach_m",
                ParamType.FLOAT,
                "distance back along the tool's z to approach from and retract to",
                "m",
                default=0.05,
                minimum=0.0,
                maximum=0.5,
            ),
            Param(
                "press_speed_m_s",
                ParamType.FLOAT,
                "speed of the push itself",
                "m/s",
                default=0.02,
                minimum=1e-4,
                maximum=0.5,
            ),
            SPEED,
        ),
        pre=(CalibrationValid(),),
        calibrated=True,
    )

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        touch = args.pose("pose")
        approach = along_tool_z(touch, -args.number("approach_m"))
        pressed = along_tool_z(touch, args.number("depth_m"))
        slow = args.number("press_speed_m_s")
        ctx.report("approaching the switch", 0.0)
        ctx.robot.move_linear(approach, speed_m_s=_speed(args))
        ctx.report("pressing", 0.4)
        ctx.robot.move_linear(pressed, speed_m_s=slow)
        ctx.report("retracting", 0.7)
        ctx.robot.move_linear(approach, speed_m_s=slow)
        ctx.report("pressed", 1.0)
        return Outcome.success(
            {
                "pressed_xyz": _xyz(pressed),
                "depth_m": args.number("depth_m"),
                "frame": args.record.frame,
            }
        )
