"""Tasks: parsing (with key paths in errors), sequence, repeat, on-failure policies, reports."""

from __future__ import annotations

import ast
from pathlib import Path
from typing import ClassVar

import pytest

from robot_client.devices.sim import sim_devices
from robot_client.skills import (
    Args,
    FailureReason,
    Outcome,
    Param,
    ParamType,
    Skill,
    SkillContext,
    SkillRegistry,
    SkillSpec,
    TaughtRecord,
)
from robot_client.tasks import (
    OnFailure,
    OperatorDecision,
    Policy,
    Step,
    TaskError,
    TaskRunner,
    load_task,
    task_from_text,
)
from robot_client.teach_store import TeachStore

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "examples/scenes/grundfos_cell.yaml"


class Count(Skill):
    """Fails its first ``fail_first`` runs (per record), then succeeds; takes 2 s."""

    spec: ClassVar[SkillSpec] = SkillSpec(
        "count", "test", (Param("fail_first", ParamType.INT, "failures before success", default=0),)
    )

    def __init__(self) -> None:
        self.runs: dict[str, int] = {}

    def run(self, args: Args, ctx: SkillContext) -> Outcome:
        n = self.runs[args.record.name] = self.runs.get(args.record.name, 0) + 1
        ctx.sleep(2.0)
        if n <= args.integer("fail_first"):
            return Outcome.failure(FailureReason.NOT_FOUND, f"run {n} found nothing")
        return Outcome.success({"run": n})


@pytest.fixture
def setup(tmp_path: Path) -> tuple[SkillRegistry, TeachStore, SkillContext, Count]:
    registry = SkillRegistry()
    skill = Count()
    registry.register(skill)
    store = TeachStore(tmp_path / "taught.yaml")
    for name, fails in (("ok", 0), ("flaky", 2), ("broken", 99)):
        store.put(TaughtRecord("count", name, {"fail_first": fails}))
    return registry, store, SkillContext.create(sim_devices(SCENE)), skill


def _run(setup: tuple[SkillRegistry, TeachStore, SkillContext, Count], text: str, **kw: object):  # type: ignore[no-untyped-def]
    registry, store, ctx, _ = setup
    return TaskRunner(registry, store, ctx, **kw).run(task_from_text(text))  # type: ignore[arg-type]


