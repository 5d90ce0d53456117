"""``make demo``: the paper's cell end to end, on the simulated cell.

1. Starts the vision server with a copy of ``examples/cell.yaml`` (simulated cameras) as a
   subprocess, with a ``calibration_board`` inspection for commissioning added.
2. Builds the simulated cell on the robot side (the writer of the world-state file that the
   server's ``qc`` camera renders), with a ChArUco board on a stand, docks the robot with a
   random error, commissions the tool camera, which the robot program knows only from its
   data sheet and drawing (intrinsics, then hand-eye: :mod:`robot_client.demo.commission`),
   and runs the task
   ``examples/robot/demo_task.yaml`` with the records in ``examples/robot/taught.yaml`` (a
   copy, with the commissioned ``hand_eye/tool_camera`` added):
   calibrate on the QR code, vision-pick rotor caps at L1 and L2 into the bin, check the
   magnet, press the conveyor switch.
3. The injected failure: the upstream station is late. The magnet is not in its slot when
   quality control first looks; the station puts it there (the scene's ``delivered`` pose,
   :meth:`SimCell.deliver`) 0.5 s later (simulated time), while the skill waits before its
   retry. So the demo shows fail → wait → retry → pass. (By hand, ``robot-client task run
   --fresh`` starts with the magnet delivered: nobody is late there.)
4. Measures each skill against the simulation's ground truth (grasp error per cap, the
   calibrated QR frame, the switch press) beside the paper's figures, prints a summary, writes
   overlay images (the server's own drawings of what it found) to the output directory, stops
   the server and exits 0 only if every step succeeded and every error bound held.

    python -m robot_client.demo [--output DIR] [--no-live] [--stay] [--pace S]

``--stay`` keeps the vision server and its web console running after the task (the console's
address and "Ctrl-C to stop" are printed), so that a person can look at the demo's cameras
and results; Ctrl-C then stops the server and the demo exits as it would have. ``--pace S``
waits S seconds after each step, to follow the cell live in the console. Without them the
demo ends by itself (CI runs it so).
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray
from rich import box
from rich.console import Console
from rich.progress import BarColumn, Progress, SpinnerColumn, TextColumn
from rich.table import Table

from geometry import invert_transform, make_transform
from simulation import BOARD_FROM_QR, SimCell, load_scene

from ..client import SyncVisionClient, overlay_image
from ..devices import Clock
from ..devices.sim import sim_devices
from ..skills import Progress as SkillProgress
from ..skills import SkillContext, SkillRegistry, default_registry
from ..tasks import Group, StepReport, Task, TaskReport, TaskRunner, load_task
from ..teach_store import TeachStore
from ..vision_geometry import rotation_error_rad
from .cell import DemoServer, grasp_error_m, vision_server
from .commission import (
    BOARD_INSPECTION,
    Commissioned,
    commission_tool_camera,
    uncommissioned_camera,
    with_board,
)

__all__ = ["Check", "DemoResult", "main", "run_demo"]

REPO = Path(__file__).resolve().parents[2]
CONFIG = REPO / "examples" / "cell.yaml"
TASK = REPO / "examples" / "robot" / "demo_task.yaml"
TAUGHT = REPO / "examples" / "robot" / "taught.yaml"
DEFAULT_OUTPUT = REPO / "demo-output"
MAGNET_DELAY_S = 0.5  # how late the upstream station is, after quality control first looks

# The paper's figures (section 3): pick within ±5 mm; calibration "at least ±10 mm at any
# position" (the switch), in under 1 s (Table 4). They are the demo's pass bounds.
PAPER_PICK_M = 5e-3
PAPER_CALIBRATION_M = 10e-3
# The tool camera's hand-eye from commissioning: issue 18's goal is p95 0.3 mm / 0.05 deg over
# seeds (bench/hand_eye.py, where single seeds reach 0.3 mm / 0.066 deg); one run's bound.
COMMISSION_M = 0.5e-3
COMMISSION_RAD = np.radians(0.1)

FloatArray = NDArray[np.float64]


# --- the vision server ------------------------------------------------------------------------


def demo_config(output: Path) -> Path:
    """A copy of examples/cell.yaml in ``output`` with the result log and the world-state file
    in ``output`` (where the example's own paths point for demo-output/) and the commissioning
    board's ``calibration_board`` inspection added."""
    doc = yaml.safe_load(CONFIG.read_text(encoding="utf-8"))
    doc["results"]["path"] = str(output / "results.sqlite3")
    qc = doc["cameras"]["qc"]
    qc["scene"] = str((CONFIG.parent / qc["scene"]).resolve())
    qc["state_file"] = str(output / "world-state.json")
    if "console" in doc:
        # Any free port (the demo prints the address): 7880 may be taken by another server
        # or demo on this machine, and the demo must not depend on it.
        doc["console"]["port"] = 0
    doc["inspections"].append(dict(BOARD_INSPECTION))
    path = output / "cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def state_file(config: Path) -> Path:
    """The world-state file the configuration's ``qc`` camera reads."""
    doc = yaml.safe_load(config.read_text(encoding="utf-8"))
    return (config.parent / str(doc["cameras"]["qc"]["state_file"])).resolve()


# --- the simulated cell around the robot --------------------------------------------------------


class UpstreamStation:
    """The station upstream of quality control, running late: it puts the magnet into its slot
    ``delay_s`` (simulated time) after :meth:`start`, i.e. after quality control first looks."""

    def __init__(self, cell: SimCell, delay_s: float) -> None:
        self.cell, self.delay_s = cell, delay_s
        self.due: float | None = None
        self.placed_at: float | None = None

    def start(self) -> None:
        if self.due is None:
            self.due = self.cell.clock.now() + self.delay_s

    def tick(self) -> None:
        if self.due is None or self.placed_at is not None or self.cell.clock.now() < self.due:
            return
        # Into the slot the scene gives it; written to the world-state file, so the server's qc
        # camera renders the magnet in place from now on.
        self.cell.deliver("magnet")
        self.placed_at = self.cell.clock.now()


class CellClock:
    """The skills' clock: the simulated clock, with the upstream station working while the
    robot waits."""

    def __init__(self, inner: Clock, upstream: UpstreamStation) -> None:
        self.inner, self.upstream = inner, upstream

    def now(self) -> float:
        return self.inner.now()

    def sleep(self, seconds: float) -> None:
        self.inner.sleep(seconds)
        self.upstream.tick()


class OverlayRecorder:
    """The vision client as the skills see it. It keeps each inspection's last request, so the
    demo can ask again with ``overlay=True`` on the same images; an inspection on the server's
    own camera that fails is asked again at once (that camera sees the world as it is now)."""

    def __init__(self, vision: SyncVisionClient, output: Path) -> None:
        self.vision, self.output = vision, output
        self.last: dict[str, tuple[Any, dict[str, Any]]] = {}
        self.written: list[Path] = []
        self.request_s = 0.0  # wall time in the skills' requests
        self._failed_live: set[str] = set()

    def inspect(self, inspection: str, image: Any = None, **kwargs: Any) -> Any:
        start = time.perf_counter()
        result = self.vision.inspect(inspection, image, **kwargs)
        self.request_s += time.perf_counter() - start
        self.last[inspection] = (image, kwargs)
        if image is None and not result.passed and inspection not in self._failed_live:
            self._failed_live.add(inspection)
            self.save(inspection, "fail")
        return result

    def save(self, inspection: str, label: str) -> Path | None:
        """Ask ``inspection`` again on its last images with an overlay; write it as PNG."""
        if inspection not in self.last:
            return None
        image, kwargs = self.last[inspection]
        picture = overlay_image(self.vision.inspect(inspection, image, **kwargs, overlay=True))
        if picture is None:
            return None
        path = self.output / f"{len(self.written) + 1:02d}_{inspection}_{label}.png"
        cv2.imwrite(str(path), picture)
        self.written.append(path)
        return path

    def ping(self, data: str = "") -> float:
        return self.vision.ping(data)

    def list_inspections(self) -> tuple[dict[str, Any], ...]:
        return self.vision.list_inspections()

    def capture(self, camera: str, **kwargs: Any) -> Any:
        return self.vision.capture(camera, **kwargs)


# --- ground truth -------------------------------------------------------------------------------


def true_base_from_qr(cell: SimCell, text: str) -> FloatArray:
    """The QR code's true pose in the robot's true (docked) mount base frame."""
    board = next(q for q in cell.scene.qr_boards if q.text == text)
    result: FloatArray = invert_transform(cell.world.world_from_base) @ (
        board.world_from_board @ BOARD_FROM_QR
    )
    return result


def press_error_m(cell: SimCell, approach_m: float) -> tuple[str, float]:
    """After ``press`` retracted by ``approach_m``: the nearest switch and the distance of the
    pose that touched it from the switch's true position."""
    touch = cell.world.world_from_tool() @ make_transform(np.eye(3), [0.0, 0.0, approach_m])
    distances = {
        s.name: float(np.linalg.norm(touch[:3, 3] - s.world_from_switch[:3, 3]))
        for s in cell.scene.switches
    }
    name = min(distances, key=lambda n: distances[n])
    return name, distances[name]


# --- the run ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Check:
    """One thing the demo verifies: a measured ``value`` (text) against a ``bound`` (text),
    the paper's figure for it, and whether it held (None: shown, not judged)."""

    what: str
    value: str
    bound: str
    paper: str
    ok: bool | None  # None: for information, not a pass criterion


@dataclass
class StepRow:
    """A finished step: the runner's report, wall time, of which waiting for the vision
    server (requests only, without the demo's overlay requests), and what it did."""

    report: StepReport
    wall_s: float
    vision_s: float
    detail: str


@dataclass
class DemoResult:
    steps: list[StepRow] = field(default_factory=list)
    checks: list[Check] = field(default_factory=list)
    overlays: list[Path] = field(default_factory=list)
    task: TaskReport | None = None
    errors: dict[str, float] = field(default_factory=dict)  # metres / radians, for tests
    server_exit: int | None = None
    error: str | None = None
    wall_s: float = 0.0

    @property
    def ok(self) -> bool:
        return (
            self.error is None
            and self.task is not None
            and self.task.ok
            and all(c.ok is not False for c in self.checks)
            and self.server_exit == 0
        )


class DemoObserver:
    """Measures each finished step against the ground truth and writes its overlays."""

    def __init__(
        self, ctx: SkillContext, cell: SimCell, recorder: OverlayRecorder, result: DemoResult
    ) -> None:
        self.ctx, self.cell, self.recorder, self.result = ctx, cell, recorder, result

    def measure(self, step: StepReport, vision_s: float) -> str:
        """Checks for one finished step; returns a one-line detail for the summary."""
        out = step.outcome
        if not out.ok:
            return out.message
        checks = self.result.checks
        if step.skill == "qr_calibration":
            self.recorder.save("station_pose", "calibration")
            estimate = self.ctx.world.calibrations[str(out.data["frame"])].base_from_frame
            truth = true_base_from_qr(self.cell, str(out.data["text"]))
            t_err = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]))
            r_err = rotation_error_rad(estimate, truth)
            self.result.errors.update(calibration_m=t_err, calibration_rad=r_err)
            checks.append(
                Check(
                    f"calibration {out.data['frame']}",
                    f"{t_err * 1e3:.2f} mm {np.degrees(r_err):.2f}°",
                    "≤ 10 mm",
                    "±10 mm",
                    t_err <= PAPER_CALIBRATION_M,
                )
            )
            checks.append(
                Check(
                    "calibration time (vision)",
                    f"{vision_s:.2f} s",
                    "",
                    "< 1 s",
                    None,
                )
            )
            return f"moved {float(out.data.get('shift_m', 0)) * 1e3:.1f} mm"
        if step.skill == "vision_pick":
            self.recorder.save("cap_locate", str(out.data["part"]))
            error = grasp_error_m(self.cell)
            self.result.errors[f"pick_{out.data['part']}_m"] = error
            checks.append(
                Check(
                    f"pick {out.data['part']} ({out.record})",
                    f"{error * 1e3:.2f} mm",
                    "≤ 5 mm",
                    "±5 mm",
                    error <= PAPER_PICK_M,
                )
            )
            return f"{out.data['part']}, view {out.data['view'] + 1}/{out.data['views']}"
        if step.skill == "place":
            part = str(out.data["part"])
            where = self.cell.world.parts[part].location
            bins = {b.name for b in self.cell.scene.bins}
            checks.append(Check(f"place {part}", where or "-", "a bin", "", where in bins))
            return f"{part} → {where}"
        if step.skill == "quality_control":
            self.recorder.save(str(out.data["inspection"]), "pass")
            verdicts = [a["verdict"] for a in out.data["attempts"]]
            checks.append(
                Check(
                    "quality control magnet",
                    " → ".join(verdicts),
                    "fail → pass",
                    "Fig. 4b",
                    verdicts == ["fail", "pass"],
                )
            )
            values = ", ".join(f"{a.get('value', 0):.2f}" for a in out.data["attempts"])
            return f"{' → '.join(verdicts)} ({values})"
        if step.skill == "press":
            assert self.ctx.store is not None
            approach = float(self.ctx.store.get("press", step.record).params["approach_m"])
            switch, error = press_error_m(self.cell, approach)
            self.result.errors["switch_m"] = error
            checks.append(
                Check(
                    f"press {switch}",
                    f"{error * 1e3:.2f} mm",
                    "≤ 10 mm",
                    "±10 mm",
                    error <= PAPER_CALIBRATION_M,
                )
            )
            return "switch touched"
        if step.skill == "move_to":
            return "arrived"
        return ""


