"""The demo through the line protocol alone (``make demo LINE=1``, ``python -m
robot_client.demo --via line``): a robot controller with no PC picks the conveyor's rotor caps.

The "controller" follows a URScript program's rules (:mod:`robot_client.controllers.urscript`):
it moves the simulated robot to a taught search pose, sends ``T cap_pick`` followed by
``to_str(get_actual_tcp_pose())``, reads the answer with ``socket_read_ascii_float(8)`` and
moves its TCP to the pose it received, as it is (``movel(p[v[3], ..., v[8]])``): the server
turns the found cap into a base-frame grasp pose (its ``tool_sim`` camera is mounted on the
tool, ``output: {frame: base}``; protocol/LINE.md §5.7). No maths on the controller's side.
Each pick's error is measured against the simulated cell's ground truth: the distance of the
held cap's true grasp point from the TCP.
"""

from __future__ import annotations

import asyncio
import math
import socket
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray
from rich.console import Console

from geometry import (
    invert_transform,
    make_transform,
    rotation_from_rpy,
    rpy_from_rotation,
    transform_points,
)
from simulation import SimCell

from ..controllers.urscript import pose_to_str, read_line, socket_read_ascii_float, ur_pose
from .cell import grasp_error_m, vision_server

REPO = Path(__file__).resolve().parents[2]
SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"
CAMERA = "tool_camera"
CAPS = ("cap_1", "cap_2", "cap_3")
SEARCH_Z_M = 0.275
"""The taught search height of the TCP over the conveyor (base frame): the tool camera is then
0.35 m above the cap tops (examples/scenes/grundfos_cell.yaml)."""
SEARCH_STATIONS = ((0.08, -0.55), (0.23, -0.55), (0.38, -0.55))
"""Taught TCP positions (x, y in metres, base frame) for the three caps' nominal places: the
tool camera sits 0.07 m along the tool's x, so the cap is near the image centre."""
DOWN = rotation_from_rpy(math.pi, 0.0, 0.0)
"""The tool pointing down."""
APPROACH_M = 0.05
ANSWER_NUMBERS = 8
"""verdict, count, then x y z rx ry rz: what a ``ur`` answer to ``T cap_pick`` holds."""
BIN_DROP = (0.68, 0.3, 0.1)
"""Where the controller drops a picked cap: above bin_l2 (base frame, metres)."""


@dataclass(frozen=True)
class LinePick:
    """One pick: the search station, the numbers the controller read, the part it grasped
    (None: nothing) and the pick's true error in metres (NaN when nothing was grasped)."""

    station: int
    answer: list[float]
    part: str | None
    error_m: float


@dataclass
class LineDemoResult:
    picks: list[LinePick] = field(default_factory=list)
    error: str | None = None
    server_exit: int | None = None

    @property
    def max_error_m(self) -> float:
        errors = [p.error_m for p in self.picks if p.part is not None]
        return max(errors) if errors else math.nan

    @property
    def ok(self) -> bool:
        return (
            self.error is None
            and len(self.picks) == len(SEARCH_STATIONS)
            and all(p.part is not None for p in self.picks)
        )


def free_port() -> int:
    """A free loopback port for the line listener (the server prints only its main port)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def line_config(output: Path, cell: SimCell, line_port: int) -> Path:
    """A server configuration whose ``tool_sim`` camera renders the tool camera of the world the
    controller writes, mounted as in the scene, and whose ``cap_pick`` answers base-frame grasp
    poses: the plane is the caps' top, the grasp point ``grasp_depth_m`` below it."""
    spec = cell.scene.camera(CAMERA)
    cap = cell.scene.part(CAPS[0])
    base_from_world = invert_transform(cell.world.world_from_base)
    top = transform_points(base_from_world, cap.world_from_part[:3, 3] + [0, 0, cap.height])
    tool_from_camera = spec.pose
    xyz = [float(v) for v in tool_from_camera[:3, 3]]
    rpy = _rpy(tool_from_camera[:3, :3])
    doc = {
        "server": {"host": "127.0.0.1", "port": 0, "name": "line-demo"},
        "results": {"path": str(output / "results.sqlite3")},
        "cameras": {
            "tool_sim": {
                "source": "sim",
                "scene": str(SCENE),
                "camera": CAMERA,
                "state_file": str(output / "world-state.json"),
                "mount": {"tool_from_camera": {"xyz": xyz, "rpy": rpy}},
            }
        },
        "inspections": [
            {
                "name": "cap_pick",
                "type": "locate",
                "camera": "tool_sim",
                "method": "circle",
                "circle": {"min_radius_px": 60, "max_radius_px": 100, "polarity": "bright"},
                "output": {
                    "frame": "base",
                    "fields": ["count", "pose"],
                    "plane_z_m": float(top[2]),
                    "offset_m": [0.0, 0.0, -float(cap.grasp_depth_m)],
                },
            }
        ],
        "line": {"enabled": True, "host": "127.0.0.1", "port": line_port, "format": "ur"},
    }
    path = output / "line-cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


