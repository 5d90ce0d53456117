"""The skill model: a description (:class:`SkillSpec`: typed parameters, pre- and
post-conditions) kept apart from the implementation (:class:`Skill`), a teach phase that makes a
:class:`TaughtRecord` and an execute phase that returns an :class:`Outcome`.

Lifecycle of one execution (:func:`execute`), after py_trees' behaviour and SkiROS2's skills:

1. decode the record against the spec (``bad_record`` if it does not fit);
2. check the pre-conditions in order (a record taught in a calibrated frame first needs that
   frame's calibration); the first unmet one ends the run with its reason, phase ``pre``;
3. make the record's frame the robot's active base frame;
4. ``skill.run(args, ctx)`` → Outcome (or ``fail(...)``; device and vision errors become
   ``unreachable``/``device_error``/``vision_error``/``vision_unavailable``);
5. ``skill.terminate(args, ctx, outcome)``, always (stop motion, open a gripper left closed…);
6. on success, check the post-conditions (``postcondition_failed``, phase ``post``).
"""

from __future__ import annotations

import importlib
import logging
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypeVar

import numpy as np
from numpy.typing import NDArray

from protocol import CellvisionError

from ..devices import DeviceError, Unreachable
from ..errors import ClientError
from .conditions import CalibrationValid, Condition
from .context import Args, OperatorCallback, Progress, ProgressCallback, SkillContext
from .outcome import FailureReason, Outcome, SkillFailed, fail
from .record import REQUIRED, Param, ParamError, ParamType, TaughtRecord, utc_now_iso
from .world import BASE_FRAME

__all__ = [
    "Args",
    "OperatorCallback",
    "Progress",
    "ProgressCallback",
    "Skill",
    "SkillContext",
    "SkillRegistry",
    "SkillSpec",
    "UnknownSkill",
    "default_registry",
    "execute",
    "register_skill",
    "registry",
]

