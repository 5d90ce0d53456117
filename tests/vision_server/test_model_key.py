"""``set_model_key``: training points an inspection's (or a job step's) ``model:`` at its new
file by editing the configuration's text: an existing value is replaced and a missing key added
in block style, every comment and every other byte kept; what cannot be edited without guessing
(flow style, aliases, unknown names) is refused with the reason; the result loads."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from vision_server.config import ModelKeyError, load_config, set_model_key

CELL = """\
# cell 4: the press line
cameras:
  cam: {source: request}   # the top camera
inspections:
  - name: presence_check
    type: presence
    camera: cam
    roi: [0, 0, 20, 20]
    measure: dark_fraction
    threshold: 100
    min: 0.5
  - name: surface
    type: anomaly   # the plate's top face
    camera: cam
    # the model comes from vision-server train
    model: models/surface.v1.npz   # trained on Monday
    roi: [0, 0, 64, 64]
  - name: fresh
    camera: cam
    type: anomaly
    roi: [0, 0, 64, 64]
  - name: plate
    type: job
    camera: cam
    steps:
      - name: hole
        type: locate
        method: circle
        circle: {min_radius_px: 5, max_radius_px: 9, polarity: dark}
      - name: look
        type: anomaly    # between the holes
        roi: [0, 0, 32, 32]
      - name: look2
        type: anomaly
        model: "models/plate.look2.v3.npz"
        roi: [0, 0, 32, 32]
"""


def loads(tmp_path: Path, text: str) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    load_config(path)  # the model files do not exist: untrained inspections load


def only_changed_line(before: str, after: str) -> tuple[list[str], list[str]]:
    old, new = before.splitlines(), after.splitlines()
    return [line for line in old if line not in new], [line for line in new if line not in old]


def test_an_existing_value_is_replaced_keeping_its_comment(tmp_path: Path) -> None:
    after = set_model_key(CELL, "surface", "models/surface.v2.npz")
    removed, added = only_changed_line(CELL, after)
    assert removed == ["    model: models/surface.v1.npz   # trained on Monday"]
    assert added == ['    model: "models/surface.v2.npz"   # trained on Monday']
    assert len(after.splitlines()) == len(CELL.splitlines())
    loads(tmp_path, after)
    document = yaml.safe_load(after)
    assert document["inspections"][1]["model"] == "models/surface.v2.npz"


def test_a_missing_key_is_added_in_block_style_below_type(tmp_path: Path) -> None:
    after = set_model_key(CELL, "fresh", "models/fresh.v1.npz")
    lines = after.splitlines()
    at = lines.index("    type: anomaly", lines.index("  - name: fresh"))
    assert lines[at + 1] == '    model: "models/fresh.v1.npz"'
    assert after.replace('    model: "models/fresh.v1.npz"\n', "", 1) == CELL
    loads(tmp_path, after)
    assert yaml.safe_load(after)["inspections"][2]["model"] == "models/fresh.v1.npz"


def test_a_job_steps_key_is_added_or_replaced(tmp_path: Path) -> None:
    added = set_model_key(CELL, "plate", "models/plate.look.v1.npz", step="look")
    lines = added.splitlines()
    at = lines.index("        type: anomaly    # between the holes")
    assert lines[at + 1] == '        model: "models/plate.look.v1.npz"'
    assert added.replace('        model: "models/plate.look.v1.npz"\n', "", 1) == CELL
    loads(tmp_path, added)
    replaced = set_model_key(added, "plate", "models/plate.look2.v4.npz", step="look2")
    removed, new = only_changed_line(added, replaced)
    assert removed == ['        model: "models/plate.look2.v3.npz"']
    assert new == ['        model: "models/plate.look2.v4.npz"']
    steps = yaml.safe_load(replaced)["inspections"][3]["steps"]
    assert [s.get("model") for s in steps] == [
        None,
        "models/plate.look.v1.npz",
        "models/plate.look2.v4.npz",
    ]
    loads(tmp_path, replaced)


def test_an_empty_model_key_gets_the_value(tmp_path: Path) -> None:
    for written in ("    model:\n", "    model:   # not trained yet\n", "    model: ~\n"):
        text = CELL.replace("    model: models/surface.v1.npz   # trained on Monday\n", written)
        loads(tmp_path, text)
        after = set_model_key(text, "surface", "models/surface.v1.npz")
        assert yaml.safe_load(after)["inspections"][1]["model"] == "models/surface.v1.npz"
        if "#" in written:
            assert '    model: "models/surface.v1.npz"   # not trained yet\n' in after
        loads(tmp_path, after)


def test_the_last_line_without_a_newline_gets_the_key_too(tmp_path: Path) -> None:
    text = (
        "cameras:\n  cam: {source: request}\ninspections:\n  - name: s\n    camera: cam\n"
        "    type: anomaly"
    )
    after = set_model_key(text, "s", "models/s.v1.npz")
    assert after.endswith('    type: anomaly\n    model: "models/s.v1.npz"\n')
    loads(tmp_path, after)


@pytest.mark.parametrize(
    ("text", "inspection", "step", "cause"),
    [
        (CELL, "nobody", None, "no inspection named 'nobody'"),
        (CELL, "plate", "nostep", "no step of 'plate' named 'nostep'"),
        (CELL, "surface", "look", "no step of 'surface' named 'look'"),
        (
            CELL.replace(
                "  - name: fresh\n    camera: cam\n    type: anomaly\n    roi: [0, 0, 64, 64]\n",
                "  - {name: fresh, camera: cam, type: anomaly, roi: [0, 0, 64, 64]}\n",
            ),
            "fresh",
            None,
            "flow style",
        ),
        (
            CELL.replace(
                "      - name: look\n        type: anomaly    # between the holes\n"
                "        roi: [0, 0, 32, 32]\n",
                "      - {name: look, type: anomaly, roi: [0, 0, 32, 32]}\n",
            ),
            "plate",
            "look",
            "flow style",
        ),
        (
            CELL.replace("cam: {source: request}", "cam: {source: request, x: &m a.npz}").replace(
                "model: models/surface.v1.npz", "model: *m"
            ),
            "surface",
            None,
            "alias",
        ),
        (CELL.replace("model: models/surface.v1.npz", "model: [a, b]"), "surface", None, "plain"),
        ("inspections: [", "surface", None, "not valid YAML"),
        ("- a\n- b\n", "surface", None, "top level is not a mapping"),
        ("cameras: {}\n", "surface", None, "no inspection named 'surface'"),
    ],
    ids=[
        "unknown-inspection",
        "unknown-step",
        "step-of-non-job",
        "flow-inspection",
        "flow-step",
        "alias",
        "sequence-value",
        "broken-yaml",
        "not-a-mapping",
        "no-inspections",
    ],
)
def test_what_cannot_be_edited_is_refused_with_the_reason(
    text: str, inspection: str, step: str | None, cause: str
) -> None:
    with pytest.raises(ModelKeyError, match=cause):
        set_model_key(text, inspection, "models/x.v1.npz", step=step)


@settings(max_examples=30)
@given(
    st.text(
        st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00"),
        min_size=1,
        max_size=40,
    )
)
def test_any_value_is_written_as_a_scalar_that_reads_back_exactly(value: str) -> None:
    after = set_model_key(CELL, "fresh", value)
    document = yaml.safe_load(after)
    assert document["inspections"][2]["model"] == value
    assert (
        after.replace(
            after.splitlines()[after.splitlines().index("  - name: fresh") + 3] + "\n", "", 1
        )
        == CELL
    )
