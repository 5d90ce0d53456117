"""A 1024x768 image with something for every tool, and the inspections that look at it:
section 3's per-tool compute table (:mod:`.compute_tools`).

The image is the tool camera's (``dmk31bf03``: 1024x768, fx 1400 px, mild barrel distortion)
at 350 mm over a flat plate rendered by :func:`simulation.flat_parts.render_flat_part` (60 x
110 mm, i.e. about 240 x 440 px, with a 12 mm and a 7 mm through hole), a dark magnet in its
pocket, and beside the plate a DataMatrix, a Code 128 (both written by zxing-cpp's encoder, as
test_inspections/generate.py does) and a QR code (:func:`simulation.qr.qr_modules`). Positions
below are image pixels (u, v); the sizes are nominal (the lens bends them a little).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

Image = NDArray[np.uint8]

SIZE = (1024, 768)
DISTANCE_MM = 350.0
PLATE = (360.0, 384.0, 440.0, 240.0)  # centre u, v, length along u, width along v (px)
BIG_HOLE = (220.0, 384.0, 24.0)  # u, v, radius (px): the part frame's origin
SMALL_HOLE = (500.0, 384.0, 14.0)  # on the part frame's x axis
MAGNET = (360.0, 440.0, 56)  # centre u, v, side (px)
DATAMATRIX_AT = (700, 60)  # top-left of the white label (u, v)
CODE128_AT = (620, 290)
QR_AT = (700, 470)
LABEL_DM = "[)>\x1e06\x1dP12345\x1e\x04"
LABEL_128 = "ABC\x1d4711"
QR_TEXT = "cellvision:station-1"
TEMPLATE_WINDOW = (160, 324, 120, 120)  # u, v, width, height: the big hole in its plate


def _paste_label(image: Image, symbol: Image, at: tuple[int, int], quiet: int) -> None:
    """``symbol`` (black on white) on a white label with a ``quiet`` px margin at ``at``."""
    label = cv2.copyMakeBorder(symbol, quiet, quiet, quiet, quiet, cv2.BORDER_CONSTANT, value=255)
    u, v = at
    h, w = label.shape
    # print: black 20, paper 240 (not the full range a camera never gives)
    image[v : v + h, u : u + w] = (20 + label.astype(np.float64) * (220.0 / 255.0)).astype(np.uint8)


def _zxing_symbol(fmt_name: str, text: str, scale: int) -> Image:
    import zxingcpp

    symbol = zxingcpp.create_barcode(text, getattr(zxingcpp.BarcodeFormat, fmt_name))
    written = zxingcpp.write_barcode_to_image(symbol, scale=scale, add_quiet_zones=False)
    return np.ascontiguousarray(np.asarray(written, np.uint8))


def scene(seed: int = 0) -> Image:
    """The 1024x768 gray image (blur 0.8 px, noise 1.5 grey levels on the plate's render)."""
    from simulation.flat_parts import bar, disc, plane_point, render_flat_part
    from simulation.scene import camera_preset

    camera, _, _ = camera_preset("dmk31bf03")

    def mm(u: float, v: float) -> tuple[float, float]:
        return plane_point(camera, DISTANCE_MM, (u, v))

    px_per_mm = camera.fx / DISTANCE_MM
    cu, cv, length, width = PLATE
    centre = mm(cu, cv)
    along, across = (
        bar(centre, length / px_per_mm, 0.0),
        bar(centre, width / px_per_mm, math.pi / 2),
    )
    holes = [disc(mm(u, v), 2.0 * r / px_per_mm) for u, v, r in (BIG_HOLE, SMALL_HOLE)]

    def plate(x: Any, y: Any) -> Any:
        return along(x, y) & across(x, y) & ~holes[0](x, y) & ~holes[1](x, y)

    window = (
        int(cu - length / 2) - 20,
        int(cv - width / 2) - 20,
        int(length) + 40,
        int(width) + 40,
    )
    image = render_flat_part(camera, DISTANCE_MM, plate, window, supersample=4, seed=seed)
    mu, mv, side = MAGNET
    half = side // 2
    image[int(mv) - half : int(mv) + half, int(mu) - half : int(mu) + half] = 30
    _paste_label(image, _zxing_symbol("DataMatrix", LABEL_DM, 6), DATAMATRIX_AT, 24)
    _paste_label(image, _zxing_symbol("Code128", LABEL_128, 2), CODE128_AT, 24)
    from simulation.qr import qr_modules

    modules = np.where(qr_modules(QR_TEXT), 0, 255).astype(np.uint8)
    _paste_label(image, np.kron(modules, np.ones((8, 8), np.uint8)), QR_AT, 32)
    return image


def _part(u: float, v: float) -> tuple[int, int]:
    """An image point in the part frame of the job (origin at the big hole, angle 0)."""
    return int(round(u - BIG_HOLE[0])), int(round(v - BIG_HOLE[1]))


def config_text(template: str) -> str:
    """The server configuration of every tool on :func:`scene` (``template``: the template
    image's file name, beside the configuration)."""
    mu, mv, side = MAGNET
    magnet_roi = [int(mu - side / 2) + 8, int(mv - side / 2) + 8, side - 16, side - 16]
    band = "length: 320, width: 8, angle_rad: 1.5707963"  # across the plate, top to bottom
    width_band = (
        f"{{center: [440, 384], {band}}}",
        f"{{center: [{_part(440, 384)[0]}, 0], {band}}}",
    )
    mx, my = _part(magnet_roi[0], magnet_roi[1])
    dx, dy = _part(DATAMATRIX_AT[0] - 10, DATAMATRIX_AT[1] - 10)
    sx, sy = _part(SMALL_HOLE[0] - 40, SMALL_HOLE[1] - 40)
    return f"""\
cameras:
  tool: {{source: request}}
inspections:
  - {{name: locate_circle, type: locate, camera: tool, method: circle, max_count: 1,
     circle: {{min_radius_px: 20, max_radius_px: 30, polarity: dark}}}}
  - {{name: locate_blob, type: locate, camera: tool, method: blob, max_count: 1,
     blob: {{polarity: dark, min_area_px: 2600, max_area_px: 4000}}}}
  - {{name: locate_template, type: locate, camera: tool, method: template, max_count: 1,
     template: {{image: {template}}}}}
  - {{name: presence, type: presence, camera: tool, roi: {magnet_roi},
     measure: dark_fraction, threshold: 110, min: 0.6}}
  - {{name: code_datamatrix, type: code, camera: tool, symbologies: [datamatrix]}}
  - {{name: code_128, type: code, camera: tool, symbologies: [code128]}}
  - {{name: qr, type: qr, camera: tool, expect: "{QR_TEXT}"}}
  - name: caliper
    type: caliper
    camera: tool
    measurements:
      - {{name: plate_width, kind: width, band: {width_band[0]}, min: 235, max: 245}}
  - name: job
    type: job
    camera: tool
    steps:
      - {{name: big_hole, type: locate, method: circle, max_count: 1,
         circle: {{min_radius_px: 20, max_radius_px: 30, polarity: dark}}}}
      - {{name: near, type: fixture, origin: big_hole}}
      - {{name: small_hole, type: locate, fixture: near, roi: [{sx}, {sy}, 80, 80],
         method: circle, max_count: 1,
         circle: {{min_radius_px: 10, max_radius_px: 18, polarity: dark}}}}
      - {{name: part, type: fixture, origin: big_hole, x_towards: small_hole}}
      - {{name: magnet, type: presence, fixture: part, roi: [{mx}, {my}, {side - 16}, {side - 16}],
         measure: dark_fraction, threshold: 110, min: 0.6}}
      - name: gauge
        type: caliper
        fixture: part
        measurements:
          - {{name: plate_width, kind: width, band: {width_band[1]}, min: 235, max: 245}}
      - {{name: label, type: code, fixture: part, roi: [{dx}, {dy}, 180, 180],
         symbologies: [datamatrix]}}
"""


TOOLS: tuple[tuple[str, str], ...] = (
    ("locate_circle", "locate, circle (the plate's 12 mm hole)"),
    ("locate_blob", "locate, blob (the magnet)"),
    ("locate_template", "locate, template 120x120 (the hole in its plate), no angle search"),
    ("presence", "presence, dark fraction in a 40x40 ROI"),
    ("code_datamatrix", "code, DataMatrix (payload with ISO 15434 separators)"),
    ("code_128", "code, Code 128"),
    ("qr", "qr, sub-pixel corners"),
    ("caliper", "caliper, one width across the plate"),
    ("job", "job: 2 circle locates + 2 fixtures + presence + caliper + DataMatrix"),
)
"""(inspection, what it does), in the table's order."""


def write_config(directory: Path, image: Image) -> Path:
    """The configuration and its template image in ``directory``; returns the config's path."""
    u, v, w, h = TEMPLATE_WINDOW
    cv2.imwrite(str(directory / "tool_template.png"), image[v : v + h, u : u + w])
    path = directory / "tools.yaml"
    path.write_text(config_text("tool_template.png"), encoding="utf-8")
    return path


__all__ = ["SIZE", "TOOLS", "config_text", "scene", "write_config"]