def step_count(task: Task) -> int:
    """Steps the task will run, repeats unrolled."""

    def count(group: Group) -> int:
        return group.repeat * sum(count(s) if isinstance(s, Group) else 1 for s in group.steps)

    return count(task.body)


def step_line(row: StepRow) -> str:
    r = row.report
    mark = "[green]✓[/]" if r.outcome.ok else f"[red]✗ {r.outcome.reason}[/]"
    it = "".join(f" #{i}" for i in r.iteration)
    name = f"{r.skill}/{r.record}{it}"
    return (
        f"{mark} {name:<28} [dim]{r.duration_s:5.2f} s sim {row.wall_s:5.2f} s wall[/]  "
        f"{row.detail}"
    )


def run_demo(
    output: Path = DEFAULT_OUTPUT,
    *,
    console: Console | None = None,
    live: bool = True,
    pace_s: float = 0.0,
    hold: Callable[[DemoResult, DemoServer], None] | None = None,
) -> DemoResult:
    """The whole demo (module docstring) into ``output``; never raises for a failed step.

    ``pace_s``: seconds (wall time) to wait after each step, so that a person can follow the
    cell in the web console. ``hold``: called once the task is done, with the server still
    running (``--stay`` waits there for Ctrl-C); the server is stopped when it returns."""
    console = console or Console()
    started = time.perf_counter()
    result = DemoResult()
    shutil.rmtree(output, ignore_errors=True)
    output.mkdir(parents=True)
    config = demo_config(output)
    task, store = load_task(TASK), TeachStore(TAUGHT)
    try:
        with vision_server(config, output / "server.log") as server:
            console.print(f"vision server: 127.0.0.1:{server.port}, configuration {config}")
            scene = with_board(load_scene(CONFIG.parent / "scenes" / "grundfos_cell.yaml"))
            cell = SimCell(scene, state_path=state_file(config))
            docked = cell.dock()  # the mobile robot arrives at the cell, a little off
            console.print(
                f"simulated cell: docked {np.linalg.norm(docked[:2, 3]) * 1e3:.1f} mm and "
                f"{np.degrees(np.arctan2(docked[1, 0], docked[0, 0])):.2f}° off the nominal pose"
            )
            with SyncVisionClient("127.0.0.1", server.port, request_timeout_s=30.0) as client:
                recorder = OverlayRecorder(client, output)
                upstream = UpstreamStation(cell, MAGNET_DELAY_S)
                devices = sim_devices(cell, vision=recorder)
                devices.cameras["tool_camera"] = uncommissioned_camera(cell)
                commissioned = commission_tool_camera(devices, cell, store, output / "taught.yaml")
                report_commissioning(commissioned, result, console)
                store = commissioned.store
                devices.clock = CellClock(devices.clock, upstream)
                ctx = SkillContext.create(devices, store=store)
                observer = DemoObserver(ctx, cell, recorder, result)
                result.task = run_task(
                    task, default_registry(), ctx, observer, upstream, console, live, pace_s
                )
                result.overlays = list(recorder.written)
            if hold is not None:
                held = time.perf_counter()
                hold(result, server)
                started += time.perf_counter() - held  # a person looking is not the demo's time
            result.server_exit = server.stop()
    except Exception as exc:  # the demo reports; it does not crash
        result.error = f"{type(exc).__name__}: {exc}"
    result.wall_s = time.perf_counter() - started
    return result


