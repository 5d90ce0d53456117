"""The skill commands of ``robot-client``: teach, run, task run, taught list/show, skills.

Devices come from ``--backend sim`` (the default: the simulated cell of ``--scene``, sharing its
world with the vision server through ``--state-file``) or ``--backend ur --robot-host HOST``.
Taught records live in ``--store`` (default ``$CELLVISION_TEACH_STORE`` or ``taught.yaml``);
calibrated frames are kept between runs in ``--world-file`` (default: beside the store,
``<store>.world.yaml``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import yaml
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn
from rich.table import Table

from protocol.cli import ExitCode
from yamlfile import read_document

from ..address import endpoint_from_args, ssl_context
from ..devices import Devices
from ..devices.vision import LazyVision
from ..operator import DEFAULT_DEADLINE_S, ConsoleOperator, task_operator
from ..skills import Outcome, SkillContext, default_registry, execute
from ..skills import Progress as SkillProgress
from ..skills.world import WorldModel
from ..tasks import OperatorDecision, Step, StepReport, TaskRunner, check_task, load_task
from ..teach_check import check_inspection_names
from ..teach_store import TeachStore

__all__ = ["add_skill_commands"]

STORE_ENV = "CELLVISION_TEACH_STORE"
SIM_STATE_ENV = "CELLVISION_SIM_STATE"
DEFAULT_SIM_STATE = "demo-output/world-state.json"
"""The world-state file examples/cell.yaml's simulated cameras read (relative to the directory
the commands run in, the repository's root in the README): the robot and the server then see
the same world."""
DEFAULT_SCENE = "examples/scenes/grundfos_cell.yaml"


def _store(args: argparse.Namespace) -> TeachStore:
    return TeachStore(args.store or os.environ.get(STORE_ENV) or "taught.yaml")


def _world_file(args: argparse.Namespace, store: TeachStore) -> Path:
    if args.world_file:
        return Path(args.world_file)
    return store.path.with_name(store.path.stem + ".world.yaml")


def _devices(args: argparse.Namespace) -> Devices:
    endpoint = endpoint_from_args(args)
    timeout_s = args.timeout if args.timeout is not None else 10.0
    vision = LazyVision(
        endpoint.host,
        endpoint.port,
        auth_token=endpoint.token,
        ssl=ssl_context(endpoint),
        request_timeout_s=timeout_s,
        connect_timeout_s=timeout_s,
        # A skill's inspection waits out a busy server (its retry-after hint) within --timeout.
        busy_timeout_s=timeout_s,
    )
    if args.backend == "ur":
        if not args.robot_host:
            raise ValueError("--backend ur needs --robot-host HOST")
        from ..devices.ur import connect_ur

        return connect_ur(args.robot_host, vision=vision)
    from ..devices.sim import sim_devices

    state = args.state_file or os.environ.get(SIM_STATE_ENV) or DEFAULT_SIM_STATE
    return sim_devices(
        args.scene, seed=args.seed, state_path=state, vision=vision, fresh=args.fresh
    )


@contextmanager
def _context(args: argparse.Namespace, console: Console) -> Iterator[SkillContext]:
    """Devices, world model (calibrations loaded from and saved to the world file), store and
    a Rich progress display (none with --json)."""
    store = _store(args)
    devices = _devices(args)
    world = WorldModel(devices)
    world_file = _world_file(args, store)
    if world_file.exists() and not args.fresh:
        root, _ = read_document(world_file)  # the project's one YAML reader: file and line
        try:
            world.load_dict(root.data)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{world_file}: cannot read the world model: {exc}") from None
    ctx = SkillContext(devices, world, store)
    ask = _ask_operator(console) if not args.json and sys.stdin.isatty() else None
    ctx.operator = ask  # e.g. quality_control after its retries
    if getattr(args, "operator", None) == "console":
        # The person at the vision server's console; this terminal when the server cannot.
        ctx.operator = ConsoleOperator(
            devices.vision,
            ask,
            deadline_s=args.operator_timeout,
            notify=lambda text: console.print(f"[yellow]operator:[/] {escape(text)}"),
        )
    try:
        if args.json:
            yield ctx
        else:
            with _progress(console) as callback:
                ctx.progress = callback
                yield ctx
    finally:
        world_file.parent.mkdir(parents=True, exist_ok=True)
        tmp = world_file.with_name(world_file.name + ".tmp")
        tmp.write_text(yaml.safe_dump(world.to_dict(), sort_keys=False), encoding="utf-8")
        os.replace(tmp, world_file)
        devices.close()


def _ask_operator(console: Console) -> Callable[[str, Mapping[str, Any]], str]:
    """The operator at the terminal: a skill that cannot go on asks retry/continue/abort."""

    def ask(message: str, data: Mapping[str, Any]) -> str:
        console.print(f"[yellow]operator needed:[/] {escape(message)}")
        answer = console.input("retry, continue or abort? \\[abort] ").strip().lower()
        return answer if answer in ("retry", "continue", "abort") else "abort"

    return ask


@contextmanager
def _progress(console: Console) -> Iterator[Callable[[SkillProgress], None]]:
    columns = (
        SpinnerColumn(),
        TextColumn("[bold]{task.fields[skill]}[/]"),
        BarColumn(),
        TextColumn("{task.description}", markup=False),  # skill messages quote user text
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as bar:
        tasks: dict[tuple[str, str], Any] = {}

        def callback(event: SkillProgress) -> None:
            key = (event.skill, event.record)
            if key not in tasks:
                tasks[key] = bar.add_task(
                    event.message, total=1.0, skill=f"{event.skill}/{event.record}"
                )
            bar.update(tasks[key], description=event.message, completed=event.fraction)

        yield callback


def _print_outcome(outcome: Outcome, console: Console) -> None:
    if outcome.ok:
        console.print(
            "[green]OK[/] "
            + escape(f"{outcome.skill}/{outcome.record} in {outcome.duration_s:.2f} s")
        )
        for key, value in outcome.data.items():
            console.print(f"  {key}: {value}", markup=False)
    else:
        assert outcome.reason is not None
        console.print(
            f"[red]FAILED[/] {escape(f'{outcome.skill}/{outcome.record}')}: "
            f"[bold]{escape(outcome.reason.value)}[/] "
            + escape(f"({outcome.phase}) — {outcome.reason.explanation}")
        )
        console.print(f"  {outcome.message}", markup=False)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def _parse_values(args: argparse.Namespace, spec_param: Callable[[str], Any]) -> dict[str, Any]:
    values: dict[str, Any] = {}
    for item in args.params:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ValueError(f"parameters are KEY=VALUE, got {item!r}")
        try:
            param = spec_param(key)
        except KeyError as exc:
            raise ValueError(str(exc.args[0])) from None
        values[key] = "current" if text == "current" else param.parse_text(text)
    return values


# --- commands -----------------------------------------------------------------------------


def cmd_teach(args: argparse.Namespace, console: Console) -> int:
    skill = default_registry().get(args.skill)
    values = _parse_values(args, skill.spec.param)
    with _context(args, console) as ctx:
        record = skill.teach(
            args.name,
            values,
            ctx,
            frame=args.frame,
            from_current_pose=args.from_current_pose,
            notes=args.notes,
        )
        check_inspection_names(record.skill, record.params, ctx.devices.vision)
        assert ctx.store is not None
        stored = ctx.store.put(record)
    if args.json:
        print(json.dumps(stored.to_dict()))
    else:
        console.print(
            "[green]taught[/] "
            + escape(
                f"{stored.key} (revision {stored.revision}, frame {stored.frame}) "
                f"in {ctx.store.path}"
            )
        )
    return 0


def cmd_run(args: argparse.Namespace, console: Console) -> int:
    skill = default_registry().get(args.skill)
    store = _store(args)
    record = store.get(args.skill, args.name)
    with _context(args, console) as ctx:
        outcome = execute(skill, record, ctx)
    if args.json:
        print(json.dumps(outcome.to_dict()))
    else:
        _print_outcome(outcome, console)
    return ExitCode.OK if outcome.ok else ExitCode.FAILED


def _operator_options(parser: argparse.ArgumentParser, modes: tuple[str, ...]) -> None:
    parser.add_argument(
        "--operator",
        choices=modes,
        default="ask",
        help="who answers when a skill or step needs a person: ask (a prompt on this terminal, "
        "else abort), console (the vision server's console, Operator page; this terminal when "
        "the server cannot take the call)"
        + (", or always retry / skip / abort" if "retry" in modes else ""),
    )
    parser.add_argument(
        "--operator-timeout",
        type=float,
        default=DEFAULT_DEADLINE_S,
        metavar="S",
        help="with --operator console: seconds to wait for an answer before aborting "
        f"(default {DEFAULT_DEADLINE_S:g})",
    )


def _operator(mode: str, console: Console) -> Callable[[Step, Outcome], OperatorDecision]:
    def decide(step: Step, outcome: Outcome) -> OperatorDecision:
        if mode != "ask":
            return OperatorDecision(mode)
        console.print(
            f"[yellow]operator:[/] {escape(f'{step.skill}/{step.record}')} failed: "
            + escape(outcome.message)
        )
        if not sys.stdin.isatty():
            return OperatorDecision.ABORT
        answer = console.input("retry, skip or abort? \\[abort] ").strip().lower() or "abort"
        try:
            return OperatorDecision(answer)
        except ValueError:
            return OperatorDecision.ABORT

    return decide


def cmd_task_run(args: argparse.Namespace, console: Console) -> int:
    task = load_task(args.file)
    registry = default_registry()
    store = _store(args)
    # Checked before the devices exist: a refused task must not have reset the sim's world
    # (--fresh) or moved anything.
    check_task(task, registry, store)

    def on_step(step: StepReport) -> None:
        if args.json:
            return
        mark = "[green]ok[/]" if step.outcome.ok else f"[red]{escape(str(step.outcome.reason))}[/]"
        it = "".join(f"#{i}" for i in step.iteration)
        extra = "" if step.outcome.ok else escape(f" — {step.outcome.message} [{step.decision}]")
        where = escape(f"{step.path}{it} {step.skill}/{step.record}")
        console.print(
            f"{where}: {mark} "
            f"({step.attempts} attempt{'s' * (step.attempts > 1)}, {step.duration_s:.2f} s){extra}"
        )

    with _context(args, console) as ctx:
        if args.operator == "console" and ctx.operator is not None:
            decide = task_operator(ctx.operator)
        else:
            decide = _operator(args.operator, console)
        runner = TaskRunner(registry, store, ctx, operator=decide, on_step=on_step)
        started = time.monotonic()
        try:
            report = runner.run(task)
        except KeyboardInterrupt:
            _interrupted(runner, console)
            raise
    if args.json:
        print(json.dumps(report.to_dict()))
    else:
        verdict = "[green]done[/]" if report.ok else "[red]failed[/]"
        console.print(
            f"task {escape(report.task)}: {verdict}, {_count(len(report.steps), 'step')}, "
            f"{len(report.failures)} failed, "
            + _duration(report.duration_s, time.monotonic() - started, sim=args.backend == "sim")
            + (escape(f", stopped at {report.stopped_at}") if report.stopped_at else "")
        )
    return ExitCode.OK if report.ok else ExitCode.FAILED


def _duration(clock_s: float, wall_s: float, *, sim: bool) -> str:
    """A task's duration as the skills' clock measured it. In the sim that clock is simulated
    time (the arm's motions and waits; the vision requests take none of it), which is not the
    cycle time a cell would have: say so, with the wall-clock time beside it."""
    if sim:
        return f"{clock_s:.2f} s of simulated robot time ({wall_s:.2f} s wall clock)"
    return f"{clock_s:.2f} s"


def _interrupted(runner: TaskRunner, console: Console) -> None:
    """Ctrl-C during a task: where it stopped, on stderr (the CLI then exits 130)."""
    report = runner.report
    done = 0 if report is None else len(report.steps)
    where = "between steps"
    if runner.current is not None:
        step, iteration = runner.current
        it = "".join(f"#{i}" for i in iteration)
        where = f"during step {step.path}{it} {step.skill}/{step.record}"
    Console(stderr=True).print(
        f"[red]interrupted[/] {escape(where)}, after {_count(done, 'finished step')}; "
        "the robot was not sent further commands (check where it stands before running again)",
        soft_wrap=True,
    )


def cmd_taught_list(args: argparse.Namespace, console: Console) -> int:
    store = _store(args)
    records = store.records(args.skill)
    if args.json:
        print(json.dumps({"store": str(store.path), "records": [r.to_dict() for r in records]}))
        return 0
    table = Table(title=f"Taught records in {store.path}")
    for column in ("skill", "name", "rev", "frame", "taught at", "notes"):
        table.add_column(column)
    for r in records:
        cells = (r.skill, r.name, str(r.revision), r.frame, r.taught_at, r.notes)
        table.add_row(*(escape(cell) for cell in cells))
    console.print(table)
    return 0


def cmd_taught_show(args: argparse.Namespace, console: Console) -> int:
    record = _store(args).find(args.name)
    if args.json:
        print(json.dumps(record.to_dict()))
    else:
        console.print(
            yaml.safe_dump(record.to_dict(), sort_keys=False, default_flow_style=None, width=100),
            end="",
            markup=False,
        )
    return 0


def cmd_skills(args: argparse.Namespace, console: Console) -> int:
    specs = default_registry().specs()
    if args.json:
        print(
            json.dumps(
                {
                    "skills": [
                        {
                            "name": s.name,
                            "doc": s.doc,
                            "params": [
                                {"name": p.name, "type": p.type.value, "unit": p.unit, "doc": p.doc}
                                for p in s.params
                            ],
                            "pre": [c.describe() for c in s.pre],
                            "post": [c.describe() for c in s.post],
                        }
                        for s in specs
                    ]
                }
            )
        )
    else:
        for s in specs:
            console.print(s.describe(), markup=False)
            console.print()
    return 0


# --- parser -------------------------------------------------------------------------------


def _device_options() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    group = parent.add_argument_group("robot")
    group.add_argument("--backend", choices=("sim", "ur"), default="sim")
    group.add_argument("--scene", default=DEFAULT_SCENE, help="scene YAML of the simulated cell")
    group.add_argument("--seed", type=int, default=None, help="simulation seed")
    group.add_argument(
        "--state-file",
        default=None,
        help=f"the sim's shared world-state file (default ${SIM_STATE_ENV} or "
        f"{DEFAULT_SIM_STATE}, the file examples/cell.yaml's simulated cameras read)",
    )
    group.add_argument("--robot-host", default=None, help="UR controller address (--backend ur)")
    group.add_argument("--world-file", default=None, help="calibrations kept between runs")
    group.add_argument(
        "--fresh",
        action="store_true",
        help="start again: forget the kept calibrations; the sim starts from the scene with "
        "what the line delivers in place, not from --state-file",
    )
    return parent


def _store_options() -> argparse.ArgumentParser:
    parent = argparse.ArgumentParser(add_help=False)
    parent.add_argument("--store", default=None, help=f"teach store (default ${STORE_ENV})")
    return parent


def add_skill_commands(sub: Any, common: argparse.ArgumentParser) -> None:
    """Add teach, run, task, taught and skills to the ``robot-client`` subparsers; ``common``
    holds the options every command takes (server, ``--json``)."""
    dev, st = _device_options(), _store_options()

    teach = sub.add_parser(
        "teach", parents=[common, dev, st], help="teach a skill and store the record"
    )
    teach.add_argument("skill")
    teach.add_argument("name")
    teach.add_argument(
        "params", nargs="*", metavar="KEY=VALUE", help="pose: x,y,z,r,p,y or current"
    )
    teach.add_argument(
        "--from-current-pose",
        action="store_true",
        help="pose parameters not given are the robot's current tool pose",
    )
    teach.add_argument("--frame", default="base", help="frame of the poses (base or calibrated)")
    teach.add_argument("--notes", default="")
    teach.set_defaults(func=cmd_teach, sync=True)

    run = sub.add_parser("run", parents=[common, dev, st], help="execute a taught skill")
    run.add_argument("skill")
    run.add_argument("name")
    _operator_options(run, ("ask", "console"))
    run.set_defaults(func=cmd_run, sync=True)

    task = sub.add_parser("task", help="tasks composed of skills")
    task_sub = task.add_subparsers(dest="task_command", required=True)
    task_run = task_sub.add_parser("run", parents=[common, dev, st], help="run a task file")
    task_run.add_argument("file")
    _operator_options(task_run, ("ask", "console", "retry", "skip", "abort"))
    task_run.set_defaults(func=cmd_task_run, sync=True)

    taught = sub.add_parser("taught", help="the taught records")
    taught_sub = taught.add_subparsers(dest="taught_command", required=True)
    tl = taught_sub.add_parser("list", parents=[common, st], help="list taught records")
    tl.add_argument("--skill", default=None)
    tl.set_defaults(func=cmd_taught_list, sync=True)
    ts = taught_sub.add_parser(
        "show", parents=[common, st], help="show one record (NAME or SKILL/NAME)"
    )
    ts.add_argument("name")
    ts.set_defaults(func=cmd_taught_show, sync=True)

    skills = sub.add_parser("skills", parents=[common], help="the skills this robot knows")
    skills.set_defaults(func=cmd_skills, sync=True)
