"""The ``code`` inspection type: configuration (symbologies, expect, min_grade) with errors that
name file, line and key, and its verdicts and reasons on written labels."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import zxingcpp

from vision_server import InspectionInput
from vision_server.config import ConfigError, load_config
from vision_server.inspections import CodeInspection

HEAD = """\
cameras:
  cam:
    source: request
inspections:
"""
GS = "\x1d"


def load(tmp_path: Path, entry: str) -> CodeInspection:
    path = tmp_path / "cell.yaml"
    path.write_text(HEAD + entry, encoding="utf-8")
    (inspection,) = load_config(path).inspections
    assert isinstance(inspection, CodeInspection)
    return inspection


def error(tmp_path: Path, entry: str) -> str:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, entry)
    return str(info.value)


def label(text: str, fmt: zxingcpp.BarcodeFormat = zxingcpp.BarcodeFormat.DataMatrix) -> np.ndarray:
    img = np.asarray(zxingcpp.write_barcode_to_image(zxingcpp.create_barcode(text, fmt), scale=4))
    return np.pad(img, 24, constant_values=255)


def test_defaults_read_every_symbology(tmp_path: Path) -> None:
    inspection = load(tmp_path, "  - {name: k, type: code, camera: cam}\n")
    assert "datamatrix" in inspection.symbologies
    assert "databar" in inspection.symbologies
    outcome = inspection.run(InspectionInput(label(f"A{GS}B")), overlay=True)
    assert outcome.passed
    assert outcome.data["text"] == f"A{GS}B"
    assert outcome.data["text_hri"] == "A<GS>B"
    assert outcome.data["symbology"] == "datamatrix"
    assert outcome.overlay is not None


def test_bad_symbologies_name_file_line_and_key(tmp_path: Path) -> None:
    text = error(
        tmp_path, "  - {name: k, type: code, camera: cam, symbologies: [datamatrix, qrcode]}\n"
    )
    assert "cell.yaml:5" in text
    assert "symbologies" in text
    assert "'qrcode'" in text
    assert "symbologies" in error(
        tmp_path, "  - {name: k, type: code, camera: cam, symbologies: []}\n"
    )
    bad_grade = "  - {name: k, type: code, camera: cam, min_grade: {sharpness: 1}}\n"
    assert "sharpness" in error(tmp_path, bad_grade)


def test_expect_mismatch_fails_with_what_was_read(tmp_path: Path) -> None:
    inspection = load(
        tmp_path,
        '  - {name: k, type: code, camera: cam, symbologies: [datamatrix], expect: "P1"}\n',
    )
    outcome = inspection.run(InspectionInput(label("P2")), overlay=False)
    assert not outcome.passed
    assert outcome.data["found"] is False
    assert "read instead: ['P2']" in str(outcome.data["reason"])


def test_min_grade_rejects_a_poor_print_with_the_reason(tmp_path: Path) -> None:
    entry = (
        "  - {name: k, type: code, camera: cam, symbologies: [datamatrix],\n"
        "     min_grade: {module_px: 6, contrast: 0.5}}\n"
    )
    inspection = load(tmp_path, entry)
    outcome = inspection.run(InspectionInput(label("LOT42")), overlay=False)  # 4 px modules
    assert outcome.data["found"] is True
    assert not outcome.passed
    assert re.search(r"module_px [34]\.\d+ < 6", str(outcome.data["reason"]))
    assert "contrast" not in str(outcome.data["reason"])
    big = np.kron(label("LOT42"), np.ones((2, 2), np.uint8))  # 8 px modules
    assert inspection.run(InspectionInput(big), overlay=False).passed
