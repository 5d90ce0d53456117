"""Positions in the robot's base frame on the line protocol (LINE.md §5.7): the controller
conventions both ways, the configuration's checks, and a fixed camera of the simulated cell
measured against the scene's ground truth through real sockets."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from controllers import read_line, socket_read_ascii_float
from loopback import run
from plc import Plc

from geometry import invert_transform, rotation_from_rpy, transform_points, xyz_rpy_from_transform
from simulation import SimCell
from vision_server.app import App
from vision_server.commands import main as cli_main
from vision_server.config import ConfigError, ServerSettings, load_config
from vision_server.frontends.line_poses import CONVENTIONS, parse_pose, pose_values
from vision_server.service import CellRuntime

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"


def test_every_convention_reads_back_what_it_writes() -> None:
    """Seeded random poses, including half turns (the tool pointing down), survive writing and
    parsing in every format."""
    rng = np.random.default_rng(20)
    for i in range(300):
        rpy = rng.uniform(-math.pi, math.pi, 3) if i % 3 else (math.pi, 0.0, rng.uniform(-3, 3))
        pose = np.eye(4)
        pose[:3, :3] = rotation_from_rpy(*rpy)
        pose[:3, 3] = rng.uniform(-1.0, 1.0, 3)
        for fmt in CONVENTIONS:
            written = [f"{v:.9f}" for v, _ in pose_values(fmt, pose)]
            assert np.allclose(parse_pose(fmt, written), pose, atol=1e-7), (fmt, rpy)


def test_each_controller_gets_its_own_units_and_angles() -> None:
    """The tool pointing down, turned 90 degrees about the base z, at (0.3, -0.5, 0.1) m."""
    pose = np.eye(4)
    pose[:3, :3] = rotation_from_rpy(math.pi, 0.0, math.pi / 2)
    pose[:3, 3] = [0.3, -0.5, 0.1]

    def values(fmt: str) -> list[float]:
        return [round(v, 4) for v, _ in pose_values(fmt, pose)]

    half = round(math.sqrt(0.5), 4)
    assert values("kuka") == [300.0, -500.0, 100.0, 90.0, 0.0, 180.0]  # A B C
    assert values("fanuc") == [300.0, -500.0, 100.0, 180.0, 0.0, 90.0]  # W P R
    assert values("abb") == [300.0, -500.0, 100.0, 0.0, half, half, 0.0]  # q1 (scalar) first
    ur = values("ur")
    assert ur[:3] == [0.3, -0.5, 0.1]  # metres
    assert np.allclose(np.abs(ur[3:]), [math.pi * half, math.pi * half, 0.0], atol=1e-4)
    # URScript's to_str(p[...]) is accepted as a trigger's TCP pose.
    assert np.allclose(
        parse_pose("ur", ["p[0.3,", "-0.5,", "0.1,", "0,", "0,", "0]"])[:3, 3], [0.3, -0.5, 0.1]
    )


def cell_config(mount: str, output: str) -> str:
    return f"""\
server: {{port: 0}}
results: {{enabled: false}}
cameras:
  qc:
    source: sim
    scene: {SCENE}
    camera: qc_camera
    seed: 3
{mount}
inspections:
  - name: core
    type: locate
    camera: qc
    method: circle
    circle: {{min_radius_px: 70, max_radius_px: 110, polarity: dark}}
    output: {output}