def report_commissioning(done: Commissioned, result: DemoResult, console: Console) -> None:
    """One line and the checks of the commissioning step (against the simulation's truth)."""
    hand_eye = done.hand_eye
    console.print(
        f"commissioned the tool camera: fx {done.intrinsics.fx:.1f} px "
        f"({done.fx_error * 100:+.3f} %), tool_from_camera {done.mount_error_m * 1e3:.3f} mm / "
        f"{np.degrees(done.mount_error_rad):.3f}° from the truth, verdict {hand_eye.verdict} "
        f"(was told fx 1350 px and a mount 4 mm / 0.6° off)"
    )
    result.errors["commission_fx"] = done.fx_error
    result.errors["commission_mount_m"] = done.mount_error_m
    result.errors["commission_mount_rad"] = done.mount_error_rad
    result.checks.append(
        Check(
            "hand-eye calibration (tool camera)",
            f"{done.mount_error_m * 1e3:.3f} mm, {np.degrees(done.mount_error_rad):.3f}°",
            f"≤ {COMMISSION_M * 1e3:g} mm, ≤ {np.degrees(COMMISSION_RAD):g}°",
            "—",
            done.mount_error_m <= COMMISSION_M and done.mount_error_rad <= COMMISSION_RAD,
        )
    )


def run_task(
    task: Task,
    registry: SkillRegistry,
    ctx: SkillContext,
    observer: DemoObserver,
    upstream: UpstreamStation,
    console: Console,
    live: bool,
    pace_s: float = 0.0,
) -> TaskReport:
    """Run ``task`` on ``ctx``, one line per finished step, with a live progress view (the
    task's steps and what the running skill reports) when ``live``; ``pace_s`` seconds of
    wall time after each step (0: none)."""
    assert ctx.store is not None
    bar = Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f}", style="dim"),
        console=console,
        transient=True,
        disable=not live,
    )
    overall = bar.add_task(f"task {task.name}", total=step_count(task))
    current = bar.add_task("", total=1.0)
    last, vision_before = time.perf_counter(), 0.0

    def on_progress(event: SkillProgress) -> None:
        if event.skill == "quality_control":
            upstream.start()  # quality control looks: the magnet is on its way, late
        text = f"  {event.skill}/{event.record}: {event.message}"
        bar.update(current, description=text, completed=event.fraction or 0.0)

    def on_step(step: StepReport) -> None:
        nonlocal last, vision_before
        now = time.perf_counter()
        vision_s = observer.recorder.request_s - vision_before
        row = StepRow(step, now - last, vision_s, observer.measure(step, vision_s))
        last = time.perf_counter()  # measuring (and the overlays) is not the next step's time
        vision_before = observer.recorder.request_s
        observer.result.steps.append(row)
        bar.console.print(step_line(row))
        bar.advance(overall)
        if pace_s > 0:
            time.sleep(pace_s)  # a person watching the console sees each step's effect
            last = time.perf_counter()  # the pause is not the next step's time

    ctx.progress = on_progress
    with bar:
        return TaskRunner(registry, ctx.store, ctx, on_step=on_step).run(task)


