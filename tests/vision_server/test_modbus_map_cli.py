"""``vision-server modbus-map`` marks what a PLC cannot trigger and names a caliper's values:
it listed full register tables for inspections whose camera takes images in the request (a
trigger only ever gets ERROR_CODE 12) and printed a caliper's values as VALUE_2 = value_1 with
no name and no unit."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vision_server.commands import main
from vision_server.commands.modbus_map import NOT_TRIGGERABLE

CELL = """\
cameras:
  tool: {source: request}
  qc: {source: folder, path: ., glob: "*.png"}
inspections:
  - {name: pick, type: presence, camera: tool, number: 1, measure: mean_intensity, min: 10}
  - name: gauge
    type: caliper
    camera: qc
    number: 2
    units: mm
    mm_per_px: 0.1
    output: {fields: [failed, value_1, {name: value_2, scale: 1000}]}
    measurements:
      - {name: gap, kind: width, band: {center: [30, 20], length: 20}}
      - {name: edge_a, kind: line, band: {center: [30, 20], length: 10, width: 8}}
      - {name: edge_b, kind: line, band: {center: [30, 40], length: 10, width: 8}}
      - {name: tilt, kind: distance, from: edge_a, to: edge_b, value: angle}
"""


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    (tmp_path / "part.png").write_bytes(b"")  # the folder camera needs a file to replay
    path = tmp_path / "cell.yaml"
    path.write_text(CELL, encoding="utf-8")
    return path


def test_the_map_json_marks_request_cameras_and_names_caliper_values(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["modbus-map", str(cell), "--json"]) == 0
    mapped = {i["name"]: i for i in json.loads(capsys.readouterr().out)["inspections"]}
    assert mapped["pick"]["triggerable"] is False
    assert mapped["gauge"]["triggerable"] is True
    values = [(v["field"], v["meaning"], v["units"]) for v in mapped["gauge"]["values"]]
    assert values == [
        ("failed", "failed: measurements out of tolerance or not measured", ""),
        ("value_1", "value_1: gap (width)", "mm"),
        ("value_2", "value_2: edge_a (line straightness)", "mm x 1000"),
    ]


def test_the_map_table_says_a_request_camera_inspection_is_not_triggerable(
    cell: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["modbus-map", str(cell)]) == 0
    out = capsys.readouterr().out
    assert f"inspection 1 = pick (presence): {NOT_TRIGGERABLE}" in " ".join(out.split())
    assert "inspection 1 = pick (presence): result values" not in out
    assert "value_1: gap (width)" in out