def _rpy(rotation: NDArray[np.float64]) -> list[float]:
    return [float(a) for a in rpy_from_rotation(rotation)]


async def _connect(
    port: int, timeout_s: float = 30.0
) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """``socket_open`` until the server's line port answers (it starts after the main port)."""
    async with asyncio.timeout(timeout_s):
        while True:
            try:
                return await asyncio.open_connection("127.0.0.1", port)
            except OSError:
                await asyncio.sleep(0.05)


async def run_controller(cell: SimCell, port: int) -> list[LinePick]:
    """The URScript program: per taught station, look, move to the answer, grasp, drop."""
    reader, writer = await _connect(port)
    picks: list[LinePick] = []
    try:
        for index, (x, y) in enumerate(SEARCH_STATIONS):
            cell.robot.move_linear(make_transform(DOWN, [x, y, SEARCH_Z_M]))
            tcp = cell.world.base_from_tool
            writer.write(f"T cap_pick {pose_to_str(tcp)}\n".encode("ascii"))
            answer = await socket_read_ascii_float(reader, ANSWER_NUMBERS, timeout_s=30.0)
            if answer[0] != ANSWER_NUMBERS or answer[1] != 1:
                picks.append(LinePick(index, answer, None, math.nan))
                continue
            target = ur_pose(answer[3:9])
            above = target.copy()
            above[2, 3] += APPROACH_M
            cell.robot.move_linear(above)
            cell.robot.move_linear(target)
            part = cell.gripper.grasp()
            error = grasp_error_m(cell) if part is not None else math.nan
            picks.append(LinePick(index, answer, part, error))
            cell.robot.move_linear(above)
            if part is not None:
                cell.robot.move_linear(make_transform(DOWN, BIN_DROP))
                cell.gripper.release()
        writer.write(b"Q\n")
        await read_line(reader)
    finally:
        writer.close()
    return picks


def run_line_demo(output: Path, *, console: Console) -> LineDemoResult:
    """Start the server (a ``vision-server serve`` subprocess) and run the controller."""
    output.mkdir(parents=True, exist_ok=True)
    cell = SimCell.from_yaml(SCENE, state_path=output / "world-state.json")
    cell.restart()  # the scene's start, written for the server's camera
    port = free_port()
    config = line_config(output, cell, port)
    result = LineDemoResult()
    console.print(f"line protocol demo: server config {config}, line port {port}")
    try:
        with vision_server(config, output / "line-server.log") as server:
            result.picks = asyncio.run(run_controller(cell, port))
            result.server_exit = server.stop()
    except Exception as exc:  # reported, as the main demo does
        result.error = f"{type(exc).__name__}: {exc}"
    print_line_summary(result, console)
    return result


def print_line_summary(result: LineDemoResult, console: Console) -> None:
    for pick in result.picks:
        if pick.part is None:
            console.print(
                f"station {pick.station + 1}: nothing picked; the answer was {pick.answer}"
            )
        else:
            x, y, z = (v * 1000.0 for v in pick.answer[3:6])
            console.print(
                f"station {pick.station + 1}: answer x={x:.2f} y={y:.2f} z={z:.2f} mm -> picked "
                f"{pick.part}, error {pick.error_m * 1000.0:.3f} mm against the ground truth"
            )
    if result.error is not None:
        console.print(f"[red]error[/]: {result.error}")
    verdict = "OK" if result.ok else "FAILED"
    console.print(
        f"line-protocol pick: {verdict}, {sum(p.part is not None for p in result.picks)}/"
        f"{len(SEARCH_STATIONS)} caps, worst error {result.max_error_m * 1000.0:.3f} mm"
    )