line: {{enabled: true, port: 0}}
"""


def test_a_base_frame_output_on_a_camera_without_a_mount_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(cell_config("", "{frame: base, plane_z_m: 0.06}"), encoding="utf-8")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert "-> frame:" in text
    assert "set cameras.qc.mount" in text
    assert "cell.yaml" in text


def test_a_base_frame_output_of_a_type_without_pixels_is_refused(tmp_path: Path) -> None:
    config = cell_config(
        "    mount: {base_from_camera: {xyz: [0, 0, 1], rpy: [3.14159265, 0, 0]}}",
        "{frame: base, plane_z_m: 0.06}",
    ).replace("type: locate", "type: presence\n    measure: mean_intensity\n    min: 1\n#")
    path = tmp_path / "cell.yaml"
    path.write_text(config, encoding="utf-8")
    with pytest.raises(ConfigError, match=r"frame: base needs a result with a pixel position"):
        load_config(path)


def test_a_fixed_camera_answers_the_part_in_the_base_frame(tmp_path: Path) -> None:
    """The QC camera's mount is the scene's (its truth); the rotor core's top centre, found by
    the circle locator, comes back in the base frame within 0.5 mm of the scene's truth, in
    text (mm, W P R) and in URScript's format (metres, rotation vector)."""
    cell = SimCell.from_yaml(SCENE, seed=3)
    frame = cell.render("qc_camera")
    xyz, rpy = xyz_rpy_from_transform(frame.truth.base_from_camera)
    truth = frame.truth.features["rotor_core.top_centre"]
    p_base = transform_points(invert_transform(frame.truth.world_from_base), truth.p_world)
    mount = f"    mount: {{base_from_camera: {{xyz: {list(map(float, xyz))}, rpy: {list(rpy)}}}}}"
    plane_z = float(p_base[2])
    path = tmp_path / "cell.yaml"
    path.write_text(
        cell_config(mount, f"{{frame: base, fields: [count, pose], plane_z_m: {plane_z}}}"),
        encoding="utf-8",
    )
    runtime = CellRuntime(path)
    app = App(runtime.catalog, ServerSettings(port=0), line=runtime.config.line)

    async def scenario() -> tuple[str, list[float]]:
        async with app:
            assert app.line is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
            writer.write(b"T core\n")
            text = await read_line(reader)
            writer.write(b"F ur\nT 1\n")
            assert await read_line(reader) == "OK UR"
            ur = await socket_read_ascii_float(reader, 8, timeout_s=20.0)
            writer.close()
            return text, ur

    try:
        text, ur = run(scenario())
    finally:
        runtime.close()
    words = text.split()
    assert words[:2] == ["OK", "1"], text
    assert float(words[2]) == 1.0, text
    x, y, z, w, p, r = (float(v) for v in words[3:])
    assert np.allclose([x, y, z], p_base * 1000.0, atol=0.5), (text, p_base)
    assert np.allclose([w, p, r], [180.0, 0.0, 0.0], atol=1e-3) or np.allclose(
        [abs(w), p, r], [180.0, 0.0, 0.0], atol=1e-3
    )
    assert ur[:3] == [8.0, 1.0, 1.0], ur
    assert np.allclose(ur[3:6], p_base, atol=0.0005), (ur, p_base)
    assert np.allclose(np.abs(ur[6:9]), [math.pi, 0.0, 0.0], atol=1e-4), ur


def tool_camera_config(tmp_path: Path, state: Path) -> Path:
    """The scene's tool camera as a server ``sim`` camera following ``state``, mounted as in
    the scene; ``cap`` answers base-frame poses of the caps' tops."""
    config = f"""\
server: {{port: 0}}
results: {{enabled: false}}
cameras:
  tool:
    source: sim
    scene: {SCENE}
    camera: tool_camera
    state_file: {state}
    mount: {{tool_from_camera: {{xyz: [0.07, 0.0, -0.1], rpy: [0, 0, 0]}}}}
inspections:
  - name: cap
    type: locate
    camera: tool
    method: circle
    circle: {{min_radius_px: 60, max_radius_px: 100, polarity: bright}}
    output: {{frame: base, fields: [count, pose], plane_z_m: 0.025}}
line: {{enabled: true, port: 0}}
"""
    path = tmp_path / "cell.yaml"
    path.write_text(config, encoding="utf-8")
    return path