# --- the summary --------------------------------------------------------------------------------


def print_summary(result: DemoResult, console: Console, *, verdict: bool = True) -> None:
    """The steps and checks tables, then (with ``verdict``) :func:`print_verdict`."""
    steps = Table(title="Steps", box=box.SIMPLE_HEAD)
    steps.add_column("step", no_wrap=True)
    steps.add_column("outcome", no_wrap=True)
    for column in ("sim s", "wall s", "vision s"):
        steps.add_column(column, justify="right")
    for row in result.steps:
        r = row.report
        it = "".join(f" #{i}" for i in r.iteration)
        tries = "" if r.attempts == 1 else f" ({r.attempts} tries)"
        steps.add_row(
            f"{r.skill} {r.record}{it}",
            ("[green]ok[/]" if r.outcome.ok else f"[red]{r.outcome.reason}[/]") + tries,
            f"{r.duration_s:.2f}",
            f"{row.wall_s:.2f}",
            f"{row.vision_s:.2f}",
        )
    console.print(steps)
    checks = Table(title="Against the ground truth and the paper", box=box.SIMPLE_HEAD)
    for column in ("check", "measured", "pass if", "paper", "ok"):
        checks.add_column(column)
    for c in result.checks:
        ok = "—" if c.ok is None else "[green]yes[/]" if c.ok else "[red]NO[/]"
        checks.add_row(c.what, c.value, c.bound, c.paper, ok)
    console.print(checks)
    if result.overlays:
        folder = result.overlays[0].parent
        shown = folder.relative_to(REPO) if folder.is_relative_to(REPO) else folder
        names = ", ".join(p.name for p in result.overlays)
        console.print(f"overlay images in {shown}/: {names}")
    if result.task is not None:
        console.print(
            f"task {result.task.task}: {result.task.duration_s:.1f} s simulated, "
            f"{result.wall_s:.1f} s wall in all (server start and stop included)"
        )
    if verdict:
        print_verdict(result, console)


