"""``robot-client calibrate-intrinsics`` end to end: a ``vision-server serve`` process with a
calibration_board inspection and approximate intrinsics for the tool camera; the simulated
robot moves its tool camera over the ChArUco board; the solved intrinsics are written into the
server's file and the server reloaded, so that a new client sees them in WELCOME."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

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


def _calibrate(server: Server, tmp_path: Path, *extra: str) -> dict[str, object]:
    done = tool(
        "robot-client",
        "calibrate-intrinsics",
        "board_tool",
        "--camera",
        "tool_camera",
        "--scene",
        "examples/scenes/intrinsics_cell.yaml",
        "--state-file",
        str(tmp_path / "world.json"),
        "--fresh",
        "--server",
        server.address,
        "--json",
        *extra,
    )
    assert done.returncode == 0, done.stderr + done.stdout
    result: dict[str, object] = json.loads(done.stdout)
    return result


async def _served_intrinsics(address: str) -> dict[str, float]:
    host, port = address.rsplit(":", 1)
    async with VisionClient(host, int(port)) as client:
        assert client.welcome is not None
        camera = next(c for c in client.welcome.cameras if c["name"] == "tool")
        intrinsics: dict[str, float] = camera["intrinsics"]
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
    for name in TRUTH:
        assert written[name] == pytest.approx(served[name], abs=1e-3)
    assert abs(written["fx"] / TRUTH["fx"] - 1) < 0.001
    assert abs(written["cy"] - TRUTH["cy"]) < 0.5


def test_without_yes_nothing_is_written(server: Server, tmp_path: Path) -> None:
    before = server.config.read_text(encoding="utf-8")
    result = _calibrate(server, tmp_path, "--config", str(server.config))
    assert result["config"] == {"written": False, "reason": "not confirmed (--yes)"}
    assert server.config.read_text(encoding="utf-8") == before
    assert run(_served_intrinsics(server.address))["fx"] == 1350.0