def test_a_tool_camera_takes_the_robots_pose_in_each_controllers_convention(
    tmp_path: Path,
) -> None:
    """The robot (a SimCell writing the world file) stands over cap_2; the same trigger with
    its TCP pose in URScript's ``p[...]``, KUKA's X Y Z A B C and ABB's x,y,z,q1..q4 finds the
    cap's top centre in the base frame within 0.5 mm of the truth. Without a pose, with a pose
    of the wrong count, the trigger is refused naming what is expected."""
    from robot_client.controllers.urscript import pose_to_str
    from vision_server.frontends.line_poses import pose_values

    state = tmp_path / "world.json"
    cell = SimCell.from_yaml(SCENE, seed=5, state_path=state)
    cell.restart()
    tcp = np.eye(4)
    tcp[:3, :3] = rotation_from_rpy(math.pi, 0.0, 0.0)
    tcp[:3, 3] = [0.23, -0.55, 0.275]
    cell.robot.move_linear(tcp)
    truth = cell.render("tool_camera").truth.features["cap_2.top_centre"]
    p_base = transform_points(invert_transform(cell.world.world_from_base), truth.p_world)
    runtime = CellRuntime(tool_camera_config(tmp_path, state))
    app = App(runtime.catalog, ServerSettings(port=0), line=runtime.config.line)

    def numbers(fmt: str) -> str:
        return " ".join(f"{v:.6f}" for v, _ in pose_values(fmt, tcp))

    async def scenario() -> dict[str, str]:
        async with app:
            assert app.line is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)

            async def ask(line: str) -> str:
                writer.write(line.encode("ascii") + b"\n")
                return await read_line(reader, timeout_s=30.0)

            out = {
                "none": await ask("T cap"),
                "short": await ask("T cap 1 2 3"),
                "text": await ask(f"T cap {numbers('text')}"),
                "repeat": await ask("R"),
                "F kuka": await ask("F kuka"),
                "kuka": await ask(f"T 1 {numbers('kuka')}"),
                "F abb": await ask("F abb"),
                "abb": await ask("T 1 " + ",".join(numbers("abb").split())),
                "F ur": await ask("F ur"),
            }
            writer.write(f"T 1 {pose_to_str(tcp)}\n".encode("ascii"))
            ur = await socket_read_ascii_float(reader, 8, timeout_s=30.0)
            out["ur"] = " ".join(str(v) for v in ur)
            writer.close()
            return out

    try:
        out = run(scenario())
    finally:
        runtime.close()
    assert out["none"].startswith("ER 16 camera 'tool' of 'cap' is on the tool"), out
    assert "x y z w p r" in out["none"]
    assert out["short"] == "ER 16 a text pose is 6 numbers (x y z w p r), got 3", out
    expected_mm = p_base * 1000.0
    text = [float(v) for v in out["text"].split()[1:]]
    assert text[:2] == [1.0, 1.0], out
    assert np.allclose(text[2:5], expected_mm, atol=0.5), (out, expected_mm)
    assert out["repeat"] == out["text"]
    kuka = [float(v) for v in out["kuka"].split()]
    assert np.allclose(kuka[2:5], expected_mm, atol=0.5), out
    assert np.allclose(np.abs(kuka[5:8]), [0.0, 0.0, 180.0], atol=1e-3), out  # A B C
    abb = [float(v) for v in out["abb"].strip().split(",")]
    assert len(abb) == 9, out
    assert np.allclose(abb[2:5], expected_mm, atol=0.5), out
    assert np.allclose(np.abs(abb[5:9]), [0.0, 1.0, 0.0, 0.0], atol=1e-6), out  # q1..q4
    ur = [float(v) for v in out["ur"].split()]
    assert ur[:3] == [8.0, 1.0, 1.0], out
    assert np.allclose(ur[3:6], p_base, atol=0.0005), out