def print_verdict(result: DemoResult, console: Console) -> None:
    """The demo's last lines: an error, an unclean server stop, success or failure."""
    if result.error:
        console.print(f"[red]error:[/] {result.error}")
    if result.server_exit not in (0, None):
        console.print(f"[red]the vision server exited with {result.server_exit}[/]")
    console.print("[green]demo succeeded[/]" if result.ok else "[red]demo failed[/]")


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not 0.0 <= value <= 3600.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 3600 seconds, got {text}")
    return value


def stay_until_interrupted(console: Console) -> Callable[[DemoResult, DemoServer], None]:
    """``--stay``: once the task is done, show the summary and where to look, then wait for
    Ctrl-C (SIGINT; SIGTERM too) with the server and its console still up."""

    def hold(result: DemoResult, server: DemoServer) -> None:
        print_summary(result, console, verdict=False)
        if server.console_url is not None:
            console.print(
                f"The task is done; the vision server and its web console stay up: "
                f"{server.console_url} (results: {server.console_url}#/results)",
                soft_wrap=True,
            )
        else:
            console.print(
                f"The task is done; the vision server stays up on 127.0.0.1:{server.port} "
                "(the configuration does not enable the web console)",
                soft_wrap=True,
            )
        console.print("Ctrl-C to stop", soft_wrap=True)
        wait_for_interrupt()

    return hold


