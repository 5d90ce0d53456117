"""Tasks: YAML files composed of skills (the paper's top layer). A task only names skills and
taught records; it runs them through the skill registry and never touches the devices.

Format::

    task: grundfos-demo              # a name
    on_failure: stop                 # the default policy (stop when omitted)
    steps:
      - qr_calibration: station-1    # "skill: record", or {skill: ..., record: ...}
      - repeat: 10                   # a group run N times (repeat: 1 or sequence: [...])
        steps:
          - vision_pick: caps_l1
            on_failure: {retry: {times: 2, wait_s: 1.0}}
          - place: bin_l2
      - quality_control: magnet
        on_failure: operator
      - press: conveyor_switch

On-failure policies: ``stop`` (end the task, failed), ``continue`` (note the failure, go on),
``operator`` (ask the operator callback: retry, skip or abort; without one: abort),
``{retry: {times: N, wait_s: S}, then: stop|continue|operator}`` (N more attempts, S seconds
apart on the skills' clock, then the ``then`` policy, default stop). A step without its own
policy uses its group's, then the task's.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import yaml

from .skills.base import SkillContext, SkillRegistry, UnknownSkill, execute
from .skills.outcome import FailureReason, Outcome
from .teach_store import TeachStore, UnknownRecord

__all__ = [
    "Group",
    "OnFailure",
    "OperatorDecision",
    "Policy",
    "Step",
    "StepReport",
    "Task",
    "TaskError",
    "TaskReport",
    "TaskRunner",
    "load_task",
    "task_from_text",
]


class TaskError(ValueError):
    """A task file that cannot be used; the message names the file and the key path."""


class Policy(StrEnum):
    STOP = "stop"
    CONTINUE = "continue"
    OPERATOR = "operator"


@dataclass(frozen=True)
class OnFailure:
    """What to do when a step fails: ``retries`` more attempts ``wait_s`` apart, then ``then``."""

    then: Policy = Policy.STOP
    retries: int = 0
    wait_s: float = 0.0


class OperatorDecision(StrEnum):
    RETRY = "retry"
    SKIP = "skip"
    ABORT = "abort"


@dataclass(frozen=True)
class Step:
    skill: str
    record: str
    on_failure: OnFailure | None = None
    path: str = ""


@dataclass(frozen=True)
class Group:
    steps: tuple[Step | Group, ...]
    repeat: int = 1
    on_failure: OnFailure | None = None
    path: str = ""


@dataclass(frozen=True)
class Task:
    name: str
    body: Group
    on_failure: OnFailure = field(default_factory=OnFailure)
    source: str = "<task>"

    def steps(self) -> list[Step]:
        """Every step, once each (repeats not unrolled)."""
        out: list[Step] = []

        def walk(group: Group) -> None:
            for s in group.steps:
                if isinstance(s, Group):
                    walk(s)
                else:
                    out.append(s)

        walk(self.body)
        return out

    def problems(self, registry: SkillRegistry, store: TeachStore) -> list[str]:
        """What would make the task fail before it starts: unknown skills and records."""
        found: list[str] = []
        for step in self.steps():
            if step.skill not in registry:
                found.append(f"{step.path}: no skill {step.skill!r} (skills: {registry.names()})")
                continue
            try:
                store.get(step.skill, step.record)
            except UnknownRecord as exc:
                found.append(f"{step.path}: {exc}")
        return found


# --- parsing ------------------------------------------------------------------------------

_GROUP_KEYS = {"repeat", "sequence", "steps", "on_failure"}


def _policy(value: Any, where: str) -> OnFailure:
    if isinstance(value, str):
        try:
            return OnFailure(Policy(value))
        except ValueError:
            pass
    elif isinstance(value, dict) and set(value) <= {"retry", "then"} and "retry" in value:
        retry = value["retry"]
        if not isinstance(retry, dict) or not set(retry) <= {"times", "wait_s"}:
            raise TaskError(f"{where}.retry: expected {{times: N, wait_s: S}}, got {retry!r}")
        times, wait = retry.get("times", 1), retry.get("wait_s", 0.0)
        if isinstance(times, bool) or not isinstance(times, int) or times < 0:
            raise TaskError(f"{where}.retry.times: expected an integer >= 0, got {times!r}")
        if isinstance(wait, bool) or not isinstance(wait, int | float) or wait < 0:
            raise TaskError(f"{where}.retry.wait_s: expected seconds >= 0, got {wait!r}")
        then = _policy(value.get("then", "stop"), f"{where}.then")
        if then.retries:
            raise TaskError(f"{where}.then: expected stop, continue or operator")
        return OnFailure(then.then, times, float(wait))
    raise TaskError(
        f"{where}: expected stop, continue, operator or {{retry: {{times, wait_s}}, then: ...}}, "
        f"got {value!r}"
    )


def _step(item: Any, where: str) -> Step | Group:
    if not isinstance(item, dict) or not item:
        raise TaskError(f"{where}: expected a mapping (a step or a group), got {item!r}")
    on_failure = (
        _policy(item["on_failure"], f"{where}.on_failure") if "on_failure" in item else None
    )
    if "repeat" in item or "sequence" in item or "steps" in item:
        unknown = sorted(set(item) - _GROUP_KEYS)
        if unknown:
            raise TaskError(f"{where}: unknown key(s) {unknown} in a group")
        repeat = item.get("repeat", 1)
        if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
            raise TaskError(f"{where}.repeat: expected an integer >= 1, got {repeat!r}")
        key = "steps" if "steps" in item else "sequence"
        if "steps" in item and "sequence" in item:
            raise TaskError(f"{where}: give steps or sequence, not both")
        return Group(_steps(item.get(key), f"{where}.{key}"), repeat, on_failure, where)
    rest = {k: v for k, v in item.items() if k != "on_failure"}
    if set(rest) == {"skill", "record"}:
        skill, record = rest["skill"], rest["record"]
    elif len(rest) == 1:
        ((skill, record),) = rest.items()
    else:
        raise TaskError(
            f"{where}: a step is 'SKILL: RECORD' or {{skill: ..., record: ...}}, got keys "
            f"{sorted(item)}"
        )
    if not isinstance(skill, str) or not isinstance(record, str) or not skill or not record:
        raise TaskError(f"{where}: skill and record must be non-empty names, got {item!r}")
    return Step(skill, record, on_failure, where)


def _steps(items: Any, where: str) -> tuple[Step | Group, ...]:
    if not isinstance(items, list) or not items:
        raise TaskError(f"{where}: expected a non-empty list of steps")
    return tuple(_step(item, f"{where}[{i}]") for i, item in enumerate(items))


def task_from_text(text: str, source: str = "<task>") -> Task:
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}" if mark is not None else ""
        raise TaskError(f"{source}: not valid YAML{line}: {getattr(exc, 'problem', exc)}") from None
    try:
        if not isinstance(doc, dict):
            raise TaskError("expected a mapping with task, steps and optionally on_failure")
        unknown = sorted(set(doc) - {"task", "steps", "on_failure"})
        if unknown:
            raise TaskError(f"unknown top-level key(s) {unknown}")
        name = doc.get("task", Path(source).stem)
        if not isinstance(name, str) or not name:
            raise TaskError("task: expected a name")
        on_failure = _policy(doc.get("on_failure", "stop"), "on_failure")
        return Task(
            name, Group(_steps(doc.get("steps"), "steps"), 1, None, "steps"), on_failure, source
        )
    except TaskError as exc:
        raise TaskError(f"{source}: {exc}") from None


def load_task(path: str | Path) -> Task:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise TaskError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return task_from_text(text, str(path))


# --- running ------------------------------------------------------------------------------


@dataclass(frozen=True)
class StepReport:
    """One executed step: where (``path``, ``iteration`` of each enclosing repeat), what,
    how many ``attempts``, its final ``outcome``, ``duration_s`` (skills' clock) and what was
    decided (``ok``, ``continued``, ``operator: retry``…)."""

    path: str
    iteration: tuple[int, ...]
    skill: str
    record: str
    attempts: int
    outcome: Outcome
    duration_s: float
    decision: str = ""

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "iteration": list(self.iteration),
            "skill": self.skill,
            "record": self.record,
            "attempts": self.attempts,
            "duration_s": round(self.duration_s, 6),
            "decision": self.decision,
            "outcome": self.outcome.to_dict(),
        }


@dataclass
class TaskReport:
    task: str
    steps: list[StepReport] = field(default_factory=list)
    ok: bool = True
    stopped_at: str | None = None
    duration_s: float = 0.0

    @property
    def failures(self) -> list[StepReport]:
        return [s for s in self.steps if not s.outcome.ok]

    def to_dict(self) -> dict[str, Any]:
        return {
            "task": self.task,
            "ok": self.ok,
            "stopped_at": self.stopped_at,
            "duration_s": round(self.duration_s, 6),
            "steps": [s.to_dict() for s in self.steps],
        }


Operator = Callable[[Step, Outcome], OperatorDecision]


class _Stop(Exception):
    pass


class TaskRunner:
    """Runs tasks: skills from ``registry``, records from ``store``, on ``ctx``.
    ``operator(step, outcome)`` decides for the ``operator`` policy; ``on_step(report)`` is
    told of every finished step (the CLI prints them)."""

    def __init__(
        self,
        registry: SkillRegistry,
        store: TeachStore,
        ctx: SkillContext,
        *,
        operator: Operator | None = None,
        on_step: Callable[[StepReport], None] | None = None,
    ) -> None:
        self.registry, self.store, self.ctx = registry, store, ctx
        self.operator, self.on_step = operator, on_step

    def run(self, task: Task) -> TaskReport:
        """Run ``task``; raises :class:`TaskError` before moving anything if it names unknown
        skills or records."""
        problems = task.problems(self.registry, self.store)
        if problems:
            raise TaskError(f"{task.source}: " + "; ".join(problems))
        report = TaskReport(task.name)
        start = self.ctx.clock.now()
        try:
            self._group(task.body, task.on_failure, (), report)
        except _Stop:
            report.ok = False
        report.duration_s = self.ctx.clock.now() - start
        if report.ok and report.failures:
            report.ok = False  # failures that were continued past still make the task not ok
        return report

    def _group(
        self, group: Group, inherited: OnFailure, iteration: tuple[int, ...], report: TaskReport
    ) -> None:
        policy = group.on_failure or inherited
        for i in range(group.repeat):
            it = (*iteration, i + 1) if group.repeat > 1 else iteration
            for item in group.steps:
                if isinstance(item, Group):
                    self._group(item, policy, it, report)
                else:
                    self._step(item, item.on_failure or policy, it, report)

    def _attempt(self, step: Step) -> Outcome:
        try:
            skill = self.registry.get(step.skill)
            record = self.store.get(step.skill, step.record)
        except UnknownSkill as exc:
            return Outcome.failure(FailureReason.UNKNOWN_SKILL, str(exc), phase="pre")
        except UnknownRecord as exc:
            return Outcome.failure(FailureReason.UNKNOWN_RECORD, str(exc), phase="pre")
        return execute(skill, record, self.ctx)

    def _step(
        self, step: Step, policy: OnFailure, iteration: tuple[int, ...], report: TaskReport
    ) -> None:
        start = self.ctx.clock.now()
        attempts = 0
        retries_left = policy.retries
        stop = False
        while True:
            attempts += 1
            outcome = self._attempt(step)
            if outcome.ok:
                decision = "ok"
                break
            if retries_left > 0:
                retries_left -= 1
                self.ctx.sleep(policy.wait_s)
                continue
            if policy.then is Policy.OPERATOR:
                choice = (
                    self.operator(step, outcome)
                    if self.operator is not None
                    else OperatorDecision.ABORT
                )
                if choice is OperatorDecision.RETRY:
                    retries_left = policy.retries
                    continue
                decision = f"operator: {choice.value}"
                stop = choice is OperatorDecision.ABORT
            else:
                decision = policy.then.value
                stop = policy.then is Policy.STOP
            break
        result = StepReport(
            step.path,
            iteration,
            step.skill,
            step.record,
            attempts,
            outcome,
            self.ctx.clock.now() - start,
            decision,
        )
        report.steps.append(result)
        if self.on_step is not None:
            self.on_step(result)
        if not outcome.ok and stop:
            report.stopped_at = step.path
            raise _Stop


def task_summary(report: TaskReport) -> Mapping[str, Any]:
    """Counts for a one-line summary."""
    return {
        "steps": len(report.steps),
        "failed": len(report.failures),
        "ok": report.ok,
        "duration_s": report.duration_s,
    }
