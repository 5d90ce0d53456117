"""Image files for the command-line tools (``vision-server run``, ``robot-client inspect``): the
payload that carries a file's bytes, and whether an overlay can be written to a path. Pure
functions: the caller reads and writes the files (``folder_exists`` is passed in).

Every format OpenCV decodes is read (PNG, JPEG, BMP, TIFF, WebP, PGM/PPM/PNM, ...). PNG and
JPEG files travel as they are: the receiver checks their header against its pixel limit before
decoding them (SPEC §4.3). Any other format is decoded here and sent raw (``gray8``, ``bgr8``,
``depth16``), so that the receiver checks its size from the descriptor.

What a file may hold, by role:

- colour: 8-bit gray or colour; an alpha channel is dropped. A 16-bit image is refused, saying
  so: the colour inspections (locate, presence, qr) measure 8-bit gray levels, and scaling 16
  bits down would silently change what their thresholds mean.
- depth: 16-bit gray, millimetres (0 = no depth), in any of those formats.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import PurePath
from typing import Any

import numpy as np
import numpy.typing as npt

from .constants import ImageEncoding, ImageRole
from .errors import CellvisionError
from .images import ImagePayload, compressed_header, payload_from_array

__all__ = ["ImageFileError", "check_overlay_path", "encode_overlay", "payload_from_file"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_JPEG_SIGNATURE = b"\xff\xd8\xff"
_SIXTEEN_BIT_COLOUR = (
    "a 16-bit image; inspections on colour images take 8-bit gray or colour images "
    "(a 16-bit gray image is depth in millimetres: give it with --depth to a depth inspection)"
)


class ImageFileError(ValueError):
    """A file that cannot be sent as the image asked for; the message names the file."""


def payload_from_file(data: bytes, *, name: str, role: ImageRole) -> ImagePayload:
    """The payload for the bytes of the image file ``name`` in ``role`` (colour or depth).

    Raises :class:`ImageFileError` (naming ``name`` and the cause) for an empty file, one
    OpenCV cannot decode, or pixels the role does not take (see the module).
    """
    if not data:
        raise ImageFileError(f"{name}: the file is empty")
    if data.startswith(_PNG_SIGNATURE):
        return _compressed(data, ImageEncoding.PNG, name, role)
    if data.startswith(_JPEG_SIGNATURE):
        return _compressed(data, ImageEncoding.JPEG, name, role)
    return payload_from_array(_decoded(data, name, role), role=role)


def _compressed(data: bytes, encoding: ImageEncoding, name: str, role: ImageRole) -> ImagePayload:
    payload = ImagePayload(encoding, 0, 0, data, role)
    try:
        header = compressed_header(payload)
    except CellvisionError as exc:
        raise ImageFileError(f"{name}: {exc.message}") from None
    if role is ImageRole.DEPTH and (header.bits, header.channels) != (16, 1):
        raise ImageFileError(
            _not_depth(name, f"{header.channels} channel(s) of {header.bits} bits")
        )
    if role is not ImageRole.DEPTH and header.bits != 8:
        raise ImageFileError(f"{name}: {_SIXTEEN_BIT_COLOUR}")
    return payload


def _decoded(data: bytes, name: str, role: ImageRole) -> npt.NDArray[Any]:
    import cv2  # only for formats other than PNG and JPEG

    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:  # e.g. OpenCV's own pixel limits
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        raise ImageFileError(f"{name}: cannot decode: {lines[-1] if lines else exc}") from None
    if image is None:
        raise ImageFileError(f"{name}: not an image file OpenCV can read, or a damaged one")
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] in (2, 4):  # gray + alpha, BGR + alpha
        image = image[:, :, :1] if image.shape[2] == 2 else image[:, :, :3]
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    image = np.ascontiguousarray(image)
    if role is ImageRole.DEPTH:
        if image.dtype != np.uint16 or image.ndim != 2:
            channels = 1 if image.ndim == 2 else image.shape[2]
            raise ImageFileError(_not_depth(name, f"{channels} channel(s) of {image.dtype}"))
        return image
    if image.dtype == np.uint16:
        raise ImageFileError(f"{name}: {_SIXTEEN_BIT_COLOUR}")
    if image.dtype != np.uint8:
        raise ImageFileError(
            f"{name}: {image.dtype} pixels; inspections on colour images take 8-bit gray or "
            "colour images"
        )
    return image


def _not_depth(name: str, got: str) -> str:
    return f"{name}: a depth image must be 16-bit gray (millimetres); this one has {got}"


def check_overlay_path(path: str, *, folder_exists: Callable[[str], bool]) -> str:
    """The image extension of ``path`` (``".png"``), if an overlay can be written there.

    Raises :class:`ImageFileError` when OpenCV writes no image format with that extension, or
    when the folder ``path`` is in does not exist (``folder_exists(folder)`` says): no folder is
    created unasked.
    """
    import cv2

    suffix = PurePath(path).suffix.lower()
    if not suffix or not cv2.haveImageWriter("x" + suffix):
        what = f"the extension {suffix!r}" if suffix else "a file name without an extension"
        raise ImageFileError(
            f"--overlay {path}: cannot write an image with {what}; use .png (or .jpg, .bmp, "
            ".tif, .webp)"
        )
    folder = str(PurePath(path).parent)
    if not folder_exists(folder):
        raise ImageFileError(
            f"--overlay {path}: the folder {folder} does not exist (folders are not created)"
        )
    return suffix


def encode_overlay(image: npt.NDArray[Any], suffix: str) -> bytes:
    """An overlay image (BGR uint8) as the bytes of a ``suffix`` file (``".png"``)."""
    import cv2

    ok, buffer = cv2.imencode(suffix, image)
    if not ok:
        raise ImageFileError(f"OpenCV could not encode the overlay as {suffix}")
    return bytes(buffer.tobytes())
