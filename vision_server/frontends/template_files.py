"""Template images trained in the console: a rectangle of an image, kept as a grey PNG in the
``templates/`` folder beside the configuration file.

A template's file name is its content's address, ``<inspection>-<first 12 hex of the SHA-256
of its pixels>.png``: the same crop twice is the same file, and a file is never overwritten
(a name that is taken by other pixels is refused). The file is written to a temporary name
in the folder, synced, and linked to its name, which fails rather than replace a file: no
reader ever sees half a template. The folder holds at most :data:`MAX_TEMPLATES` PNG files
and :data:`MAX_FOLDER_BYTES` bytes.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..config import files

FOLDER = "templates"
"""The folder beside the configuration file that trained templates are written to."""
MIN_SIDE = 8
"""The smallest template side, pixels (a smaller one correlates with anything)."""
MAX_SIDE = 1024
"""The largest template side, pixels (the search's cost grows with its area)."""
MAX_TEMPLATES = 1000
"""The most PNG files the folder may hold before training is refused."""
MAX_FOLDER_BYTES = 200 << 20
"""The most bytes of PNG files the folder may hold before training is refused (1000 noisy
1024 x 1024 crops are some 800 MB)."""


class TemplateRefused(ValueError):
    """The crop cannot be a template; ``status`` is the HTTP status that says why (400: the
    request's rectangle or image, 409: the folder)."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


@dataclass(frozen=True)
class Template:
    """A template written (or found already written): ``path`` relative to the configuration's
    folder, in POSIX form as the configuration names it; ``png`` its bytes."""

    path: str
    width: int
    height: int
    png: bytes


def check_rect(rect: Any, width: int, height: int) -> tuple[int, int, int, int]:
    """``rect`` ``[x, y, w, h]`` in whole pixels inside a ``width`` x ``height`` image, each
    side in ``MIN_SIDE..MAX_SIDE``; TemplateRefused naming ``rect`` otherwise."""
    if (
        not isinstance(rect, list)
        or len(rect) != 4
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in rect)
    ):
        raise TemplateRefused("rect must be [x, y, w, h] in whole pixels")
    x, y, w, h = rect
    if not (MIN_SIDE <= w <= MAX_SIDE and MIN_SIDE <= h <= MAX_SIDE):
        raise TemplateRefused(
            f"rect {rect}: a template is {MIN_SIDE}..{MAX_SIDE} px on each side, got {w}x{h}"
        )
    if x < 0 or y < 0:
        raise TemplateRefused(f"rect {rect}: x and y must be >= 0")
    if x + w > width or y + h > height:
        raise TemplateRefused(f"rect {rect} is not inside the {width}x{height} image")
    return x, y, w, h


def cut(image: np.ndarray, rect: Any) -> np.ndarray:
    """The grey crop of ``image`` (grey or BGR, 8 or 16 bits) at ``rect``: a template the loader
    will take (textured, 8-bit)."""
    height, width = image.shape[:2]
    x, y, w, h = check_rect(rect, width, height)
    patch = image[y : y + h, x : x + w]
    if patch.ndim == 3:
        patch = cv2.cvtColor(patch, cv2.COLOR_BGR2GRAY)
    if patch.dtype != np.uint8:  # a 16-bit image: its top 8 bits, as the analyses read it
        patch = (patch >> 8).astype(np.uint8)
    if float(patch.std()) == 0.0:
        raise TemplateRefused(
            f"rect {rect} is one flat grey: a template needs texture to be found by correlation"
        )
    return np.ascontiguousarray(patch)


def address(grey: np.ndarray) -> str:
    """The first 12 hex digits of the SHA-256 of the template's size and pixels."""
    digest = hashlib.sha256(f"{grey.shape[1]}x{grey.shape[0]}:".encode())
    digest.update(grey.tobytes())
    return digest.hexdigest()[:12]


def keep(config_dir: Path, inspection: str, grey: np.ndarray) -> Template:
    """Write ``grey`` as ``templates/<inspection>-<address>.png`` in ``config_dir`` (made when
    missing), atomically and never over another file; the same pixels again find their file.
    Raises TemplateRefused (409) for a full or unusable folder, OSError for the disk's faults."""
    base = config_dir.resolve()
    folder = base / FOLDER
    if folder.is_symlink() or (folder.exists() and not folder.is_dir()):
        raise TemplateRefused(f"{FOLDER}/ beside the configuration is not a folder", 409)
    folder.mkdir(exist_ok=True)
    name = f"{inspection}-{address(grey)}.png"
    final = folder / name
    ok, encoded = cv2.imencode(".png", grey)
    if not ok:
        raise OSError("the template could not be encoded as PNG")
    png = encoded.tobytes()
    relative = f"{FOLDER}/{name}"
    if final.exists():
        return _same(final, relative, grey, png)
    pngs = [entry for entry in folder.iterdir() if entry.suffix.lower() == ".png"]
    held = sum(entry.stat().st_size for entry in pngs if entry.is_file())
    if len(pngs) >= MAX_TEMPLATES or held + len(png) > MAX_FOLDER_BYTES:
        raise TemplateRefused(
            f"{FOLDER}/ beside the configuration holds {len(pngs)} templates of {held} bytes; "
            f"it may hold {MAX_TEMPLATES} templates and {MAX_FOLDER_BYTES} bytes: delete those "
            "no inspection uses",
            409,
        )
    if not files.write_new(final, png, mode=0o644):  # never over another file
        return _same(final, relative, grey, png)  # written meanwhile, by another request
    return Template(relative, grey.shape[1], grey.shape[0], png)


def _same(final: Path, relative: str, grey: np.ndarray, png: bytes) -> Template:
    """The file already at the template's name, when it holds these very pixels."""
    if final.is_file() and final.stat().st_size == len(png) and final.read_bytes() == png:
        return Template(relative, grey.shape[1], grey.shape[0], png)
    # Another encoder's file of the same pixels (read only when no larger than a template
    # may be: a file put there by hand is not decoded whatever its size).
    small = final.is_file() and final.stat().st_size <= 4 * MAX_SIDE * MAX_SIDE
    existing = cv2.imread(str(final), cv2.IMREAD_UNCHANGED) if small else None
    if existing is None or existing.shape != grey.shape or not np.array_equal(existing, grey):
        raise TemplateRefused(
            f"{relative} exists and holds another image: it is not overwritten (rename it)", 409
        )
    return Template(relative, grey.shape[1], grey.shape[0], png)


__all__ = [
    "FOLDER",
    "MAX_SIDE",
    "MAX_FOLDER_BYTES",
    "MAX_TEMPLATES",
    "MIN_SIDE",
    "Template",
    "TemplateRefused",
    "address",
    "check_rect",
    "cut",
    "keep",
]
