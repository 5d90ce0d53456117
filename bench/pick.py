"""5. Vision pick (the paper's Table 1): grasp error and search time against where the part
lies along the taught search line, through the robot client's ``vision_pick`` skill, the
server's ``cap_locate`` and the simulated cell.

The example cell's taught record ``caps_l1`` (examples/robot/taught.yaml: the tool camera
searches the conveyor from x = 0.05 to 0.55 m in steps of 0.05 m) with ``refine: 0`` (Table 1
exactly) and with ``refine: 1`` (one look again from straight above the chosen cap). One
rotor cap lies at a distance ("offset") along the line from the first view's centre, within
±2 cm across it; the other caps are out of sight. Grasp error: the distance of the cap's true
grasp point from the TCP when the gripper closes.

Search time, as a real cell would spend it: the robot's motion until the capture that found
the cap (simulated at the taught speed), the camera's frames at 30 fps, the INSPECT round
trips (measured) and the client's own work (measured; rendering is the simulation's cost and
is left out).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from .cell import require
from .common import ROOT, SCENE, Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .env import Env
from .plots import pyplot, save
from .servers import HOST
from .skills import FPS, TimedCamera, TimedVision

NAME = "pick"
TITLE = "5. Vision pick: grasp error and search time"
TAUGHT = ROOT / "examples" / "robot" / "taught.yaml"
RECORD = ("vision_pick", "caps_l1")
PAPER_MM = 5.0
GOAL_MM = 0.5
CAMERA_X_ON_TOOL = 0.07  # tool_from_camera x of the example's tool camera


def _place(cell: Any, part: str, x: float, y: float) -> None:
    pose = cell.world.parts[part].world_from_part.copy()
    pose[:2, 3] = (x, y)
    cell.world.parts[part].world_from_part = pose
    cell.publish()


def _grasp_error_mm(cell: Any) -> float:
    from geometry import invert_transform, transform_points

    held = cell.gripper.held
    tool_from_world = invert_transform(cell.world.world_from_tool())
    p = transform_points(tool_from_world, cell.gripper.grasp_point(held))
    return float(np.linalg.norm(p)) * 1000.0


def _trial(client: Any, record: Any, offset: float, seed: int) -> dict[str, float]:
    from robot_client.devices.sim import sim_devices
    from robot_client.skills import SkillContext, default_registry, execute
    from simulation import SimCell

    rng = np.random.default_rng([seed, 5])
    cell = SimCell.from_yaml(SCENE, seed=seed)
    vision = TimedVision(client)
    devices = sim_devices(cell, vision=vision)
    camera = TimedCamera(cell, "tool_camera")
    devices.cameras["tool_camera"] = camera
    ctx = SkillContext.create(devices)
    start = record.params["p_cam_start"]["xyz"]
    world_from_base = cell.robot.world_from_base
    x0 = start[0] + CAMERA_X_ON_TOOL + world_from_base[0, 3]
    y0 = start[1] + world_from_base[1, 3]
    for k, part in enumerate(("cap_2", "cap_3")):
        _place(cell, part, 2.0 + 0.1 * k, 2.0)  # on the floor, out of sight
    _place(cell, "cap_1", x0 + offset, y0 + rng.uniform(-0.02, 0.02))
    skill = default_registry().get(RECORD[0])
    args = skill.spec.decode(record)
    ctx.robot.move_linear(args["p_cam_start"])
    t_sim0 = cell.clock.now()
    t0 = time.perf_counter()
    outcome = execute(skill, record, ctx)
    wall = (time.perf_counter() - t0) * 1000.0
    ok = outcome.ok and cell.gripper.held == "cap_1"
    vision_ms = sum(c.wall_ms for c in vision.calls)
    client_ms = wall - camera.render_ms - vision_ms
    found_at = camera.sim_times[-1] if camera.sim_times else t_sim0
    motion_ms = (found_at - t_sim0) * 1000.0
    camera_ms = camera.frames / FPS * 1000.0
    return {
        "ok": float(ok),
        "error_mm": _grasp_error_mm(cell) if ok else float("nan"),
        "captures": float(len(camera.sim_times)),
        "motion_ms": motion_ms,
        "camera_ms": camera_ms,
        "vision_ms": vision_ms,
        "client_ms": client_ms,
        "search_ms": motion_ms + camera_ms + vision_ms + client_ms,
    }


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client import SyncVisionClient
    from robot_client.teach_store import TeachStore

    section = Section(NAME, TITLE)
    server = env.server("cellvision")
    if "cap_locate" not in server.info["inspections"]:
        require(env.catalog, "cap_locate")
    if server.info.get("problem"):
        section.notes.append(f"Catalog: {server.info['problem']}.")
    taught = TeachStore(TAUGHT).get(*RECORD)
    modes = {
        "Table 1 (refine 0)": dataclasses.replace(taught, params={**taught.params, "refine": 0}),
        "second look (refine 1)": dataclasses.replace(
            taught, params={**taught.params, "refine": 1}
        ),
    }
    # from 2 cm: at 0 the cap would lie exactly on the start of the acceptance segment
    offsets = [round(0.02 + 0.05 * k, 2) for k in range(10)] if not cfg.quick else [0.02]
    trials = cfg.n(3, 1)
    results: dict[str, dict[float, list[dict[str, float]]]] = {m: {} for m in modes}
    client = SyncVisionClient(HOST, server.port)
    try:
        for mode, record in modes.items():
            for offset in offsets:
                results[mode][offset] = [
                    _trial(client, record, offset, seed=1000 + 37 * i + int(offset * 100))
                    for i in range(trials)
                ]
    finally:
        client.close()

    summary = Table(
        [
            "record",
            "picks",
            "failed",
            "grasp error p50 / p95 / max mm",
            "p95 ÷ paper ±5 mm",
            "search p50 ms",
        ]
    )
    by_offset = Table(
        [
            "record",
            "offset m",
            "captures",
            "motion ms",
            "camera ms",
            "vision ms",
            "client ms",
            "search ms",
            "÷ first offset",
            "error p50 mm",
        ],
        caption="By offset (medians over the trials):",
    )
    for mode, rows in results.items():
        everything = [t for ts in rows.values() for t in ts]
        errors = [t["error_mm"] for t in everything if t["ok"]]
        failed = sum(1 for t in everything if not t["ok"])
        e = Stats.of(errors)
        search = Stats.of(t["search_ms"] for t in everything)
        summary.add(
            mode,
            len(everything),
            failed,
            f"{fmt(e.p50)} / {fmt(e.p95)} / {fmt(e.max)}",
            ratio(e.p95, PAPER_MM),
            fmt(search.p50, 0),
        )
        key = "refine0" if "refine 0" in mode else "refine1"
        section.value(f"{key}_error_p95_mm", e.p95)
        section.value(f"{key}_failed", failed)
        section.value(f"{key}_search_p50_ms", search.p50)
        reference = float(np.median([t["search_ms"] for t in rows[offsets[0]]]))
        for offset, ts in rows.items():
            med = {k: float(np.median([t[k] for t in ts])) for k in ts[0]}
            by_offset.add(
                mode,
                f"{offset:.2f}",
                f"{med['captures']:.0f}",
                fmt(med["motion_ms"], 0),
                fmt(med["camera_ms"], 0),
                fmt(med["vision_ms"], 0),
                fmt(med["client_ms"], 0),
                fmt(med["search_ms"], 0),
                ratio(med["search_ms"], reference),
                fmt(
                    float(np.nanmedian([t["error_mm"] for t in ts]))
                    if any(t["ok"] for t in ts)
                    else float("nan")
                ),
            )
        section.goals.append(
            Goal(
                f"grasp error within the paper's ±{PAPER_MM:g} mm and <= {GOAL_MM} mm (DESIGN), "
                f"p95, no failed pick ({mode})",
                f"p95 {fmt(e.p95)} mm over {e.n} picks, {failed} failed",
                e.n > 0 and e.p95 <= GOAL_MM and failed == 0,
            )
        )
    if not any(t["ok"] for rows in results.values() for ts in rows.values() for t in ts):
        raise Skip("no pick succeeded; nothing to report")
    section.intro = (
        f"{trials} trial(s) per offset and record, {len(offsets)} offsets from "
        f"{offsets[0]} to {offsets[-1]} m; the robot's taught speed in simulated time; frames at "
        f"{FPS:g} fps; search time ratios are to the first offset."
    )
    section.tables += [summary, by_offset]

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for mode, rows in results.items():
            xs, errs, xs_t, times = [], [], [], []
            for offset, ts in rows.items():
                for t in ts:
                    xs_t.append(offset)
                    times.append(t["search_ms"])
                    if t["ok"]:
                        xs.append(offset)
                        errs.append(t["error_mm"])
            axes[0].plot(xs, errs, "o", ms=4, label=mode)
            axes[1].plot(xs_t, times, "o", ms=4, label=mode)
        axes[0].set_ylabel("grasp error [mm]")
        axes[1].set_ylabel("search time [ms]")
        for ax in axes:
            ax.set_xlabel("offset along the search line [m]")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
        return [save(fig, directory / "pick.png")]

    section.plot = plot
    return section
