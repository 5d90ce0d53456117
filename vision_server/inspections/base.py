"""What every configured inspection shares: its name, camera, ROI, how many frames it takes,
and the step from measurements to a verdict and an overlay."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from protocol import BadImage, CellvisionError, InspectionFailed
from yamlfile import Node, integer, kind, name, positive_int, string

from ..analysis import AnalysisError, BadImageError, RoiError, TemplateError
from ..cameras import CameraSettings, Intrinsics
from .output import OutputFormat

Image = npt.NDArray[Any]
ROI = tuple[int, int, int, int]

GREEN = (0, 200, 0)
RED = (0, 0, 255)


@dataclass(frozen=True)
class Common:
    """The keys every inspection has. ``roi`` is ``(u, v, width, height)`` in full-image
    pixels (None: the whole image); ``frames`` is how many frames a server camera captures;
    ``image_size`` is the camera's declared ``(width, height)`` in pixels (None: not
    declared, known only when images arrive)."""

    name: str
    type: str
    camera: str
    roi: ROI | None
    frames: int
    description: str
    intrinsics: Intrinsics | None
    camera_has_depth: bool
    image_size: tuple[int, int] | None = None
    number: int | None = None
    """The ``number:`` a line-protocol trigger may use instead of the name (None: the
    inspection's position in the list)."""
    output: OutputFormat | None = None
    """The ``output:`` of a line-protocol answer (None: every summary value)."""

    def region_size(self) -> tuple[int, int] | None:
        """The ``(width, height)`` an analysis sees: the ROI's, else the declared image's."""
        return (self.roi[2], self.roi[3]) if self.roi is not None else self.image_size


def declared_size(settings: CameraSettings) -> tuple[int, int, str] | None:
    """The image size a camera's settings promise, ``(width, height, where it is declared)``:
    the intrinsics' size, or an OpenCV camera's requested width and height (its frames are
    resized to them). None when the settings do not say."""
    intrinsics = getattr(settings, "intrinsics", None)
    if isinstance(intrinsics, Intrinsics):
        return intrinsics.width, intrinsics.height, "its intrinsics"
    width, height = getattr(settings, "width", None), getattr(settings, "height", None)
    if isinstance(width, int) and isinstance(height, int):
        return width, height, "its width and height"
    return None


def parse_common(
    node: Node, kind: str, cameras: Mapping[str, CameraSettings], *, default_frames: int = 1
) -> Common:
    inspection_name = node.take("name", name)
    node.take("type", string)
    camera = node.take("camera", name)
    if camera not in cameras:
        raise node.error(
            f"no camera named {camera!r}; configured: {', '.join(sorted(cameras)) or 'none'}",
            "camera",
        )
    settings = cameras[camera]
    has_depth = bool(getattr(settings, "depth", False)) or type(settings).__name__ == (
        "SimCameraSettings"
    )
    region = node.take("roi", roi, None)
    size = declared_size(settings)
    if region is not None and size is not None:
        u, v, w, h = region
        width, height, where = size
        if u + w > width or v + h > height:
            raise node.error(
                f"ROI [u={u}, v={v}, width={w}, height={h}] reaches past the {width}x{height} "
                f"image of camera {camera!r} ({where}): it must end by u + width <= {width} "
                f"and v + height <= {height}",
                "roi",
            )
    return Common(
        inspection_name,
        kind,
        camera,
        region,
        node.take("frames", positive_int, default_frames),
        node.take("description", string, ""),
        getattr(settings, "intrinsics", None),
        has_depth,
        None if size is None else (size[0], size[1]),
    )


class Configured:
    """The catalog properties every configured inspection derives from its ``common`` keys."""

    common: Common

    @property
    def name(self) -> str:
        return self.common.name

    @property
    def camera(self) -> str:
        return self.common.camera

    @property
    def frames(self) -> int:
        return self.common.frames

    @property
    def number(self) -> int | None:
        return self.common.number

    @property
    def output(self) -> OutputFormat | None:
        return self.common.output


def analysis_failed(inspection: str, exc: AnalysisError) -> CellvisionError:
    """The protocol error for an analysis error: the input's fault (BAD_IMAGE) or the
    analysis's (INSPECTION_FAILED)."""
    message = f"inspection {inspection!r}: {exc}"
    if isinstance(exc, BadImageError | RoiError | TemplateError):
        return BadImage(message)
    return InspectionFailed(message)


def crop(image: Image, region: ROI | None, *, inspection: str) -> tuple[Image, tuple[int, int]]:
    """The ROI of ``image`` and its offset (u0, v0); BadImage when it lies outside the image."""
    if region is None:
        return image, (0, 0)
    u, v, w, h = region
    height, width = image.shape[:2]
    if u + w > width or v + h > height:
        raise BadImage(
            f"inspection {inspection!r}: ROI [u={u}, v={v}, width={w}, height={h}] lies outside "
            f"the {width}x{height} image"
        )
    return image[v : v + h, u : u + w], (u, v)


def gray(image: Image) -> Image:
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)


