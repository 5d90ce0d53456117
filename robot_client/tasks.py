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
from typing import Any, cast

from yamlfile import (
    DocumentError,
    Key,
    Node,
    integer,
    kind,
    non_negative,
    non_negative_int,
    parse_document,
    read_document,
    string,
)

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
    "check_task",
    "load_task",
    "task_from_text",
]


class TaskError(DocumentError):
    """A task file that cannot be used (the message names the file, the line and the key path),
    or a task that names skills or records that do not exist."""


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
                found.append(
                    f"{step.path}: no skill {step.skill!r} (skills: {', '.join(registry.names())})"
                )
                continue
            try:
                store.get(step.skill, step.record)
            except UnknownRecord as exc:
                found.append(f"{step.path}: {exc}")
        return found


# --- parsing ------------------------------------------------------------------------------


class _TaskNode(Node):
    """A mapping of a task file; errors are TaskErrors naming file, line and key path."""

    error_type = TaskError

    def error(self, message: str, key: Key | None = None) -> TaskError:
        return cast(TaskError, super().error(message, key))


_POLICY_HELP = "stop, continue, operator or {retry: {times: N, wait_s: S}, then: ...}"


def _policy_name(value: Any) -> Policy:
    try:
        return Policy(value)
    except ValueError:
        raise ValueError(f"expected {_POLICY_HELP}, got {kind(value)}") from None


def _then(value: Any) -> Policy:
    if value not in tuple(Policy):
        raise ValueError(f"expected stop, continue or operator, got {kind(value)}")
    return Policy(value)


def _at_least_one(value: Any) -> int:
    out = integer(value)
    if out < 1:
        raise ValueError(f"expected an integer >= 1, got {value!r}")
    return out


def _policy(node: _TaskNode, key: str) -> OnFailure | None:
    """The on-failure policy at ``key`` (None when absent)."""
    if not isinstance(node.data.get(key), dict):
        name = node.take(key, _policy_name, None)
        return None if name is None else OnFailure(name)
    spec = node.sub(key)
    if "retry" not in spec:
        raise spec.error(f"expected {_POLICY_HELP}")
    retry = spec.sub("retry", required=True)
    times = retry.take("times", non_negative_int, 1)
    wait_s = retry.take("wait_s", non_negative, 0.0)
    retry.finish()
    then = spec.take("then", _then, Policy.STOP)
    spec.finish()
    return OnFailure(then, times, wait_s)


def _where(node: _TaskNode) -> str:
    """A step's place in the file as reports show it: ``steps[1].steps[0]``."""
    out = ""
    for part in node.path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else part)
    return out


def _step(node: _TaskNode) -> Step | Group:
    if not node.data:
        raise node.error("expected a step or a group, got an empty mapping")
    on_failure = _policy(node, "on_failure")
    if "repeat" in node or "sequence" in node or "steps" in node:
        if "steps" in node and "sequence" in node:
            raise node.error("give steps or sequence, not both")
        repeat = node.take("repeat", _at_least_one, 1)
        body = _steps(node, "steps" if "steps" in node else "sequence")
        node.finish()
        return Group(body, repeat, on_failure, _where(node))
    rest = [k for k in node.data if k != "on_failure"]
    if sorted(rest) == ["record", "skill"]:
        skill, record = node.take("skill", string), node.take("record", string)
    elif len(rest) == 1 and isinstance(rest[0], str) and rest[0]:
        skill, record = rest[0], node.take(rest[0], string)
    else:
        raise node.error(
            f"a step is 'SKILL: RECORD' or {{skill: ..., record: ...}}, got keys "
            f"{', '.join(sorted(map(str, node.data))) or 'none'}"
        )
    node.finish()
    return Step(skill, record, on_failure, _where(node))


def _steps(node: _TaskNode, key: str) -> tuple[Step | Group, ...]:
    value = node.data.get(key)
    if not isinstance(value, list) or not value:
        raise node.error(f"expected a non-empty list of steps, got {kind(value)}", key)
    return tuple(_step(item) for item in node.items(key))


def _task(root: _TaskNode) -> Task:
    name = root.take("task", string, Path(root.source).stem)
    on_failure = _policy(root, "on_failure") or OnFailure()
    body = Group(_steps(root, "steps"), 1, None, "steps")
    root.finish()
    return Task(name, body, on_failure, root.source)


def task_from_text(text: str, source: str = "<task>") -> Task:
    """Parse a task; errors (TaskError) name ``source``, the line and the key path."""
    return _task(parse_document(text, source=source, node_type=_TaskNode))


def load_task(path: str | Path) -> Task:
    """Read and parse a task file; errors show the file as ``path`` is given."""
    root, _ = read_document(Path(path), node_type=_TaskNode)
    return _task(root)


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


def check_task(task: Task, registry: SkillRegistry, store: TeachStore) -> None:
    """Raise :class:`TaskError` if ``task`` names skills or records that ``registry`` and
    ``store`` do not have (before anything moves)."""
    problems = task.problems(registry, store)
    if problems:
        raise TaskError(f"{task.source}: " + "; ".join(problems))


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
        self.current: tuple[Step, tuple[int, ...]] | None = None
        """The step running now and its iteration (None between steps): where a task that
        was interrupted (Ctrl-C) stopped."""
        self.report: TaskReport | None = None
        """The report of the task running or last run, complete up to the step running."""

    def run(self, task: Task) -> TaskReport:
        """Run ``task``; raises :class:`TaskError` before moving anything if it names unknown
        skills or records."""
        check_task(task, self.registry, self.store)
        report = TaskReport(task.name)
        self.report = report
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
        self.current = (step, iteration)
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
        self.current = None
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
