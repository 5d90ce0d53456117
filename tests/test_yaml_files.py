"""Every YAML file the project reads (the server's configuration, scenes, task files, taught
records) goes through one reader, yamlfile: merge keys work, and the same mistakes give the same
errors, naming the file, the line and the key path (``file:line path -> key: cause``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from robot_client.tasks import OnFailure, Policy, TaskError, load_task
from robot_client.teach_store import TeachStore, TeachStoreError
from simulation import SceneError, load_scene
from vision_server.config import ConfigError, load_config

MARK = "#!"  # ends the line an error must name


@dataclass(frozen=True)
class Kind:
    """One kind of file: a valid ``text`` that uses a merge key, how to ``load`` it, how its
    errors show the file (``shown``), ``check`` of the merged values, and ``mistakes``: id ->
    (text to replace, its replacement with MARK on the bad line, key path, cause)."""

    text: str
    load: Callable[[Path], Any]
    error: type[Exception]
    shown: Callable[[Path], str]
    check: Callable[[Any], bool]
    mistakes: dict[str, tuple[str, str, str, str]]


CONFIG = Kind(
    text="""\
cameras:
  tool: &camera
    source: request
    intrinsics: {width: 640, height: 480, fx: 500, fy: 500, cx: 320, cy: 240}
  side:
    <<: *camera
inspections:
  - name: bright
    type: presence
    camera: side
    measure: mean_intensity
    min: 10
""",
    load=load_config,
    error=ConfigError,
    shown=lambda path: path.name,  # errors go to clients: no server paths
    check=lambda config: config.cameras["side"].intrinsics.width == 640,
    mistakes={
        "wrong type": (
            "    min: 10",
            f"    min: high  {MARK}",
            "inspections[0] (name='bright') -> min",
            "expected a number, got 'high'",
        ),
        "unknown key": (
            "    measure: mean_intensity",
            f"    measure: mean_intensity\n    colour: red  {MARK}",
            "inspections[0] (name='bright') -> colour",
            "unknown key",
        ),
        "duplicate key": (
            "    camera: side",
            f"    camera: side\n    camera: tool  {MARK}",
            "inspections[0] -> camera",
            "duplicate key 'camera' (first on line 10)",
        ),
        "beside a merge key": (
            "    <<: *camera",
            f"    <<: *camera\n    colour: red  {MARK}",
            "cameras -> side -> colour",
            "unknown key",
        ),
    },
)

SCENE = Kind(
    text="""\
name: yaml_test
surfaces:
  - {name: floor, center: [0, 0], height: 0.0, size: [4, 4], color: 90}
qr_boards:
  - name: qr
    text: "cellvision:test"
    side_m: 0.16
    pose: {xyz: [0.989, 0.0, 1.0], rpy: [1.5707963267948966, 0.0, -1.5707963267948966]}
robot:
  world_from_base: {xyz: [0, 0, 0]}
  home: {xyz: [0, 0, 1.0]}
  workspace: {min: [-1, -1, 0], max: [1, 1, 2]}
cameras:
  - &camera
    name: rgbd
    model: xtion
    mount: tool
    pose: {xyz: [0, 0, 0]}
  - <<: *camera
    name: rgbd2
""",
    load=load_scene,
    error=SceneError,
    shown=str,
    check=lambda scene: scene.camera("rgbd2").intrinsics.width == 640,
    mistakes={
        "wrong type": (
            "    side_m: 0.16",
            f"    side_m: zero  {MARK}",
            "qr_boards[0] (name='qr') -> side_m",
            "expected a number, got 'zero'",
        ),
        "unknown key": (
            "    text: ",
            f"    colour: red  {MARK}\n    text: ",
            "qr_boards[0] (name='qr') -> colour",
            "unknown key",
        ),
        "duplicate key": (
            "    side_m: 0.16",
            f"    side_m: 0.16\n    side_m: 0.2  {MARK}",
            "qr_boards[0] -> side_m",
            "duplicate key 'side_m' (first on line 7)",
        ),
        "beside a merge key": (
            "    name: rgbd2",
            f"    name: rgbd2\n    colour: red  {MARK}",
            "cameras[1] (name='rgbd2') -> colour",
            "unknown key",
        ),
    },
)

TASK = Kind(
    text="""\
