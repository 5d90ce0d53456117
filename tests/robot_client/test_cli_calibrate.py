"""``robot-client calibrate-intrinsics`` end to end: a ``vision-server serve`` process with a
calibration_board inspection and approximate intrinsics for the tool camera; the simulated
robot moves its tool camera over the ChArUco board; the solved intrinsics are written into the
server's file and the server reloaded, so that a new client sees them in WELCOME."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import cv2
import pytest
import yaml
from cli_tools import Server, _serve, tool
from loopback import run

from robot_client import VisionClient

CONFIG = """\
server: {port: 0, allow_reload: true}
results: {enabled: false}
cameras:
  # The tool camera, with intrinsics typed in from the lens's data sheet.
  tool:
    source: request
    intrinsics: {width: 1024, height: 768, fx: 1350.0, fy: 1350.0, cx: 512.0, cy: 384.0,
                 distortion: [0.0, 0.0, 0.0, 0.0, 0.0]}
inspections:
  - name: board_tool
    type: calibration_board
    camera: tool
    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}
"""
TRUTH = {"fx": 1400.0, "fy": 1400.0, "cx": 511.5, "cy": 383.5}  # the scene's dmk31bf03


@pytest.fixture
def server(tmp_path: Path) -> Iterator[Server]:
    config = tmp_path / "cell.yaml"
    config.write_text(CONFIG, encoding="utf-8")
    yield from _serve(config)


TOOL_VIEWS = ("--camera", "tool_camera", "--scene", "examples/scenes/intrinsics_cell.yaml")
"""The robot's tool camera over the board of the intrinsics scene."""


def _intrinsics(
    server: Server, tmp_path: Path, inspection: str, *args: str
) -> subprocess.CompletedProcess[str]:
    """``robot-client calibrate-intrinsics INSPECTION ARGS`` on ``server``, the simulated
    world in ``tmp_path``."""
    return tool(
        "robot-client",
        "calibrate-intrinsics",
        inspection,
        *args,
        "--state-file",
        str(tmp_path / "world.json"),
        "--server",
        server.address,
    )


def _calibrate(server: Server, tmp_path: Path, *extra: str) -> dict[str, object]:
    done = _intrinsics(server, tmp_path, "board_tool", *TOOL_VIEWS, "--fresh", "--json", *extra)
    assert done.returncode == 0, done.stderr + done.stdout
    result: dict[str, object] = json.loads(done.stdout)
    return result


async def _served_intrinsics(address: str, name: str = "tool") -> dict[str, float] | None:
    """The camera's intrinsics a new client sees in WELCOME (None: it has none)."""
    host, port = address.rsplit(":", 1)
    async with VisionClient(host, int(port)) as client:
        assert client.welcome is not None
        camera = next(c for c in client.welcome.cameras if c["name"] == name)
        intrinsics: dict[str, float] | None = camera.get("intrinsics")
        return intrinsics


def test_calibrated_intrinsics_are_written_and_served(server: Server, tmp_path: Path) -> None:
    result = _calibrate(server, tmp_path, "--config", str(server.config), "--yes")
    assert result["config"]["written"] is True  # type: ignore[index]
    assert result["rms_px"] < 0.2  # type: ignore[operator]
    text = server.config.read_text(encoding="utf-8")
    assert "# The tool camera, with intrinsics typed in" in text  # the file's comments stay
    assert "# intrinsics calibrated" in text
    assert "charuco 11x8, 30 mm squares" in text
    written = yaml.safe_load(text)["cameras"]["tool"]["intrinsics"]
    served = run(_served_intrinsics(server.address))
    assert served is not None
    for name in TRUTH:
        assert written[name] == pytest.approx(served[name], abs=1e-3)
    assert abs(written["fx"] / TRUTH["fx"] - 1) < 0.001
    assert abs(written["cy"] - TRUTH["cy"]) < 0.5


def test_without_yes_nothing_is_written(server: Server, tmp_path: Path) -> None:
    before = server.config.read_text(encoding="utf-8")
    result = _calibrate(server, tmp_path, "--config", str(server.config))
    assert result["config"] == {"written": False, "reason": "not confirmed (--yes)"}
    assert server.config.read_text(encoding="utf-8") == before
    served = run(_served_intrinsics(server.address))
    assert served is not None
    assert (served["fx"], served["fy"], served["cx"], served["cy"]) == (1350, 1350, 512, 384)


def _render_views(folder: Path) -> None:
    """The planned views of the tool camera saved as files: to a fixed camera, a board shown
    at these poses looks the same."""
    from geometry import invert_transform
    from robot_client.commissioning.views import plan_tool_views
    from simulation import SimCell, load_scene
    from simulation.calibration_board import spec_from_opencv

    scene = load_scene("examples/scenes/intrinsics_cell.yaml")
    cell = SimCell(scene)
    board = scene.calibration_boards[0]
    base_from_board = (
        invert_transform(scene.robot.world_from_base)
        @ board.world_from_board
        @ spec_from_opencv(board)
    )
    poses = plan_tool_views(
        base_from_board,
        scene.camera("tool_camera").pose,
        board.size_m,
        fx_px=1400.0,
        image_width_px=1024,
    )
    folder.mkdir()
    for i, pose in enumerate(poses):
        cell.robot.move_linear(pose)
        cv2.imwrite(str(folder / f"view{i:02d}.png"), cell.render("tool_camera").color)