def overlay_base(image: Image, region: ROI | None) -> Image:
    """A BGR copy of the image with the ROI drawn in green (the paper's Figure 4b)."""
    canvas = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    if region is not None:
        u, v, w, h = region
        cv2.rectangle(canvas, (u, v), (u + w - 1, v + h - 1), GREEN, 2)
    return canvas


MIN_TEXT_PX = 14
"""The smallest text an overlay writes, pixels (cap height and descent): legible on a small
image shown at its size."""
TEXT_FRACTION = 1 / 30
"""An overlay's text is about this fraction of the image's height (25 px on 768 rows)."""
LABEL_BACKING = (20, 20, 20)
"""The dark box behind every text: legible on a bright part and on a dark belt alike."""
_HERSHEY_PX = 22.0
"""How tall FONT_HERSHEY_SIMPLEX's capitals are at font scale 1, pixels."""


def text_px(canvas: Image) -> float:
    """The height of an overlay's labels on ``canvas``: about 1/30 of its height, at least
    :data:`MIN_TEXT_PX` (pixels of the image: the text scales with the image)."""
    return max(float(MIN_TEXT_PX), float(canvas.shape[0]) * TEXT_FRACTION)


def draw_text(
    canvas: Image,
    text: str,
    origin: tuple[int, int],
    colour: tuple[int, int, int],
    *,
    px: float | None = None,
    opacity: float = 0.7,
    box: bool = True,
    letters: bool = True,
) -> tuple[int, int, int, int]:
    """Write ``text`` (ASCII: Hershey fonts draw nothing else) with its baseline starting at
    ``origin`` (u, v), ``px`` tall (default :func:`text_px`), in ``colour`` over a dark box
    of ``opacity`` (the image shows through a little), moved inside the image when it would
    leave it. Returns the box ``(left, top, right, bottom)`` in pixels. ``box`` / ``letters``
    False leave out that layer: a legend paints its boxes, then the shapes, then its letters,
    so that the shapes stay visible under the legend's boxes."""
    size = text_px(canvas) if px is None else px
    scale = size / _HERSHEY_PX
    thickness = max(1, round(size / 12))
    pad = max(2, round(size / 6))
    rows, cols = canvas.shape[:2]
    text = fitted(text, size, cols - 2 * pad)
    (width, height), descent = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    u = min(max(int(origin[0]), pad), max(cols - width - pad, pad))
    v = min(max(int(origin[1]), height + pad), max(rows - descent - pad, height + pad))
    left, top = max(u - pad, 0), max(v - height - pad, 0)
    right, bottom = min(u + width + pad, cols), min(v + descent + pad, rows)
    if box and right > left and bottom > top:
        region = canvas[top:bottom, left:right]
        backing = np.empty_like(region)
        backing[...] = LABEL_BACKING if region.ndim == 3 else LABEL_BACKING[0]
        cv2.addWeighted(backing, opacity, region, 1.0 - opacity, 0.0, dst=region)
    if letters:
        cv2.putText(
            canvas, text, (u, v), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, thickness, cv2.LINE_AA
        )
    return left, top, right, bottom


def fitted(text: str, px: float, width_px: int) -> str:
    """``text`` in ASCII (Hershey fonts draw nothing else), cut with "..." to ``width_px`` at
    ``px`` tall (as :func:`draw_text` writes it): a reason is longer than a small image is
    wide."""
    text = text.encode("ascii", "replace").decode()
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, px / _HERSHEY_PX
    thickness = max(1, round(px / 12))
    if cv2.getTextSize(text, font, scale, thickness)[0][0] <= width_px:
        return text
    while len(text) > 1 and cv2.getTextSize(text + "...", font, scale, thickness)[0][0] > width_px:
        text = text[:-1]
    return text + "..."


def verdict_px(canvas: Image) -> float:
    """The height of the verdict's text: half as tall again as a label."""
    return 1.5 * text_px(canvas)


def _verdict_metrics(canvas: Image) -> tuple[float, int, int, int, int]:
    """The verdict's font scale, stroke, padding, word height and descent, pixels."""
    size = verdict_px(canvas)
    scale = size / _HERSHEY_PX
    thickness = max(2, round(size / 10))
    (_, word_h), descent = cv2.getTextSize("FAIL", cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)
    return scale, thickness, max(3, round(size / 5)), word_h, descent


