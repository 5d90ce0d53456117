"""Scenes for the simulation tests: the example cell and small purpose-built scenes."""

from __future__ import annotations

from pathlib import Path

import pytest

from simulation import Scene, SimCell, scene_from_text

REPO = Path(__file__).resolve().parents[2]
EXAMPLE_SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"

# A cap on a black surface under a camera straight above, lit straight from above with no ambient
# light: the cap's sides render as black as the surface, so the bright blob is exactly its top.
CAP_SCENE = """
name: cap_test
seed: 1
background: 0
light: {{direction: [0, 0, -1], ambient: 0.0, diffuse: 1.0}}
surfaces:
  - {{name: belt, center: [0, 0], height: 0.5, size: [2, 2], color: 0}}
parts:
  - {{name: cap, type: rotor_cap, at: [{x}, {y}], support: belt, radius: 0.02, height: 0.025,
     color: 200}}
robot:
  world_from_base: {{xyz: [0, 0, 0]}}
  home: {{xyz: [0, 0, 0.8], rpy: [3.141592653589793, 0, 0]}}
  workspace: {{min: [-1, -1, 0], max: [1, 1, 1.5]}}
cameras:
  - name: cam
    mount: fixed
    pose: {{xyz: [0, 0, 0.9], rpy: [3.141592653589793, 0, 0]}}
    intrinsics: {{width: 640, height: 480, fx: 900, fy: 900, cx: 319.5, cy: 239.5,
                 dist: [{k1}, 0.0, 0.0, 0.0, 0.0]}}
    channels: 1
    noise_sigma: 0
    vignetting: 0
"""

# An RGB-D camera 1 m in front of a large board (fronto-parallel), plus a QR code.
BOARD_SCENE = """
name: board_test
seed: 5
surfaces:
  - {name: floor, center: [0, 0], height: 0.0, size: [4, 4], color: 90}
boxes:
  - {name: wall, pose: {xyz: [1.0, 0, 0], rpy: [0, 0, 0]}, size: [0.02, 1.0, 2.5], color: 150}
qr_boards:
  - name: qr
    text: "cellvision:test"
    side_m: 0.16
    pose: {xyz: [0.989, 0.0, 1.0], rpy: [1.5707963267948966, 0.0, -1.5707963267948966]}
robot:
  world_from_base: {xyz: [0, 0, 0]}
  home: {xyz: [0, 0, 1.0], rpy: [-1.5707963267948966, 0, -1.5707963267948966]}
  workspace: {min: [-1, -1, 0], max: [1, 1, 2]}
cameras:
  - {name: rgbd, model: xtion, mount: tool, pose: {xyz: [0, 0, 0]}, noise_sigma: 1.0}
"""


def cap_scene(x: float = 0.05, y: float = -0.03, k1: float = 0.0) -> Scene:
    return scene_from_text(CAP_SCENE.format(x=x, y=y, k1=k1), source="cap_test.yaml")


@pytest.fixture
def board_cell() -> SimCell:
    return SimCell(scene_from_text(BOARD_SCENE, source="board_test.yaml"))


@pytest.fixture
def example_cell(tmp_path: Path) -> SimCell:
    return SimCell.from_yaml(EXAMPLE_SCENE, state_path=tmp_path / "world.json")