def test_a_pose_sent_to_an_inspection_that_takes_none_is_refused(tmp_path: Path) -> None:
    mount = "    mount: {base_from_camera: {xyz: [0.15, 0.65, 0.6], rpy: [3.14159265, 0, 0]}}"
    path = tmp_path / "cell.yaml"
    path.write_text(cell_config(mount, "{frame: base, plane_z_m: 0.06}"), encoding="utf-8")
    runtime = CellRuntime(path)
    app = App(runtime.catalog, ServerSettings(port=0), line=runtime.config.line)

    async def scenario() -> str:
        async with app:
            assert app.line is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
            writer.write(b"T core 0 0 0 0 0 0\n")
            answer = await read_line(reader)
            writer.close()
            return answer

    try:
        answer = run(scenario())
    finally:
        runtime.close()
    assert answer.startswith("ER 16 'core' takes no pose"), answer


@pytest.mark.parametrize(
    ("mount", "message"),
    [
        ("{}", "give exactly one of base_from_camera or tool_from_camera (got none)"),
        (
            "{base_from_camera: {xyz: [0, 0, 1], rpy: [0, 0, 0]}, "
            "tool_from_camera: {xyz: [0, 0, 1], rpy: [0, 0, 0]}}",
            "give exactly one of base_from_camera or tool_from_camera (got base_from_camera, "
            "tool_from_camera)",
        ),
        ("{base_from_camera: {xyz: [0, 0], rpy: [0, 0, 0]}}", "xyz must be a list of 3 numbers"),
        ("{tool_from_camera: {xyz: [0, 0, 1], rpy: [0, 0, 0], scale: 2}}", "scale"),
    ],
)
def test_a_bad_mount_is_a_configuration_error_naming_the_key(
    tmp_path: Path, mount: str, message: str
) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(cell_config(f"    mount: {mount}", "{}"), encoding="utf-8")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    assert message in str(caught.value)
    assert "cameras" in str(caught.value)


def test_a_plc_reads_the_same_base_frame_pose_over_modbus(tmp_path: Path) -> None:
    """A PLC gets the pose as six float32 values (mm; W P R in degrees: the text format's
    convention), the ones a controller reads on the line protocol, and the map printed for
    the PLC programmer names them with their units."""
    cell = SimCell.from_yaml(SCENE, seed=3)
    frame = cell.render("qc_camera")
    xyz, rpy = xyz_rpy_from_transform(frame.truth.base_from_camera)
    truth = frame.truth.features["rotor_core.top_centre"]
    p_base = transform_points(invert_transform(frame.truth.world_from_base), truth.p_world)
    mount = f"    mount: {{base_from_camera: {{xyz: {list(map(float, xyz))}, rpy: {list(rpy)}}}}}"
    path = tmp_path / "cell.yaml"
    config = cell_config(
        mount, f"{{frame: base, fields: [count, pose], plane_z_m: {float(p_base[2])}}}"
    )
    path.write_text(config + "modbus: {enabled: true, port: 0}\n", encoding="utf-8")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert cli_main(["modbus-map", str(path), "--json"]) == 0
    (listed,) = json.loads(printed.getvalue())["inspections"]
    assert [(v["field"], v["units"]) for v in listed["values"]] == [
        ("count", "features"),
        ("pose.x", "mm"),
        ("pose.y", "mm"),
        ("pose.z", "mm"),
        ("pose.w", "deg"),
        ("pose.p", "deg"),
        ("pose.r", "deg"),
    ]
    runtime = CellRuntime(path)
    app = App(
        runtime.catalog,
        ServerSettings(port=0),
        line=runtime.config.line,
        modbus=runtime.config.modbus,
    )

    async def scenario() -> tuple[str, list[float]]:
        async with app:
            assert app.line is not None
            assert app.modbus is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
            writer.write(b"T core\n")
            text = await read_line(reader)
            writer.close()
            plc = await Plc(app.modbus.port).connect()
            result = await plc.run(1)
            plc.close()
            return text, result.values

    try:
        text, values = run(scenario())
    finally:
        runtime.close()
    line_values = [float(v) for v in text.split()[3:]]
    assert len(values) == 7, values
    assert values[0] == 1.0
    assert np.allclose(values[1:4], p_base * 1000.0, atol=0.5), (values, p_base)
    assert np.allclose(values[1:], line_values, atol=0.01), (values, text)
