"""Saving an inspection whole (vision_server/frontends/http_save_whole.py): the text edit alone,
on the shapes a hand-written file takes. The rest of the file must stay byte for byte; the new
entry must read back as exactly the mapping given, whatever its strings hold."""

from __future__ import annotations

from typing import Any

import pytest
import yaml

from vision_server.frontends.http_save import NotInPlace, SaveRefused
from vision_server.frontends.http_save_whole import replaced_text

FILE = """\
# the cell
cameras:
  qc: {source: sim}   # the camera
defaults: &presence_defaults
  measure: dark_fraction
  min: 0.25
inspections:
  # first
  - name: a
    type: presence
    camera: qc
    <<: *presence_defaults
  - name: b       # the second
    type: locate
    camera: qc
    circle: {min_radius_px: 3, max_radius_px: 5}
    method: circle

  # after b
line:
  enabled: false
"""

JOB = {
    "name": "b",
    "type": "job",
    "camera": "qc",
    "steps": [
        {"name": "hole", "type": "locate", "method": "circle", "roi": [1, 2, 30, 40],
         "circle": {"min_radius_px": 10.5, "max_radius_px": 15, "polarity": "dark"}},
        {"name": "frame", "type": "fixture", "origin": "hole"},
    ],
    "verdict": "all(hole, frame)",
    "description": None,
}  # fmt: skip


def entries(text: str) -> list[Any]:
    return list(yaml.safe_load(text)["inspections"])


def test_replacing_an_entry_keeps_everything_else_byte_for_byte() -> None:
    out, created = replaced_text(FILE, "cell.yaml", "b", JOB)
    assert not created
    start = FILE.index("  - name: b") + len("  - ")
    end = FILE.index("method: circle") + len("method: circle")
    assert out.startswith(FILE[:start])
    assert out.endswith(FILE[end:])
    assert entries(out)[1] == JOB
    assert yaml.safe_load(out)["defaults"] == {"measure": "dark_fraction", "min": 0.25}
    assert '\n    steps:\n      - name: "hole"\n' in out


def test_a_new_entry_is_appended_at_the_lists_indentation() -> None:
    config = {**JOB, "name": "c"}
    out, created = replaced_text(FILE, "cell.yaml", "c", config)
    assert created
    end = FILE.index("method: circle") + len("method: circle")
    assert out.startswith(FILE[:end])
    assert out.endswith(FILE[end:])
    assert out[end:].startswith('\n  - name: "c"\n    type: "job"\n')
    assert entries(out)[-1] == config
    assert len(entries(out)) == 3


@pytest.mark.parametrize(
    ("text", "tail"),
    [
        ("cameras: {}\ninspections: [{name: a, type: qr}]\n", "]\n"),
        ("cameras: {}\ninspections: []\n", "]\n"),
        ("cameras: {}\ninspections:\n", ""),
        ("cameras: {}\ninspections: ~\nline: {}\n", "\nline: {}\n"),
        ("cameras: {}\n", ""),
        ("cameras: {}", ""),
        ("cameras: {}\r\ninspections:\r\n  - name: a\r\n    type: qr\r\n", "\r\n"),
    ],
)
def test_every_shape_of_the_list_takes_a_new_entry(text: str, tail: str) -> None:
    config = {**JOB, "name": "c"}
    out, created = replaced_text(text, "cell.yaml", "c", config)
    assert created
    assert entries(out)[-1] == config
    assert out.endswith(tail)
    if "\r\n" in text:
        assert "\n" not in out.replace("\r\n", "")


def test_strings_never_become_structure() -> None:
    tricky = [
        "{a: 1}", "&anchor", "*alias", "1\n- name: x", "# not a comment", "yes", "null", "1.5",
        "'quoted'", '"double"', "tab\there", "ünïcödé ✓", "\x1d\x1e", "key: value", "- item",
        "", " lead", "trail ", "@at", "`tick`", "%percent", "!tag",
    ]  # fmt: skip
    for text in tricky:
        config = {**JOB, "verdict": text, "description": text, "steps": [{"name": text}]}
        out, _ = replaced_text(FILE, "cell.yaml", "b", config)
        assert entries(out)[1] == config, text


def test_keys_that_yaml_would_read_otherwise_are_quoted() -> None:
    config = {**JOB, "output": {"scale": {"gauge.plate_width": 1000, "n": 1, "on": 2}}}
    out, _ = replaced_text(FILE, "cell.yaml", "b", config)
    assert entries(out)[1] == config


@pytest.mark.parametrize(
    ("config", "message"),
    [
        ({**JOB, "name": "other"}, "'other'"),
        ({**JOB, "bad key": 1}, "is not a key"),
        ({**JOB, "roi": float("nan")}, "finite"),
        ({**JOB, "x": {"y": {"z": {"a": {"b": {"c": {"d": {"e": {"f": 1}}}}}}}}}, "deeper"),
        ({**JOB, "x": object()}, "expected a number"),
        ({**JOB, "x": "\ud800"}, "Unicode"),
        ([], "mapping"),
    ],
)
def test_what_cannot_be_written_is_refused(config: Any, message: str) -> None:
    with pytest.raises(SaveRefused, match=message):
        replaced_text(FILE, "cell.yaml", "b", config)


def test_an_entry_with_a_merge_key_an_alias_or_an_anchor_is_refused() -> None:
    merged = {"name": "a", "type": "presence", "camera": "qc", "measure": "dark_fraction"}
    with pytest.raises(NotInPlace, match="anchors, aliases or merge keys"):
        replaced_text(FILE, "cell.yaml", "a", merged)
    anchored = FILE.replace("    method: circle\n", "    method: &m circle\n")
    with pytest.raises(NotInPlace, match="anchor"):
        replaced_text(anchored, "cell.yaml", "b", JOB)
    used = anchored.replace("line:\n  enabled: false\n", "line:\n  format: *m\n")
    with pytest.raises(NotInPlace, match="anchor"):
        replaced_text(used, "cell.yaml", "b", JOB)
    aliased = FILE.replace(
        "    method: circle\n", "    method: circle\n    x: *presence_defaults\n"
    )
    with pytest.raises(NotInPlace, match="anchor"):
        replaced_text(aliased, "cell.yaml", "b", JOB)


def test_a_file_that_is_not_a_mapping_or_a_list_is_refused() -> None:
    with pytest.raises(NotInPlace):
        replaced_text("- a\n- b\n", "cell.yaml", "b", JOB)
    with pytest.raises(NotInPlace):
        replaced_text("inspections: some text\n", "cell.yaml", "b", JOB)
    with pytest.raises(NotInPlace):
        replaced_text("inspections: {a: 1}\n", "cell.yaml", "b", JOB)
