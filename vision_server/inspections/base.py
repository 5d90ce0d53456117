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


def draw_verdict(canvas: Image, passed: bool, text: str) -> Image:
    label = ("PASS" if passed else "FAIL") + (f"  {text}" if text else "")
    scale = max(0.5, canvas.shape[1] / 1400.0)
    cv2.putText(
        canvas,
        label,
        (10, int(30 * scale) + 5),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        GREEN if passed else RED,
        max(1, int(2 * scale)),
        cv2.LINE_AA,
    )
    return canvas


def resolve(base_dir: Path, value: str) -> Path:
    path = Path(value).expanduser()
    return path if path.is_absolute() else base_dir / path


def load_template(node: Node, key: str, base_dir: Path, common: Common | None = None) -> Image:
    """A template image named in the configuration, read as gray uint8 at load time; refused
    when it cannot be correlated (constant) or, with ``common``, cannot fit in the region
    searched (the ROI, else the camera's declared image)."""
    path = resolve(base_dir, node.take(key, string))
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if image is None:
        raise node.error(f"cannot read the template image {path}", key)
    if image.shape[0] < 3 or image.shape[1] < 3:
        raise node.error(f"the template image {path} is smaller than 3x3 pixels", key)
    if float(image.std()) == 0.0:
        raise node.error(
            f"the template image {path} is one flat grey: normalised correlation needs texture",
            key,
        )
    region = None if common is None else common.region_size()
    if region is not None and (image.shape[1] > region[0] or image.shape[0] > region[1]):
        what = "ROI" if common is not None and common.roi is not None else "camera's image"
        raise node.error(
            f"the {image.shape[1]}x{image.shape[0]} template {path} is larger than the "
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
