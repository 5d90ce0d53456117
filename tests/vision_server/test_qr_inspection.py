"""The ``qr`` inspection's ``corners`` choice: sub-pixel corners (the default) or the decoder's
own, cheaper ones for a check that needs the payload only; a bad value names file, line and key."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import zxingcpp

from vision_server import InspectionInput
from vision_server.config import ConfigError, load_config
from vision_server.inspections import QRInspection

HEAD = """\
cameras:
  cam:
    source: request
inspections:
"""
SHIFT = np.array([0.3, 0.6])  # (du, dv) px: the code's corners lie between pixel centres


def load(tmp_path: Path, entry: str) -> QRInspection:
    path = tmp_path / "cell.yaml"
    path.write_text(HEAD + entry, encoding="utf-8")
    (inspection,) = load_config(path).inspections
    assert isinstance(inspection, QRInspection)
    return inspection


def shifted_code() -> tuple[np.ndarray, np.ndarray]:
    """A QR code at 5 px per module moved by SHIFT, and its true outer corners c0..c3 (px)."""
    symbol = zxingcpp.create_barcode("CELL-7", zxingcpp.BarcodeFormat.QRCode)
    img = np.pad(
        np.asarray(zxingcpp.write_barcode_to_image(symbol, scale=5), np.uint8),
        30,
        constant_values=255,
    )
    rows, cols = np.nonzero(img < 128)
    # the outer boundary of the dark modules: half a pixel outside the outermost dark centres
    u0, u1, v0, v1 = cols.min() - 0.5, cols.max() + 0.5, rows.min() - 0.5, rows.max() + 0.5
    corners = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]]) + SHIFT
    move = np.array([[1.0, 0.0, SHIFT[0]], [0.0, 1.0, SHIFT[1]]])
    shifted = cv2.warpAffine(img, move, img.shape[::-1], flags=cv2.INTER_LINEAR, borderValue=255)
    return np.asarray(shifted, np.uint8), corners


def test_subpixel_is_the_default_and_refines_the_corners(tmp_path: Path) -> None:
    image, truth = shifted_code()
    inspection = load(tmp_path, "  - {name: q, type: qr, camera: cam}\n")
    outcome = inspection.run(InspectionInput(image), overlay=False)
    assert outcome.passed
    assert outcome.data["text"] == "CELL-7"
    error = np.abs(np.array(outcome.data["corners"]) - truth).max()
    assert error < 0.25, (outcome.data["corners"], truth)


def test_decoder_corners_skip_the_refinement_and_keep_the_order(tmp_path: Path) -> None:
    image, truth = shifted_code()
    inspection = load(tmp_path, "  - {name: q, type: qr, camera: cam, corners: decoder}\n")
    outcome = inspection.run(InspectionInput(image), overlay=True)
    assert outcome.passed
    assert outcome.data["text"] == "CELL-7"
    corners = np.array(outcome.data["corners"])
    # the decoder's estimates: whole pixels, not the sub-pixel corners, c0 top-left and
    # clockwise like the refined ones (within a module of the truth)
    np.testing.assert_array_equal(corners, np.round(corners))
    assert np.abs(corners - truth).max() > 0.25
    assert np.abs(corners - truth).max() < 5.0
    assert outcome.overlay is not None


def test_a_bad_corners_value_names_file_line_and_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as info:
        load(tmp_path, "  - {name: q, type: qr, camera: cam, corners: exact}\n")
    text = str(info.value)
    assert "cell.yaml:5" in text, text
    assert "corners" in text, text
    assert "subpixel" in text, text