def test_sequence_and_repeat(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(
        setup,
        "task: t\nsteps:\n  - count: ok\n  - repeat: 3\n    steps:\n      - count: ok\n"
        "      - {skill: count, record: ok}\n",
    )
    assert report.ok
    assert len(report.steps) == 7
    assert [s.iteration for s in report.steps[1:3]] == [(1,), (1,)]
    assert report.steps[-1].iteration == (3,)
    assert report.steps[-1].path == "steps[1].steps[1]"
    assert report.duration_s == pytest.approx(14.0)  # simulated seconds
    assert setup[3].runs["ok"] == 7
    d = report.to_dict()
    assert d["steps"][0]["outcome"]["ok"] is True


def test_stop_is_the_default(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(setup, "steps:\n  - count: broken\n  - count: ok\n")
    assert not report.ok
    assert report.stopped_at == "steps[0]"
    assert len(report.steps) == 1
    assert report.steps[0].outcome.reason is FailureReason.NOT_FOUND
    assert report.steps[0].decision == "stop"


def test_continue_goes_on_but_the_task_is_not_ok(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(setup, "on_failure: continue\nsteps:\n  - count: broken\n  - count: ok\n")
    assert [s.outcome.ok for s in report.steps] == [False, True]
    assert report.steps[0].decision == "continue"
    assert not report.ok
    assert report.stopped_at is None


def test_retry_waits_on_the_skills_clock(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(
        setup, "steps:\n  - count: flaky\n    on_failure: {retry: {times: 3, wait_s: 5}}\n"
    )
    assert report.ok
    (step,) = report.steps
    assert step.attempts == 3
    assert step.duration_s == pytest.approx(3 * 2.0 + 2 * 5.0)


def test_retry_then_continue_when_retries_run_out(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(
        setup,
        "steps:\n  - count: broken\n"
        "    on_failure: {retry: {times: 1, wait_s: 0}, then: continue}\n"
        "  - count: ok\n",
    )
    assert report.steps[0].attempts == 2
    assert len(report.steps) == 2


def test_group_policy_is_inherited(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(
        setup,
        "steps:\n  - repeat: 2\n    on_failure: continue\n    steps:\n      - count: broken\n"
        "  - count: ok\n",
    )
    assert [s.decision for s in report.steps] == ["continue", "continue", "ok"]


@pytest.mark.parametrize(
    ("decisions", "expect_steps", "ok"),
    [
        ([OperatorDecision.SKIP], 2, False),
        ([OperatorDecision.ABORT], 1, False),
        ([OperatorDecision.RETRY, OperatorDecision.RETRY], 2, True),
    ],
)
def test_operator_policy(setup, decisions, expect_steps, ok) -> None:  # type: ignore[no-untyped-def]
    asked: list[tuple[Step, Outcome]] = []

    def operator(step: Step, outcome: Outcome) -> OperatorDecision:
        asked.append((step, outcome))
        return decisions[min(len(asked), len(decisions)) - 1]

    report = _run(
        setup,
        "steps:\n  - count: flaky\n    on_failure: operator\n  - count: ok\n",
        operator=operator,
    )
    assert len(report.steps) == expect_steps
    assert report.ok is ok
    assert asked[0][0].record == "flaky"
    assert asked[0][1].reason is FailureReason.NOT_FOUND


def test_operator_policy_without_an_operator_aborts(setup) -> None:  # type: ignore[no-untyped-def]
    report = _run(setup, "steps:\n  - count: broken\n    on_failure: operator\n  - count: ok\n")
    assert report.steps[0].decision == "operator: abort"
    assert len(report.steps) == 1


def test_unknown_skills_and_records_are_found_before_anything_moves(setup) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(
        TaskError, match=r"steps\[1\]: no skill 'pick'.*steps\[2\]: .*no record 'nope'"
    ):
        _run(setup, "steps:\n  - count: ok\n  - pick: a\n  - count: nope\n")
    assert setup[3].runs == {}


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("steps: []\n", "steps: expected a non-empty list"),
        (
            "steps:\n  - count: ok\n    on_failure: shrug\n",
            r"demo.yaml:3 steps\[0\] -> on_failure: expected stop",
        ),
        ("steps:\n  - repeat: 0\n    steps: [{count: ok}]\n", r"demo.yaml:2 steps\[0\] -> repeat"),
        ("steps:\n  - {a: b, c: d}\n", r"steps\[0\]: a step is"),
        (
            "steps:\n  - repeat: 2\n    steps:\n      - 7\n",
            r"demo.yaml:4 steps\[0\] -> steps\[0\]: expected a mapping",
        ),
        (
            "steps:\n  - count: ok\n    on_failure: {retry: {times: -1}}\n",
            r"demo.yaml:3 steps\[0\] -> on_failure -> retry -> times",
        ),
        ("colour: red\nsteps: [{count: ok}]\n", "demo.yaml:1 colour: unknown key"),
        ("steps: [\n", "demo.yaml:2: invalid YAML"),
    ],
)
def test_parse_errors_name_the_key_path(text: str, match: str) -> None:
    with pytest.raises(TaskError, match=match):
        task_from_text(text, "demo.yaml")


def test_load_task_file(tmp_path: Path) -> None:
    path = tmp_path / "grundfos.yaml"
    path.write_text(
        "steps:\n  - qr_calibration: station-1\n  - repeat: 10\n    steps:\n"
        "      - vision_pick: caps_l1\n        on_failure: {retry: {times: 2, wait_s: 1.0}}\n"
        "      - place: bin_l2\n  - quality_control: magnet\n    on_failure: operator\n"
        "  - press: conveyor_switch\n"
    )
    task = load_task(path)
    assert task.name == "grundfos"
    assert [s.skill for s in task.steps()] == [
        "qr_calibration",
        "vision_pick",
        "place",
        "quality_control",
        "press",
    ]
    assert task.steps()[1].on_failure == OnFailure(Policy.STOP, 2, 1.0)
    assert task.steps()[3].on_failure == OnFailure(Policy.OPERATOR)
    with pytest.raises(TaskError, match="cannot read"):
        load_task(tmp_path / "missing.yaml")


def test_tasks_never_touch_robot_internals() -> None:
    tree = ast.parse((REPO / "robot_client/tasks.py").read_text())
    imported = {
        node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
    } | {a.name for node in ast.walk(tree) if isinstance(node, ast.Import) for a in node.names}
    assert not any("devices" in m or "simulation" in m for m in imported), imported
