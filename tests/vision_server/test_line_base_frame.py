"""Positions in the robot's base frame on the line protocol (LINE.md §5.7): the controller
conventions both ways, the configuration's checks, and a fixed camera of the simulated cell
measured against the scene's ground truth through real sockets."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import numpy as np
import pytest
from controllers import read_line, socket_read_ascii_float
from loopback import run

from geometry import invert_transform, rotation_from_rpy, transform_points, xyz_rpy_from_transform
from simulation import SimCell
from vision_server.app import App
from vision_server.config import ConfigError, load_config
from vision_server.frontends.line_poses import CONVENTIONS, parse_pose, pose_values
from vision_server.runtime import CellRuntime
from vision_server.settings import ServerSettings

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
