"""read_qr: decoding, corner order (printed c0..c3), sub-pixel corners, real photographs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from vision_server.analysis import BadImageError, NotFoundError, RoiError
from vision_server.analysis.qr import QRCode, decode_raw, read_qr

from .conftest import render_qr, square_corners

TEXT = "cellvision:station-1"


@pytest.mark.parametrize("angle", [0, 90, 180, 270, 33])
def test_corner_order_follows_the_print_under_rotation(angle: float) -> None:
    corners = square_corners((320, 240), 180, angle)
    img = render_qr(TEXT, corners, noise_sigma=2)
    (code,) = read_qr(img)
    assert isinstance(code, QRCode)
    assert code.text == TEXT
    assert code.corners.shape == (4, 2)
    assert code.corners.dtype == np.float64
    np.testing.assert_allclose(code.corners, corners, atol=0.3)


def test_corner_order_under_perspective() -> None:
    corners = np.array([[250.0, 150.0], [430.0, 180.0], [410.0, 330.0], [230.0, 300.0]])
    for k in range(4):  # every corner of the print at every corner of the quad
        c = np.roll(corners, k, axis=0)
        (code,) = read_qr(render_qr(TEXT, c, blur_sigma=0.7, noise_sigma=2, seed=k))
        np.testing.assert_allclose(code.corners, c, atol=0.4)


@pytest.mark.parametrize("angle", [0, 90, 200])
def test_mirrored_image_keeps_c0_at_the_top_left_finder_and_stays_clockwise(angle: float) -> None:
    uv = square_corners((320, 240), 160, angle)
    # mirrored: uv are the image positions of the printed c1, c0, c3, c2
    (code,) = read_qr(render_qr(TEXT, uv, mirror=True))
    assert code.text == TEXT
    np.testing.assert_allclose(code.corners[0], uv[1], atol=0.3)  # top-left finder
    np.testing.assert_allclose(code.corners[2], uv[3], atol=0.3)  # no finder
    # documented: clockwise on the screen, so c1/c3 are the printed bottom-left/top-right
    np.testing.assert_allclose(code.corners[[1, 3]], uv[[2, 0]], atol=0.3)


def test_subpixel_corner_accuracy_on_synthetic_warps() -> None:
    rng = np.random.default_rng(7)
    errors = []
    for i in range(25):
        side = rng.uniform(70, 220)
        c = square_corners(
            (rng.uniform(220, 420), rng.uniform(190, 290)), side, rng.uniform(0, 360)
        )
        c = c + rng.normal(0, 0.06 * side, (4, 2))
        img = render_qr(TEXT, c, blur_sigma=rng.uniform(0, 1.2), noise_sigma=2, seed=i)
        code = read_qr(img, expect=TEXT)[0]
        errors.append(np.linalg.norm(code.corners - c, axis=1))
    err = np.concatenate(errors)
    assert np.median(err) < 0.12
    assert np.percentile(err, 95) < 0.35


def test_expect_selects_among_several_codes_and_roi_offsets_corners() -> None:
    a = square_corners((170, 240), 140)
    b = square_corners((470, 240), 140, 20)
    img = np.minimum(
        render_qr("part:A-17", a, background=255), render_qr("part:B-42", b, background=255)
    )
    codes = read_qr(img)
    assert {c.text for c in codes} == {"part:A-17", "part:B-42"}
    (code,) = read_qr(img, expect="part:B-42")
    np.testing.assert_allclose(code.corners, b, atol=0.3)
    (code,) = read_qr(img, expect=re.compile(r"part:A-\d+"))
    assert code.text == "part:A-17"
    (code,) = read_qr(img, roi=[330, 80, 290, 320])
    assert code.text == "part:B-42"
    np.testing.assert_allclose(code.corners, b, atol=0.3)
    with pytest.raises(NotFoundError, match="part:C"):
        read_qr(img, expect="part:C")


def test_the_fastest_decoder_goes_first_and_the_others_only_when_it_finds_nothing() -> None:
    # issue 19: running every decoder on every image cost 20x zxing-cpp alone for a few reads
    img = render_qr(TEXT, square_corners((320, 240), 150))
    found, tried = decode_raw(img, ("zxing", "pyzbar", "opencv", "opencv_aruco"))
    assert [f.text for f in found] == [TEXT]
    assert tried == ["zxing"]
    (code,) = read_qr(img)
    assert code.decoder == "zxing"
    # a decoder that finds nothing escalates to the next one
    blank = np.full((240, 320), 200, np.uint8)
    _, tried = decode_raw(blank, ("zxing", "pyzbar"), preprocess=False)
    assert tried == ["zxing", "pyzbar"]


def test_colour_input_and_errors() -> None:
    img = render_qr(TEXT, square_corners((320, 240), 150))
    (code,) = read_qr(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    assert code.text == TEXT
    with pytest.raises(NotFoundError, match="tried zxing, pyzbar"):
        read_qr(np.full((480, 640), 128, np.uint8))
    with pytest.raises(BadImageError):
        read_qr(img.astype(np.float32))
    with pytest.raises(BadImageError):
        read_qr(np.zeros((10, 10), np.uint8))
    with pytest.raises(RoiError):
        read_qr(img, roi=[600, 0, 100, 100])
    with pytest.raises(RoiError):
        read_qr(img, roi=[0, 0, 0, 10])


def test_real_photographs(qr_real_dir: Path) -> None:
    rows = json.loads((qr_real_dir / "manifest.json").read_text())
    assert len(rows) == 179
    decoded = 0
    for row in rows:
        img = cv2.imread(str(qr_real_dir / row["image"]), cv2.IMREAD_GRAYSCALE)
        try:
            read_qr(img, expect=row["expected_text"], refine=False)
        except NotFoundError:
            continue
        decoded += 1
    assert decoded >= 170
