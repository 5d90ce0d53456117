"""What a skill execution returns: :class:`Outcome` = success(data) or failure(reason, message);
every failure carries a :class:`FailureReason` code with a one-line explanation (SkiROS2's
``fail(msg, code)``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import Any, NoReturn

__all__ = ["FailureReason", "Outcome", "SkillFailed", "fail"]


class FailureReason(StrEnum):
    """Why a skill failed. The value is the stable code (in reports, JSON and task files)."""

    # the skill is not situated: a pre-condition does not hold
    NOT_HOLDING = "not_holding"
    GRIPPER_NOT_EMPTY = "gripper_not_empty"
    NOT_NEAR = "not_near_taught_region"
    NO_CALIBRATION = "no_calibration"
    CALIBRATION_INVALID = "calibration_invalid"
    CALIBRATION_STALE = "calibration_stale"
    # the skill ran and did not achieve its goal
    POSTCONDITION_FAILED = "postcondition_failed"
    NOT_FOUND = "not_found"
    OUT_OF_REGION = "out_of_region"
    GRASP_FAILED = "grasp_failed"
    INSPECTION_FAILED = "inspection_failed"
    NO_DEPTH = "no_depth"
    POOR_QUALITY = "poor_quality"
    # the devices or the vision server
    UNREACHABLE = "unreachable"
    DEVICE_ERROR = "device_error"
    VISION_ERROR = "vision_error"
    VISION_UNAVAILABLE = "vision_unavailable"
    # the input
    BAD_RECORD = "bad_record"
    UNKNOWN_SKILL = "unknown_skill"
    UNKNOWN_RECORD = "unknown_record"
    # people and bugs
    OPERATOR_ABORT = "operator_abort"
    INTERNAL_ERROR = "internal_error"

    @property
    def explanation(self) -> str:
        return _EXPLANATIONS[self]


_EXPLANATIONS: dict[FailureReason, str] = {
    FailureReason.NOT_HOLDING: "the skill needs a held part, and the gripper holds nothing",
    FailureReason.GRIPPER_NOT_EMPTY: "the skill needs an empty gripper, and it holds something",
    FailureReason.NOT_NEAR: "the robot is not near the region the skill was taught at",
    FailureReason.NO_CALIBRATION: "the skill was taught relative to a frame never calibrated",
    FailureReason.CALIBRATION_INVALID: "the calibration of the skill's frame is not valid",
    FailureReason.CALIBRATION_STALE: "the calibration of the skill's frame is too old",
    FailureReason.POSTCONDITION_FAILED: "the skill ran but the world is not as it should be after",
    FailureReason.NOT_FOUND: "vision found nothing to act on",
    FailureReason.OUT_OF_REGION: "what vision found lies outside the taught acceptance region",
    FailureReason.GRASP_FAILED: "the gripper closed on nothing",
    FailureReason.INSPECTION_FAILED: "the inspection's verdict is fail",
    FailureReason.NO_DEPTH: "the depth camera gave no depth where it was needed",
    FailureReason.POOR_QUALITY: "the measurement is worse than the skill accepts",
    FailureReason.UNREACHABLE: "a move target is outside the robot's workspace",
    FailureReason.DEVICE_ERROR: "a device (robot, gripper, camera) reported an error",
    FailureReason.VISION_ERROR: "the vision server answered with an error",
    FailureReason.VISION_UNAVAILABLE: "the vision server could not be reached",
    FailureReason.BAD_RECORD: "the taught record does not fit the skill",
    FailureReason.UNKNOWN_SKILL: "no skill of that name is registered",
    FailureReason.UNKNOWN_RECORD: "no taught record of that name",
    FailureReason.OPERATOR_ABORT: "the operator stopped the task",
    FailureReason.INTERNAL_ERROR: "a bug: the skill raised an unexpected exception",
}


@dataclass(frozen=True)
class Outcome:
    """The result of one skill execution.

    ``ok``: success. ``data``: what the skill measured or did (JSON-able values, metres and
    radians). On failure, ``reason`` and ``message`` (what happened, with numbers) and ``phase``:
    ``"pre"`` (a pre-condition), ``"execute"`` or ``"post"`` (a post-condition).
    ``duration_s`` on the context's clock (simulated time in the simulated cell).
    """

    ok: bool
    data: Mapping[str, Any] = field(default_factory=dict)
    reason: FailureReason | None = None
    message: str = ""
    phase: str = "execute"
    skill: str = ""
    record: str = ""
    duration_s: float = 0.0

    @classmethod
    def success(cls, data: Mapping[str, Any] | None = None, message: str = "") -> Outcome:
        return cls(True, dict(data or {}), None, message)

    @classmethod
    def failure(
        cls,
        reason: FailureReason,
        message: str,
        data: Mapping[str, Any] | None = None,
        *,
        phase: str = "execute",
    ) -> Outcome:
        return cls(False, dict(data or {}), FailureReason(reason), message, phase)

    def with_context(self, *, skill: str, record: str, duration_s: float) -> Outcome:
        return replace(self, skill=skill, record=record, duration_s=duration_s)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "ok": self.ok,
            "skill": self.skill,
            "record": self.record,
            "duration_s": round(self.duration_s, 6),
            "data": dict(self.data),
        }
        if not self.ok:
            assert self.reason is not None
            out.update(
                reason=self.reason.value,
                explanation=self.reason.explanation,
                message=self.message,
                phase=self.phase,
            )
        elif self.message:
            out["message"] = self.message
        return out

    def __str__(self) -> str:
        where = f"{self.skill}/{self.record}" if self.skill else "skill"
        if self.ok:
            return f"{where}: ok" + (f" ({self.message})" if self.message else "")
        assert self.reason is not None
        return f"{where}: {self.reason.value} ({self.phase}): {self.message}"


class SkillFailed(Exception):
    """Raised inside a skill to end it with a failure (the runner turns it into an Outcome)."""

    def __init__(
        self, reason: FailureReason, message: str, data: Mapping[str, Any] | None = None
    ) -> None:
        super().__init__(f"{reason.value}: {message}")
        self.reason = FailureReason(reason)
        self.message = message
        self.data = dict(data or {})


def fail(reason: FailureReason, message: str, data: Mapping[str, Any] | None = None) -> NoReturn:
    """End the running skill with a failure: ``fail(FailureReason.NOT_FOUND, "no cap seen")``."""
    raise SkillFailed(reason, message, data)
