"""The sim source: frames rendered by the simulated cell, following a shared world-state file."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from protocol import CameraUnavailable
from simulation import SimCell
from vision_server.cameras import Intrinsics, SimCamera, SimCameraSettings, make_camera

REPO = Path(__file__).resolve().parents[3]
EXAMPLE_SCENE = REPO / "examples" / "scenes" / "grundfos_cell.yaml"
T = 10.0

# A bright cap on a dark belt under a small fixed RGB-D camera.
SCENE = """
name: sim_camera_test
seed: 1
background: 0
light: {direction: [0, 0, -1], ambient: 0.2, diffuse: 0.8}
surfaces:
  - {name: belt, center: [0, 0], height: 0.5, size: [2, 2], color: 20}
parts:
  - {name: cap, type: rotor_cap, at: [0.0, 0.0], support: belt, radius: 0.03, height: 0.025,
     color: 220}
robot:
  world_from_base: {xyz: [0, 0, 0]}
  home: {xyz: [0, 0, 0.8], rpy: [3.141592653589793, 0, 0]}
  workspace: {min: [-1, -1, 0], max: [1, 1, 1.5]}
cameras:
  - name: top
    mount: fixed
    pose: {xyz: [0, 0, 1.3], rpy: [3.141592653589793, 0, 0]}
    intrinsics: {width: 160, height: 120, fx: 150, fy: 150, cx: 79.5, cy: 59.5,
                 dist: [0.0, 0.0, 0.0, 0.0, 0.0]}
    channels: 1
    noise_sigma: 1.0
    vignetting: 0
  - name: rgbd
    mount: fixed
    pose: {xyz: [0, 0, 1.3], rpy: [3.141592653589793, 0, 0]}
    intrinsics: {width: 160, height: 120, fx: 150, fy: 150, cx: 79.5, cy: 59.5,
                 dist: [0.0, 0.0, 0.0, 0.0, 0.0]}
    channels: 3
    noise_sigma: 1.0
    vignetting: 0
    depth: {}
"""


@pytest.fixture
def scene(tmp_path: Path) -> Path:
    path = tmp_path / "scene.yaml"
    path.write_text(SCENE, encoding="utf-8")
    return path


def sim_camera(settings: SimCameraSettings, base_dir: Path) -> SimCamera:
    camera = make_camera("sim", settings, base_dir=base_dir)
    assert isinstance(camera, SimCamera)
    camera.open()
    return camera


def test_renders_gray_frames_with_scene_intrinsics(scene: Path) -> None:
    camera = sim_camera(SimCameraSettings(Path("scene.yaml"), "top"), scene.parent)
    assert camera.source == "sim"
    assert not camera.has_depth
    assert camera.intrinsics is not None
    assert (camera.intrinsics.width, camera.intrinsics.fx) == (160, 150.0)
    first, second = camera.grab_many(2, timeout_s=T)
    assert first.color.shape == (120, 160)
    assert first.color.dtype == np.uint8
    assert first.depth is None
    assert (first.index, second.index) == (0, 1)
    assert not np.array_equal(first.color, second.color)  # new sensor noise per frame
    assert first.color[60, 80] > 150 > first.color[5, 5]  # the cap in the middle of the belt
    camera.close()


def test_rgbd_camera_gives_registered_depth_in_mm(scene: Path) -> None:
    camera = sim_camera(SimCameraSettings(scene, "rgbd"), scene.parent)
    assert camera.has_depth
    frame = camera.grab(timeout_s=T)
    assert frame.color.shape == (120, 160, 3)
    assert frame.depth is not None
    assert frame.depth.dtype == np.uint16
    assert frame.depth.shape == (120, 160)
    # The camera is 0.8 m above the belt and 0.775 m above the cap's top.
    assert abs(int(np.median(frame.depth[5:15, 5:15])) - 800) < 15
    assert abs(int(np.median(frame.depth[57:63, 77:83])) - 775) < 15


def test_example_cell_camera_and_explicit_intrinsics(scene: Path) -> None:
    camera = sim_camera(SimCameraSettings(EXAMPLE_SCENE, "rgbd", seed=3), scene.parent)
    assert camera.has_depth
    assert camera.intrinsics is not None
    assert camera.intrinsics.to_dict()["width"] == 640
    assert camera.descriptor()["depth"] is True


def test_follows_the_world_state_written_by_another_cell(scene: Path, tmp_path: Path) -> None:
    state = tmp_path / "world.json"
    writer = SimCell.from_yaml(scene, seed=5, state_path=state)
    writer.publish()
    following = sim_camera(SimCameraSettings(scene, "top", state_file=state, seed=5), tmp_path)
    reference = sim_camera(SimCameraSettings(scene, "top", seed=5), tmp_path)

    before = following.grab(timeout_s=T)
    assert np.array_equal(before.color, reference.grab(timeout_s=T).color)  # same seed, frame

    moved = writer.world.parts["cap"].world_from_part.copy()
    moved[0, 3] += 0.25  # 0.25 m along x: far outside where the cap was
    writer.world.parts["cap"].world_from_part = moved
    writer.publish()

    after = following.grab(timeout_s=T)
    unchanged = reference.grab(timeout_s=T)
    assert after.index == unchanged.index == 1  # same frame index, hence the same noise
    difference = np.abs(after.color.astype(int) - unchanged.color.astype(int))
    assert difference[60, 80] > 100  # the cap left the centre of the image
    assert unchanged.color[60, 80] > 150


def test_concurrent_grabs_are_serialised(scene: Path) -> None:
    camera = sim_camera(SimCameraSettings(scene, "top"), scene.parent)
    indices: list[int] = []
    lock = threading.Lock()

    def worker() -> None:
        for _ in range(3):
            index = camera.grab(timeout_s=T).index
            with lock:
                indices.append(index)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(indices) == list(range(12))
    assert camera.status()["frames"] == 12


def test_bad_scene_or_camera_is_a_configuration_error(scene: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no camera named 'nope'"):
        make_camera("sim", SimCameraSettings(scene, "nope"), base_dir=tmp_path)
    wrong = Intrinsics(320, 240, 300.0, 300.0, 159.5, 119.5)
    with pytest.raises(ValueError, match="renders 160x120"):
        make_camera("sim", SimCameraSettings(scene, "top", intrinsics=wrong), base_dir=tmp_path)
    with pytest.raises(ValueError, match="cannot load scene") as excinfo:
        make_camera("sim", SimCameraSettings(Path("missing.yaml"), "top"), base_dir=tmp_path)
    # Named as configured: a RELOAD's client gets this message (the log has the full path).
    assert "missing.yaml" in str(excinfo.value)
    assert str(tmp_path) not in str(excinfo.value)


def test_a_broken_world_state_file_is_named_as_configured(
    scene: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    state = tmp_path / "state" / "world.json"
    SimCell.from_yaml(scene, state_path=state).publish()
    settings = SimCameraSettings(scene, "top", state_file=Path("state/world.json"))
    camera = sim_camera(settings, tmp_path)
    state.write_text("[1, 2, 3, 4, 5, 6]", encoding="utf-8")  # another process broke it
    with (
        caplog.at_level("WARNING", logger="vision_server.cameras"),
        pytest.raises(CameraUnavailable) as excinfo,
    ):
        camera.grab(timeout_s=T)
    message = excinfo.value.message
    assert "state/world.json: not a world-state document" in message
    assert str(tmp_path) not in message
    assert str(tmp_path / "state" / "world.json") in caplog.text
    assert camera.status()["last_error"] == message