def verdict_bottom(canvas: Image) -> int:
    """The row just below the verdict's box (:func:`draw_verdict`): a legend may start there."""
    _, _, pad, word_h, descent = _verdict_metrics(canvas)
    return min(10 + pad + word_h + descent + pad, int(canvas.shape[0]) - 1) + 1


def draw_verdict(canvas: Image, passed: bool, text: str) -> Image:
    """The verdict at the top left: PASS in green or FAIL in red, with a black outline, on a
    solid dark box, then ``text`` (what it found) in white on the same box."""
    scale, thickness, pad, word_h, descent = _verdict_metrics(canvas)
    font = cv2.FONT_HERSHEY_SIMPLEX
    word = "PASS" if passed else "FAIL"
    detail = text.encode("ascii", "replace").decode()
    word_w = cv2.getTextSize(word, font, scale, thickness)[0][0]
    small, thin = scale * 0.7, max(1, thickness - 1)
    room = canvas.shape[1] - 2 - (10 + pad + word_w) - pad
    detail = fitted("  " + detail, verdict_px(canvas) * 0.7, room)[2:] if detail else ""
    detail_w = cv2.getTextSize("  " + detail, font, small, thin)[0][0] if detail else 0
    left, top = 10, 10
    right = min(left + pad + word_w + detail_w + pad, canvas.shape[1] - 2)
    bottom = verdict_bottom(canvas) - 1
    colour = GREEN if passed else RED
    cv2.rectangle(canvas, (left, top), (right, bottom), LABEL_BACKING, -1)
    cv2.rectangle(canvas, (left, top), (right, bottom), colour, max(1, thickness // 2))
    base = (left + pad, top + pad + word_h)
    # The outline: the word in black shifted all around (OpenCV draws text no bolder than
    # thickness 2, so a thicker black stroke under it is no outline).
    ring = max(2, round(verdict_px(canvas) / 14))
    for step in range(16):
        angle = step * np.pi / 8
        at = (base[0] + round(ring * np.cos(angle)), base[1] + round(ring * np.sin(angle)))
        cv2.putText(canvas, word, at, font, scale, (0, 0, 0), thickness, cv2.LINE_AA)
    cv2.putText(canvas, word, base, font, scale, colour, thickness, cv2.LINE_AA)
    if detail:
        at = (left + pad + word_w, top + pad + word_h)
        cv2.putText(canvas, "  " + detail, at, font, small, (255, 255, 255), thin, cv2.LINE_AA)
    return canvas


def resolve(base_dir: Path, value: str) -> Path:
    path = Path(value).expanduser()
    return path if path.is_absolute() else base_dir / path


def load_template(node: Node, key: str, base_dir: Path, common: Common | None = None) -> Image:
    """A template image named in the configuration, read as gray uint8 at load time; refused
    when it cannot be correlated (constant) or, with ``common``, cannot fit in the region
    searched (the ROI, else the camera's declared image)."""
    written = node.take(key, string)
    path = resolve(base_dir, written)
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    # Named as the configuration writes it: an error goes to clients (a console try, RELOAD),
    # which need not see the server's folders.
    if image is None:
        raise node.error(f"cannot read the template image {written!r}", key)
    if image.shape[0] < 3 or image.shape[1] < 3:
        raise node.error(f"the template image {written!r} is smaller than 3x3 pixels", key)
    if float(image.std()) == 0.0:
        raise node.error(
            f"the template image {written!r} is one flat grey: normalised correlation needs "
            "texture",
            key,
        )
    region = None if common is None else common.region_size()
    if region is not None and (image.shape[1] > region[0] or image.shape[0] > region[1]):
        what = "ROI" if common is not None and common.roi is not None else "camera's image"
        raise node.error(
            f"the {image.shape[1]}x{image.shape[0]} template {written!r} is larger than the "
            f"{region[0]}x{region[1]} {what} it is searched in",
            key,
        )
    return np.ascontiguousarray(image)


def roi(value: Any) -> tuple[int, int, int, int]:
    """An ROI ``[u, v, width, height]`` in whole pixels."""
    if not isinstance(value, list) or len(value) != 4:
        raise ValueError(f"expected [u, v, width, height], got {kind(value)}")
    u, v, w, h = (integer(x) for x in value)
    if u < 0 or v < 0 or w <= 0 or h <= 0:
        raise ValueError(
            f"ROI [u, v, width, height] needs u, v >= 0 and a positive size, got {value!r}"
        )
    return u, v, w, h