def wait_for_interrupt() -> None:
    """Block until SIGINT or SIGTERM arrives (either ends the wait, not the program)."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        while True:
            signal.pause()
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m robot_client.demo", description=__doc__)
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT, help="output directory")
    parser.add_argument("--no-live", action="store_true", help="plain output, no progress view")
    parser.add_argument(
        "--stay",
        action="store_true",
        help="after the task, keep the vision server and its web console running until Ctrl-C",
    )
    parser.add_argument(
        "--pace",
        type=_seconds,
        default=0.0,
        metavar="S",
        help="wait S seconds after each step, to follow the cell in the web console",
    )
    parser.add_argument(
        "--via",
        choices=("skills", "line"),
        default="skills",
        help="line: a robot controller with no PC picks the caps through the line protocol "
        "alone (URScript's rules), receiving base-frame poses (robot_client/demo/line.py)",
    )
    args = parser.parse_args(argv)
    console = Console()
    if args.via == "line":
        from .line import run_line_demo

        console.print("[bold]cellvision demo[/]: the pick through the line protocol alone")
        return 0 if run_line_demo(args.output, console=console).ok else 1
    console.print("[bold]cellvision demo[/]: the paper's cell, simulated")
    live = console.is_terminal and not args.no_live
    hold = stay_until_interrupted(console) if args.stay else None
    result = run_demo(args.output, console=console, live=live, pace_s=args.pace, hold=hold)
    if args.stay:
        print_verdict(result, console)  # the tables were shown before the wait
    else:
        print_summary(result, console)
    return 0 if result.ok else 1


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