task: demo
steps:
  - vision_pick: caps_l1
    on_failure: &retry
      retry: {times: 2, wait_s: 1.0}
  - place: bin_l2
    on_failure:
      <<: *retry
      then: continue
""",
    load=load_task,
    error=TaskError,
    shown=str,
    check=lambda task: task.steps()[1].on_failure == OnFailure(Policy.CONTINUE, 2, 1.0),
    mistakes={
        "wrong type": (
            "  - place: bin_l2",
            f"  - place: 7  {MARK}",
            "steps[1] -> place",
            "expected a non-empty string, got 7",
        ),
        "unknown key": (
            "task: demo",
            f"task: demo\ncolour: red  {MARK}",
            "colour",
            "unknown key",
        ),
        "duplicate key": (
            "task: demo",
            f"task: demo\ntask: other  {MARK}",
            "task",
            "duplicate key 'task' (first on line 1)",
        ),
        "beside a merge key": (
            "      then: continue",
            f"      then: continue\n      colour: red  {MARK}",
            "steps[1] -> on_failure -> colour",
            "unknown key",
        ),
    },
)


def _taught(path: Path) -> list[Any]:
    return TeachStore(path).records()


TAUGHT = Kind(
    text="""\
format: cellvision-taught
schema_version: 2
records:
  - &place
    skill: place
    name: bin_l2
    params: {approach_m: 0.1}
  - <<: *place
    name: bin_l3
""",
    load=_taught,
    error=TeachStoreError,
    shown=str,
    check=lambda records: (
        [(r.name, dict(r.params)) for r in records]
        == [("bin_l2", {"approach_m": 0.1}), ("bin_l3", {"approach_m": 0.1})]
    ),
    mistakes={
        "wrong type": (
            "    params: {approach_m: 0.1}",
            f"    revision: first  {MARK}\n    params: {{approach_m: 0.1}}",
            "records[0] (place/bin_l2) -> revision",
            "expected an integer, got 'first'",
        ),
        "unknown key": (
            "schema_version: 2",
            f"schema_version: 2\ncolour: red  {MARK}",
            "colour",
            "unknown key",
        ),
        "duplicate key": (
            "    name: bin_l2",
            f"    name: bin_l2\n    name: bin_l4  {MARK}",
            "records[0] -> name",
            "duplicate key 'name' (first on line 6)",
        ),
        "beside a merge key": (
            "    name: bin_l3",
            f"    name: bin_l3\n    colour: red  {MARK}",
            "records[1] (place/bin_l3) -> colour",
            "unknown key",
        ),
    },
)

KINDS = {"config": CONFIG, "scene": SCENE, "task": TASK, "taught": TAUGHT}
CASES = [(k, m) for k, kind in KINDS.items() for m in kind.mistakes]


@pytest.mark.parametrize("kind_name", sorted(KINDS))
def test_a_file_with_merge_keys_loads_with_the_merged_values(
    tmp_path: Path, kind_name: str
) -> None:
    kind = KINDS[kind_name]
    path = tmp_path / f"{kind_name}.yaml"
    path.write_text(kind.text, encoding="utf-8")
    assert kind.check(kind.load(path))


@pytest.mark.parametrize(("kind_name", "mistake"), CASES)
def test_a_mistake_names_the_file_the_line_and_the_key_path(
    tmp_path: Path, kind_name: str, mistake: str
) -> None:
    kind = KINDS[kind_name]
    old, new, key_path, cause = kind.mistakes[mistake]
    assert kind.text.count(old) == 1, old
    text = kind.text.replace(old, new)
    line = 1 + next(i for i, row in enumerate(text.splitlines()) if MARK in row)
    path = tmp_path / f"{kind_name}.yaml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(kind.error) as excinfo:
        kind.load(path)
    message = str(excinfo.value)
    assert message.startswith(f"{kind.shown(path)}:{line} {key_path}: "), message
    assert cause in message


def test_every_reader_raises_the_one_reader_s_error() -> None:
    from yamlfile import DocumentError

    for kind in KINDS.values():
        assert issubclass(kind.error, DocumentError)