def test_a_fixed_camera_is_calibrated_from_the_views_the_operator_shows(tmp_path: Path) -> None:
    _render_views(tmp_path / "views")
    config = tmp_path / "cell.yaml"
    config.write_text(
        "server: {port: 0, allow_reload: true}\nresults: {enabled: false}\n"
        "cameras:\n  overhead: {source: folder, path: views, mode: once}\n"
        "inspections:\n  - name: board_overhead\n    type: calibration_board\n"
        "    camera: overhead\n"
        "    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}\n",
        encoding="utf-8",
    )
    for server in _serve(config):
        done = _intrinsics(
            server,
            tmp_path,
            "board_overhead",
            "--fixed",
            "--views",
            "15",
            "--scene",
            "examples/scenes/intrinsics_cell.yaml",
            "--config",
            str(config),
            "--yes",
        )
        assert done.returncode == 0, done.stderr + done.stdout
        # The operator is told what is still missing after each view, until nothing is.
        assert "missing: top left" in done.stdout
        assert "coverage complete" in done.stdout
        assert "RMS reprojection error: 0.0" in done.stdout
        assert "server reloaded" in done.stdout
        written = yaml.safe_load(config.read_text(encoding="utf-8"))
        intrinsics = written["cameras"]["overhead"]["intrinsics"]
        assert abs(intrinsics["fx"] / TRUTH["fx"] - 1) < 0.001
        served = run(_served_intrinsics(server.address, "overhead"))
        assert served is not None
        assert served["fx"] == pytest.approx(intrinsics["fx"], abs=1e-3)


def test_a_file_the_server_refuses_is_put_back(tmp_path: Path) -> None:
    # The camera declares no size, so an ROI of 1100x800 loads; calibrated intrinsics of a
    # 1024x768 camera make it reach past the image, which the server refuses on reload.
    config = tmp_path / "cell.yaml"
    text = (
        "server: {port: 0, allow_reload: true}\nresults: {enabled: false}\n"
        "cameras:\n  tool:\n    source: request\n"
        "inspections:\n"
        "  - name: board_tool\n    type: calibration_board\n    camera: tool\n"
        "    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}\n"
        "  - {name: wide, type: presence, camera: tool, roi: [0, 0, 1100, 800], "
        "measure: mean_intensity, min: 1}\n"
    )
    config.write_text(text, encoding="utf-8")
    for server in _serve(config):
        done = _intrinsics(
            server,
            tmp_path,
            "board_tool",
            *TOOL_VIEWS,
            "--fresh",
            "--config",
            str(config),
            "--yes",
        )
        assert done.returncode == 4, done.stderr + done.stdout
        assert "reaches past the 1024x768 image" in done.stderr
        assert "put back as it was" in done.stderr
        assert config.read_text(encoding="utf-8") == text
        assert run(_served_intrinsics(server.address)) is None


def test_a_camera_is_given_intrinsics_in_any_layout() -> None:
    from geometry import CameraIntrinsics
    from robot_client.commissioning.config_file import replace_intrinsics

    k = CameraIntrinsics(1024, 768, 1401.25, 1400.5, 511.0, 383.75, (-0.08, 0.05, 0, 0, 0))
    for text in (
        "cameras:\n  cam: {source: request}\n",  # one line, added inside
        "cameras:\n  cam: {source: request, intrinsics: {width: 1, height: 1, fx: 1, fy: 1, "
        "cx: 0, cy: 0}}\n",  # one line, replaced inside
        "cameras:\n  cam:\n    source: request\n  # next\n  other: {source: request}\n",
        "cameras:\n  cam:\n    source: request\n    intrinsics:\n      width: 1\n      height: 1"
        "\n      fx: 1\n      fy: 1\n      cx: 0\n      cy: 0\n\n  other: {source: request}\n",
    ):
        once = replace_intrinsics(text, "cam", k, "first")
        twice = replace_intrinsics(once, "cam", k, "second")
        data = yaml.safe_load(twice)
        assert data["cameras"]["cam"]["intrinsics"]["fx"] == 1401.25, twice
        assert data["cameras"]["cam"]["source"] == "request"
        assert twice.count("# intrinsics calibrated") == 1, twice
        assert "# intrinsics calibrated second" in twice
        if "other" in text:
            assert data["cameras"]["other"] == {"source": "request"}
    with pytest.raises(ValueError, match="no camera 'nope'"):
        replace_intrinsics("cameras:\n  cam: {source: request}\n", "nope", k, "x")


