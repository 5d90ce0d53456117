"""Scene YAML validation: typed results, and errors that name file, line and key path."""

from __future__ import annotations

import pytest

from simulation import SceneError, load_scene, scene_from_text

from .conftest import BOARD_SCENE, EXAMPLE_SCENE


def test_example_scene_loads() -> None:
    scene = load_scene(EXAMPLE_SCENE)
    assert scene.name == "grundfos_cell"
    tool = scene.camera("tool_camera")
    assert (tool.intrinsics.width, tool.intrinsics.height) == (1024, 768)
    assert tool.intrinsics.has_distortion
    rgbd = scene.camera("rgbd")
    assert (rgbd.intrinsics.width, rgbd.intrinsics.height) == (640, 480)
    assert rgbd.depth is not None
    assert rgbd.depth.fb_px_m == pytest.approx(43.5)
    caps = [p for p in scene.parts if p.type == "rotor_cap"]
    assert len(caps) == 5
    # Parts stand on their support: a cap on the conveyor has its bottom at the belt height.
    assert scene.part("cap_1").world_from_part[2, 3] == pytest.approx(0.8)
    assert len(scene.qr_boards) == 1
    assert len(scene.switches) == 1


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        (
            "side_m: 0.16",
            "side_m: 0.16\n    sise_m: 1",
            r"board_test.yaml:\d+ qr_boards\[0\] \(name='qr'\) -> sise_m: unknown key",
        ),
        (
            "side_m: 0.16",
            "side_m: -0.16",
            r"board_test.yaml:\d+ qr_boards\[0\] \(name='qr'\) -> side_m: expected a number > 0",
        ),
        (
            "color: 150}",
            "color: [1, 2]}",
            r"boxes\[0\] \(name='wall'\) -> color: expected a BGR colour",
        ),
        (
            "model: xtion",
            "model: kinect9",
            r"cameras\[0\] \(name='rgbd'\) -> model: expected one of",
        ),
        ("max: [1, 1, 2]", "max: [1, 1, -2]", r"robot -> workspace: expected min < max"),
    ],
)
def test_errors_name_file_line_and_path(old: str, new: str, expected: str) -> None:
    assert old in BOARD_SCENE
    with pytest.raises(SceneError, match=expected):
        scene_from_text(BOARD_SCENE.replace(old, new, 1), source="board_test.yaml")


def test_error_line_number_is_the_offending_line() -> None:
    text = BOARD_SCENE.replace("side_m: 0.16", "side_m: zero")
    line = text.splitlines().index("    side_m: zero") + 1
    with pytest.raises(
        SceneError, match=rf"board_test.yaml:{line} qr_boards\[0\] \(name='qr'\) -> side_m"
    ):
        scene_from_text(text, source="board_test.yaml")


def test_unknown_support_and_duplicate_names() -> None:
    bad = BOARD_SCENE.replace(
        "qr_boards:",
        "parts:\n  - {name: c, type: rotor_cap, at: [0, 0], support: nowhere}\nqr_boards:",
    )
    with pytest.raises(
        SceneError, match=r"parts\[0\] \(name='c'\) -> support: unknown support 'nowhere'"
    ):
        scene_from_text(bad)
    dup = BOARD_SCENE.replace("name: qr\n", "name: wall\n")
    with pytest.raises(SceneError, match="duplicate name 'wall'"):
        scene_from_text(dup)


def test_missing_file_and_bad_yaml(tmp_path: object) -> None:
    with pytest.raises(SceneError, match="cannot read"):
        load_scene("/nonexistent/scene.yaml")
    with pytest.raises(SceneError, match="invalid YAML"):
        scene_from_text("name: [unclosed\n")