log = logging.getLogger("robot_client.skills")
FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SkillSpec:
    """What a skill is, apart from how it works: ``name``, ``doc``, typed ``params``,
    ``pre``/``post`` conditions, and whether poses are normally taught in a calibrated frame
    (``calibrated``: the CLI's teach then defaults to the latest calibrated frame)."""

    name: str
    doc: str
    params: tuple[Param, ...] = ()
    pre: tuple[Condition, ...] = ()
    post: tuple[Condition, ...] = ()
    calibrated: bool = False

    def __post_init__(self) -> None:
        names = [p.name for p in self.params]
        if len(set(names)) != len(names):
            raise ValueError(f"skill {self.name!r}: duplicate parameter names {names}")

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"skill {self.name!r} has no parameter {name!r}")

    def encode_params(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """Validate ``values`` (typed or plain) → plain values, defaults filled in."""
        unknown = sorted(set(values) - {p.name for p in self.params})
        if unknown:
            known = ", ".join(p.name for p in self.params) or "none"
            raise ParamError(
                f"skill {self.name!r} has no parameter {', '.join(unknown)} (parameters: {known})"
            )
        out: dict[str, Any] = {}
        for p in self.params:
            if p.name in values:
                out[p.name] = p.encode(values[p.name])
            elif p.required:
                raise ParamError(f"skill {self.name!r}: parameter {p.name!r} is required ({p.doc})")
            else:
                out[p.name] = p.encode(p.default)
        return out

    def decode(self, record: TaughtRecord) -> Args:
        if record.skill != self.name:
            raise ParamError(
                f"record {record.key} is for skill {record.skill!r}, not {self.name!r}"
            )
        plain = self.encode_params(record.params)
        values = {p.name: p.decode(plain[p.name]) for p in self.params}
        return Args(self, record, values)

    def describe(self) -> str:
        lines = [f"{self.name}: {self.doc}", "parameters:"]
        lines += [f"  {p.describe()}" for p in self.params] or ["  (none)"]
        lines += ["pre-conditions:"] + ([f"  {c.describe()}" for c in self.pre] or ["  (none)"])
        lines += ["post-conditions:"] + ([f"  {c.describe()}" for c in self.post] or ["  (none)"])
        return "\n".join(lines)


class Skill(ABC):
    """A skill implementation. Subclasses set ``spec`` and implement :meth:`run`; they may
    override :meth:`teach` (to measure something while teaching) and :meth:`terminate`."""

    spec: ClassVar[SkillSpec]

    @property
    def name(self) -> str:
        return self.spec.name

    def teach(
        self,
        name: str,
        values: Mapping[str, Any],
        ctx: SkillContext,
        *,
        frame: str = BASE_FRAME,
        from_current_pose: bool = False,
        notes: str = "",
    ) -> TaughtRecord:
        """Make a record from ``values`` (typed or plain). A pose or position value
        ``"current"`` — or, with ``from_current_pose``, any pose parameter not given — is the
        robot's current tool pose in ``frame``. Raises :class:`ParamError` or ValueError (the
        frame is not calibrated)."""
        given = dict(values)
        current: FloatArray | None = None
        for p in self.spec.params:
            if p.type not in (ParamType.POSE, ParamType.POSITION):
                continue
            value = given.get(p.name)
            wants = (isinstance(value, str) and value == "current") or (
                from_current_pose and p.name not in given and p.type is ParamType.POSE
            )
            if wants:
                if current is None:
                    current = ctx.world.tool_pose_in(frame)
                given[p.name] = current if p.type is ParamType.POSE else current[:3, 3]
        params = self.spec.encode_params(given)
        return TaughtRecord(self.spec.name, name, params, frame, 1, utc_now_iso(), notes)

    def initialise(self, args: Args, ctx: SkillContext) -> None:
        """Called after the pre-conditions hold, before :meth:`run`."""
        return None

    @abstractmethod
    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        """Do the skill; return ``Outcome.success(data)`` or ``Outcome.failure(...)`` (or call
        :func:`fail`). Report progress with ``ctx.report``."""

    def terminate(self, args: Args, ctx: SkillContext, outcome: Outcome) -> None:
        """Called after :meth:`run`, whatever happened (also when it raised)."""
        return None


def _failure_from_exception(exc: BaseException) -> Outcome:
    if isinstance(exc, SkillFailed):
        return Outcome.failure(exc.reason, exc.message, exc.data)
    if isinstance(exc, Unreachable):
        return Outcome.failure(FailureReason.UNREACHABLE, str(exc))
    if isinstance(exc, DeviceError):
        return Outcome.failure(FailureReason.DEVICE_ERROR, str(exc))
    if isinstance(exc, CellvisionError):
        return Outcome.failure(FailureReason.VISION_ERROR, f"{exc.code.name}: {exc.message}")
    if isinstance(exc, ClientError | ConnectionError):
        return Outcome.failure(FailureReason.VISION_UNAVAILABLE, str(exc))
    log.error("skill raised an unexpected exception", exc_info=exc)
    return Outcome.failure(FailureReason.INTERNAL_ERROR, f"{type(exc).__name__}: {exc}")


def execute(skill: Skill, record: TaughtRecord, ctx: SkillContext) -> Outcome:
    """Run one skill on one taught record through the whole lifecycle (module docstring)."""
    start = ctx.clock.now()
    ctx._current = (skill.name, record.name)

    def done(outcome: Outcome) -> Outcome:
        ctx._current = ("", "")
        return outcome.with_context(
            skill=skill.name, record=record.name, duration_s=ctx.clock.now() - start
        )

    try:
        args = skill.spec.decode(record)
    except ParamError as exc:
        return done(Outcome.failure(FailureReason.BAD_RECORD, str(exc), phase="pre"))

    pre = list(skill.spec.pre)
    if record.frame != BASE_FRAME and not any(isinstance(c, CalibrationValid) for c in pre):
        pre.insert(0, CalibrationValid())
    for condition in pre:
        unmet = condition.check(ctx, args)
        if unmet is not None:
            return done(
                Outcome.failure(
                    unmet.reason,
                    f"pre-condition {unmet.condition!r} does not hold: {unmet.message}",
                    phase="pre",
                )
            )

    outcome: Outcome
    try:
        ctx.world.use_frame(record.frame)
        skill.initialise(args, ctx)
        outcome = skill.run(args, ctx)
    except Exception as exc:
        outcome = _failure_from_exception(exc)
    try:
        skill.terminate(args, ctx, outcome)
    except Exception as exc:
        log.error("terminate of %s failed", skill.name, exc_info=exc)
        if outcome.ok:
            outcome = _failure_from_exception(exc)
    if not outcome.ok:
        return done(outcome)

    for condition in skill.spec.post:
        unmet = condition.check(ctx, args)
        if unmet is not None:
            return done(
                Outcome.failure(
                    FailureReason.POSTCONDITION_FAILED,
                    f"post-condition {unmet.condition!r} does not hold: {unmet.message}",
                    outcome.data,
                    phase="post",
                )
            )
    return done(outcome)


class UnknownSkill(LookupError):
    """No skill of that name is registered."""


_S = TypeVar("_S", bound=type[Skill])


class SkillRegistry:
    """Skills by name: what tasks and the CLI look skills up in."""

    def __init__(self) -> None:
        self._skills: dict[str, Skill] = {}

    def register(self, skill: Skill) -> Skill:
        name = skill.spec.name
        existing = self._skills.get(name)
        if existing is not None and type(existing) is not type(skill):
            raise ValueError(f"a different skill is already registered as {name!r}")
        self._skills[name] = skill
        return skill

    def get(self, name: str) -> Skill:
        try:
            return self._skills[name]
        except KeyError:
            known = ", ".join(sorted(self._skills)) or "none"
            raise UnknownSkill(f"no skill {name!r} (skills: {known})") from None

    def __contains__(self, name: object) -> bool:
        return name in self._skills

    def names(self) -> list[str]:
        return sorted(self._skills)

    def specs(self) -> list[SkillSpec]:
        return [self._skills[n].spec for n in self.names()]


registry = SkillRegistry()
"""The process-wide registry that :func:`register_skill` adds to."""


def register_skill(cls: _S) -> _S:
    """Class decorator: register one instance of the skill in :data:`registry`."""
    registry.register(cls())
    return cls


# Modules that define skills; the vision skills may not be installed yet.
SKILL_MODULES = (
    "robot_client.skills.basic",
    "robot_client.skills.vision_pick",
    "robot_client.skills.quality_control",
    "robot_client.skills.qr_calibration",
)


def default_registry() -> SkillRegistry:
    """:data:`registry` with every skill module of ours imported."""
    for module in SKILL_MODULES:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name != module:
                raise
    return registry


# re-exported for skill authors: ``from robot_client.skills.base import fail, REQUIRED``
__all__ += ["REQUIRED", "fail"]