def test_views_that_miss_regions_and_tilts_are_not_written(tmp_path: Path) -> None:
    # A fixed camera and a board nobody moves: every view is the same frontal one.
    scene = Path("examples/scenes/intrinsics_cell.yaml").resolve()
    config = tmp_path / "cell.yaml"
    text = (
        "server: {port: 0, allow_reload: true}\nresults: {enabled: false}\n"
        f"cameras:\n  overhead: {{source: sim, scene: '{scene}', camera: fixed_camera}}\n"
        "inspections:\n  - name: board_overhead\n    type: calibration_board\n"
        "    camera: overhead\n"
        "    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}\n"
    )
    config.write_text(text, encoding="utf-8")
    for server in _serve(config):
        done = _intrinsics(
            server,
            tmp_path,
            "board_overhead",
            "--fixed",
            "--views",
            "4",
            "--scene",
            str(scene),
            "--config",
            str(config),
            "--yes",
        )
        assert done.returncode == 1, done.stderr + done.stdout
        assert "coverage incomplete (missing: top left" in done.stdout
        assert "tilted left" in done.stdout
        assert "not written" in done.stdout
        assert config.read_text(encoding="utf-8") == text


def test_a_reload_that_does_not_serve_the_written_file_fails(
    server: Server, tmp_path: Path
) -> None:
    """Integrator finding 2: --config names a copy, the server runs its own file. The copy is
    written, the server reloads its unchanged file: that is an error naming both files'
    hashes and what to do, not "server reloaded"."""
    copy = tmp_path / "copy.yaml"
    copy.write_text(CONFIG, encoding="utf-8")
    done = _intrinsics(
        server,
        tmp_path,
        "board_tool",
        *TOOL_VIEWS,
        "--fresh",
        "--config",
        str(copy),
        "--yes",
    )
    assert done.returncode == 2, done.stderr + done.stdout
    err = " ".join(done.stderr.split())
    assert "but the server reloaded another configuration" in err, err
    assert str(copy) in err
    assert "the server's camera 'tool' has fx 1350" in err
    assert "give that file to --config" in err
    assert "server reloaded, config hash" not in done.stdout
    assert "# intrinsics calibrated" in copy.read_text(encoding="utf-8")
    assert server.config.read_text(encoding="utf-8") == CONFIG
    served = run(_served_intrinsics(server.address))
    assert served is not None
    assert served["fx"] == 1350


def test_images_of_one_camera_are_not_written_under_another(tmp_path: Path) -> None:
    """Integrator finding 3: the tool camera's views through the overhead camera's inspection
    would be written as the overhead camera's intrinsics. Refused (exit 2, both cameras
    named) before the robot moves; nothing written."""
    scene = Path("examples/scenes/intrinsics_cell.yaml").resolve()
    config = tmp_path / "cell.yaml"
    text = CONFIG + (
        "  - name: board_overhead\n    type: calibration_board\n    camera: overhead\n"
        "    board: {kind: charuco, columns: 11, rows: 8, square_m: 0.03, marker_m: 0.0225}\n"
    )
    text = text.replace(
        "inspections:\n",
        f"  overhead: {{source: sim, scene: '{scene}', camera: fixed_camera}}\ninspections:\n",
    )
    config.write_text(text, encoding="utf-8")
    for server in _serve(config):
        done = _intrinsics(
            server,
            tmp_path,
            "board_overhead",
            "--camera",
            "tool_camera",
            "--scene",
            str(scene),
            "--fresh",
            "--config",
            str(config),
            "--yes",
        )
        assert done.returncode == 2, done.stderr + done.stdout
        err = " ".join(done.stderr.split())
        assert "the images come from the robot's camera 'tool_camera'" in err, err
        assert "runs on the server camera 'overhead', which takes its own images" in err
        assert "--server-camera overhead" in err
        assert "view 1" not in done.stdout  # refused before the robot moved
        assert config.read_text(encoding="utf-8") == text


class _Vision:
    def list_inspections(self) -> tuple[dict[str, object], ...]:
        return (
            {"name": "board_tool", "type": "calibration_board", "camera": "tool"},
            {"name": "board_wrist", "type": "calibration_board", "camera": "wrist"},
        )


def test_the_server_camera_rule() -> None:
    """One rule for calibrate-intrinsics and calibrate-hand-eye: --server-camera is explicit;
    --fixed is the inspection's camera; --camera ROBOT is ROBOT or ROBOT without _camera."""
    import argparse

    from robot_client.commands.commission import server_camera

    class _Devices:
        vision = _Vision()

    def args(inspection: str, **kw: object) -> argparse.Namespace:
        base = {"server_camera": None, "fixed": False, "camera": None}
        return argparse.Namespace(inspection=inspection, **{**base, **kw})

    devices: object = _Devices()
    assert server_camera(devices, args("board_tool", camera="tool_camera")) == "tool"  # type: ignore[arg-type]
    assert server_camera(devices, args("board_wrist", camera="wrist")) == "wrist"  # type: ignore[arg-type]
    assert server_camera(devices, args("board_wrist", fixed=True)) == "wrist"  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="'tool_camera'.*'wrist'"):
        server_camera(devices, args("board_wrist", camera="tool_camera"))  # type: ignore[arg-type]
    explicit = args("board_wrist", camera="tool_camera", server_camera="wrist")
    assert server_camera(devices, explicit) == "wrist"  # type: ignore[arg-type]
