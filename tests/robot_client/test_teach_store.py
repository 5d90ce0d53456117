"""The YAML teach store: round trip, revisions, atomic writes, errors, the v1 → v2 upgrade."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from geometry import transform_from_xyz_rpy
from robot_client.skills import TaughtRecord, pose_from_yaml
from robot_client.teach_store import SCHEMA_VERSION, TeachStore, TeachStoreError, UnknownRecord

HEAD = "format: cellvision-taught\nschema_version: 2\nrecords:\n"
POSE = {"xyz": [0.68, 0.3, 0.1], "rpy": [3.141592654, 0.0, 0.0]}


def test_put_get_and_revisions(tmp_path: Path) -> None:
    store = TeachStore(tmp_path / "cell" / "taught.yaml")
    assert store.records() == []
    first = store.put(TaughtRecord("place", "bin_l2", {"pose": POSE}, taught_at="t1"))
    assert first.revision == 1
    again = store.put(TaughtRecord("place", "bin_l2", {"pose": POSE, "approach_m": 0.2}))
    assert again.revision == 2
    store.put(TaughtRecord("press", "switch", {"pose": POSE}, frame="qr:station-1", notes="hi"))
    fresh = TeachStore(store.path)
    assert fresh.get("place", "bin_l2").params["approach_m"] == 0.2
    assert fresh.find("switch").frame == "qr:station-1"
    assert fresh.find("press/switch").notes == "hi"
    assert [r.key for r in fresh.records()] == ["place/bin_l2", "press/switch"]
    assert [r.key for r in fresh.records("press")] == ["press/switch"]
    doc = yaml.safe_load(store.path.read_text())
    assert doc["schema_version"] == SCHEMA_VERSION
    assert doc["format"] == "cellvision-taught"
    store.remove("press", "switch")
    with pytest.raises(UnknownRecord, match="no record 'switch' for skill 'press'"):
        store.get("press", "switch")
    assert not list(store.path.parent.glob(".taught.yaml.*"))  # no temporary files left


def test_ambiguous_names_need_the_skill(tmp_path: Path) -> None:
    store = TeachStore(tmp_path / "t.yaml")
    store.put(TaughtRecord("move_to", "l2", {"pose": POSE}))
    store.put(TaughtRecord("place", "l2", {"pose": POSE}))
    with pytest.raises(UnknownRecord, match="ambiguous"):
        store.find("l2")
    assert store.find("place/l2").skill == "place"


def test_a_failed_write_leaves_the_old_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    store = TeachStore(tmp_path / "t.yaml")
    store.put(TaughtRecord("place", "a", {"pose": POSE}))
    before = store.path.read_text()

    def broken(*_: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr("robot_client.teach_store.os.replace", broken)
    with pytest.raises(OSError, match="disk full"):
        store.put(TaughtRecord("place", "b", {"pose": POSE}))
    assert store.path.read_text() == before
    assert [p.name for p in tmp_path.iterdir()] == ["t.yaml"]


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("records: [\n  - {skill: a\n", r"t\.yaml:2: invalid YAML"),
        ("- 1\n", "t.yaml:1: the top level must be a mapping"),
        ("format: cellvision-taught\nschema_version: 99\n", "newer than this program"),
        ("format: other\nschema_version: 2\n", "t.yaml:1 format: expected one of"),
        (
            HEAD + "  - {skill: place, name: a, colour: red}\n",
            r"t\.yaml:4 records\[0\] \(place/a\) -> colour: unknown key",
        ),
        (
            HEAD + "  - {skill: place, name: a, revision: 0}\n",
            r"t\.yaml:4 records\[0\] \(place/a\) -> revision: expected an integer >= 1",
        ),
        (
            HEAD + "  - {skill: place}\n",
            r"t\.yaml:4 records\[0\] \(place/None\): missing required key 'name'",
        ),
        (
            HEAD + "  - {skill: p, name: a}\n  - {skill: p, name: a}\n",
            "p/a appears twice",
        ),
        ("format: cellvision-taught\nschema_version: 2\nextra: 1\n", "t.yaml:3 extra: unknown key"),
    ],
)
def test_errors_name_file_record_and_key(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "t.yaml"
    path.write_text(text)
    with pytest.raises(TeachStoreError, match=match):
        TeachStore(path).records()


def test_yaml_tags_are_not_executed(tmp_path: Path) -> None:
    path = tmp_path / "t.yaml"
    path.write_text("!!python/object/apply:os.system ['echo hacked']\n")
    with pytest.raises(TeachStoreError, match="invalid YAML"):
        TeachStore(path).records()


V1 = """\
version: 1
skills:
  bin_l2:
    skill: place
    params:
      pose: [[1, 0, 0, 0.68], [0, -1, 0, 0.3], [0, 0, -1, 0.1], [0, 0, 0, 1]]
      approach_m: 0.1
  switch:
    skill: press
    frame: "qr:station-1"
    notes: from the old robot
    params: {pose: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], depth_m: 0.004}
"""


def test_a_version_1_file_is_upgraded(tmp_path: Path) -> None:
    path = tmp_path / "t.yaml"
    path.write_text(V1)
    store = TeachStore(path)
    records = {r.name: r for r in store.records()}
    assert store.upgraded_from == 1
    place = records["bin_l2"]
    assert (place.skill, place.frame, place.revision) == ("place", "base", 1)
    expected = transform_from_xyz_rpy([0.68, 0.3, 0.1], [np.pi, 0.0, 0.0])
    assert np.allclose(pose_from_yaml(place.params["pose"]), expected, atol=1e-8)
    assert set(place.params["pose"]) == {"xyz", "rpy"}
    assert records["switch"].frame == "qr:station-1"
    assert records["switch"].notes == "from the old robot"
    assert records["switch"].params["depth_m"] == 0.004
    assert path.read_text() == V1  # reading never rewrites
    store.save()
    doc = yaml.safe_load(path.read_text())
    assert doc["schema_version"] == SCHEMA_VERSION
    assert {r["name"] for r in doc["records"]} == {"bin_l2", "switch"}
    assert TeachStore(path).upgraded_from is None


def test_an_error_in_a_version_1_file_names_the_line_of_its_entry(tmp_path: Path) -> None:
    path = tmp_path / "t.yaml"
    path.write_text("version: 1\nskills:\n  a:\n    skill: place\n  b:\n    params: {x: 1}\n")
    with pytest.raises(TeachStoreError, match=r"t\.yaml:5 records\[1\] \(None/b\): missing"):
        TeachStore(path).records()
    path.write_text("version: 1\nskills:\n  a: 3\n")
    with pytest.raises(TeachStoreError, match=r"t\.yaml:3 skills -> a: expected a mapping"):
        TeachStore(path).records()
