"""Skills: the middle layer between device primitives and tasks (the paper, section 2.1).

A skill is a :class:`SkillSpec` (typed parameters, pre- and post-conditions) plus an
implementation (:class:`Skill`): taught once (``teach`` → :class:`TaughtRecord`), executed many
times (:func:`execute` → :class:`Outcome`). See :mod:`robot_client.skills.base`.
"""

from .base import (
    Args,
    Progress,
    ProgressCallback,
    Skill,
    SkillContext,
    SkillRegistry,
    SkillSpec,
    UnknownSkill,
    default_registry,
    execute,
    register_skill,
    registry,
)
from .conditions import (
    CalibrationValid,
    Condition,
    GripperEmpty,
    Holding,
    NearTaught,
    Predicate,
    Unmet,
)
from .outcome import FailureReason, Outcome, SkillFailed, fail
from .record import (
    REQUIRED,
    Param,
    ParamError,
    ParamType,
    TaughtRecord,
    pose_from_yaml,
    pose_to_yaml,
)
from .world import BASE_FRAME, Calibration, CalibrationProblem, WorldModel

__all__ = [
    "BASE_FRAME",
    "REQUIRED",
    "Args",
    "Calibration",
    "CalibrationProblem",
    "CalibrationValid",
    "Condition",
    "FailureReason",
    "GripperEmpty",
    "Holding",
    "NearTaught",
    "Outcome",
    "Param",
    "ParamError",
    "ParamType",
    "Predicate",
    "Progress",
    "ProgressCallback",
    "Skill",
    "SkillContext",
    "SkillFailed",
    "SkillRegistry",
    "SkillSpec",
    "TaughtRecord",
    "Unmet",
    "UnknownSkill",
    "WorldModel",
    "default_registry",
    "execute",
    "fail",
    "pose_from_yaml",
    "pose_to_yaml",
    "register_skill",
    "registry",
]
