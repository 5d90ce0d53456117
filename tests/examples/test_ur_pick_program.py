"""examples/robots/ur/vision_pick.script against a real server and the simulated cell: a test
client performs the script's calls in its order (move to the search pose, ``F ur``, ``T 1`` with
``to_str(get_actual_tcp_pose())``, ``socket_read_ascii_float(8)``, ``movel`` to the pose read)
with URScript's rules (robot_client.controllers.urscript), and the simulated gripper must close
on a cap within 0.5 mm of its true grasp point."""

from __future__ import annotations

import asyncio
import re
from dataclasses import replace
from pathlib import Path

from loopback import run

from robot_client.controllers.urscript import (
    pose_to_str,
    read_line,
    socket_read_ascii_float,
    ur_pose,
)
from robot_client.demo.cell import grasp_error_m
from robot_client.demo.line import SCENE, line_config
from simulation import SimCell
from vision_server.app import App
from vision_server.config import ServerSettings
from vision_server.service import CellRuntime

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "robots" / "ur" / "vision_pick.script"
NUMBER = r"-?\d+(?:\.\d*)?"


def code() -> str:
    text = SCRIPT.read_text(encoding="utf-8")
    return "\n".join(line.split("#", 1)[0] for line in text.splitlines())


def test_the_script_reads_what_it_declares_and_moves_to_it_as_it_is() -> None:
    text = SCRIPT.read_text(encoding="utf-8")
    script = code()
    assert "cellvision: format ur, numbers 8" in text
    assert 'socket_send_line("F ur", "vision")' in script
    assert 'socket_send_line(str_cat("T 1 ", to_str(get_actual_tcp_pose())), "vision")' in script
    assert 'socket_read_ascii_float(8, "vision", 12.0)' in script
    # The pose read goes to movel unchanged: numbers 3..8 of the answer, in order.
    assert "grasp = p[r[3], r[4], r[5], r[6], r[7], r[8]]" in script
    assert "movel(grasp)" in script


def test_the_script_picks_a_cap_of_the_simulated_cell(tmp_path: Path) -> None:
    script = code()
    found = re.search(rf"search = p\[((?:\s*{NUMBER},?)+)\]", script)
    assert found, "no search pose in the script"
    search = ur_pose([float(v) for v in found.group(1).split(",")])
    state = tmp_path / "world-state.json"
    cell = SimCell.from_yaml(SCENE, seed=11, state_path=state)
    cell.restart()
    runtime = CellRuntime(line_config(tmp_path, cell, 0))
    line = replace(runtime.config.line, port=0)
    app = App(runtime.catalog, ServerSettings(port=0), line=line)

    async def program() -> tuple[str, list[float]]:
        async with app:
            assert app.line is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
            writer.write(b"F ur\n")
            ack = await read_line(reader, 2.0)
            cell.robot.move_linear(search)  # movel(search)
            writer.write(f"T 1 {pose_to_str(cell.world.base_from_tool)}\n".encode("ascii"))
            answer = await socket_read_ascii_float(reader, 8, 12.0)
            writer.close()
            return ack, answer

    try:
        ack, r = run(program())
    finally:
        runtime.close()
    assert ack == "OK UR"
    assert r[:3] == [8.0, 1.0, 1.0], r
    grasp = ur_pose(r[3:9])  # grasp = p[r[3], ..., r[8]]
    above = grasp.copy()
    above[2, 3] += 0.05  # pose_add(grasp, above)
    cell.robot.move_linear(above)
    cell.robot.move_linear(grasp)
    assert cell.gripper.grasp() == "cap_2"
    assert grasp_error_m(cell) <= 0.5e-3
