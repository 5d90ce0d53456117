"""Section 3's per-tool table times tools that work: on the drawn 1024x768 image every tool
passes and finds what it is meant to (not a neighbour), and the table has a row and a ratio to
the 3x3 blur for each. No timing is asserted (shared machines)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from bench.common import RunConfig, Section
from bench.compute_tools import add_tool_table
from bench.tool_scene import BIG_HOLE, MAGNET, SIZE, TOOLS, scene, write_config
from vision_server import InspectionInput
from vision_server.config import load_config


@pytest.fixture(scope="module")
def image() -> Any:
    return scene()


def test_every_tool_passes_on_the_drawn_image_and_finds_its_target(
    image: Any, tmp_path: Path
) -> None:
    assert image.shape == (SIZE[1], SIZE[0])
    inspections = {i.name: i for i in load_config(write_config(tmp_path, image)).inspections}
    assert set(inspections) == {name for name, _ in TOOLS}
    out = {n: i.run(InspectionInput(image), overlay=False) for n, i in inspections.items()}
    failed = {n: o.data for n, o in out.items() if not o.passed}
    assert not failed
    for name, (u, v) in (
        ("locate_circle", BIG_HOLE[:2]),
        ("locate_template", BIG_HOLE[:2]),
        ("locate_blob", MAGNET[:2]),
    ):
        (found,) = out[name].data["features"]
        # the lens's distortion bends the drawn positions by less than a pixel here
        assert found["u"] == pytest.approx(u, abs=1.5), name
        assert found["v"] == pytest.approx(v, abs=1.5), name
    assert out["code_datamatrix"].data["symbology"] == "datamatrix"
    assert out["code_128"].data["symbology"] == "code128"
    assert out["caliper"].data["value"] == pytest.approx(240.0, abs=1.0)
    steps = out["job"].data["steps"]
    assert [s["type"] for s in steps.values()] == [
        "locate",
        "fixture",
        "locate",
        "fixture",
        "presence",
        "caliper",
        "code",
    ]
    assert steps["gauge"]["plate_width"] == pytest.approx(240.0, abs=1.0)


def test_the_table_has_the_blur_and_every_tool_with_its_ratio(tmp_path: Path) -> None:
    section = Section("compute", "3.")
    add_tool_table(RunConfig(quick=True, workdir=tmp_path, plots=False), section)
    assert not section.skipped
    (table,) = section.tables
    assert [row[0] for row in table.rows] == ["3x3 box blur"] + [name for name, _ in TOOLS]
    assert all(row[2] in ("pass", "—") for row in table.rows)
    for name, _ in TOOLS:
        assert section.values[f"tool_{name}_1024x768_p50_ms"] > 0
        assert section.values[f"tool_{name}_1024x768_over_blur3"] > 0
    assert section.values["box_blur3_1024x768_ms"] > 0
