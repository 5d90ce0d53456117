"""Images uploaded to the console's try panel: any format OpenCV reads, as `vision-server run`.

PNG and JPEG go to the service as they are (their headers are checked against the pixel limit
before decoding, :func:`decode_payloads`); any other format (BMP, TIFF, WebP, PNM, ...) is
decoded into the raw payload the service takes (:func:`protocol.image_files.payload_from_file`).
For BMP and TIFF the size in the header is checked against the limit before decoding; for the
rest OpenCV's own limit, tied to ``max_image_pixels`` (:mod:`vision_server.process.decoder_limits`),
stops the decoder before it allocates. Everything runs in the service's worker (decoding is CPU
work), once the inspection is known.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

from protocol import BadImage, ImageRole
from protocol.errors import ImageTooLarge
from protocol.image_files import ImageFileError, payload_from_file

from ..service import ImageNeeds, Images
from .images import decode_payloads

__all__ = ["header_size", "upload_loader"]

UPLOAD_NAME = "the uploaded file"

_TIFF_WIDTH, _TIFF_LENGTH = 256, 257
_TIFF_SHORT, _TIFF_LONG = 3, 4


def upload_loader(data: bytes) -> Callable[[ImageNeeds], Images]:
    """A loader for an uploaded image file; BAD_IMAGE or IMAGE_TOO_LARGE naming the cause."""
    if not data:
        raise BadImage(f"{UPLOAD_NAME} is empty")

    def load(needs: ImageNeeds) -> Images:
        size = header_size(data)
        if size is not None and needs.max_pixels is not None:
            width, height = size
            if width * height > needs.max_pixels:
                raise ImageTooLarge(
                    f"{UPLOAD_NAME} is {width}x{height} = {width * height} pixels, more than "
                    f"the limit of {needs.max_pixels}",
                    details={"pixels": width * height, "max_pixels": needs.max_pixels},
                )
        try:
            payload = payload_from_file(data, name=UPLOAD_NAME, role=ImageRole.COLOR)
        except ImageFileError as exc:
            raise BadImage(str(exc)) from None
        return decode_payloads([payload], needs)

    return load


def header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) in pixels from a BMP or TIFF header, None for other formats or a header
    too short or damaged to say (the decoder then decides)."""
    try:
        if data.startswith(b"BM") and len(data) >= 26:
            header_bytes = struct.unpack_from("<I", data, 14)[0]
            if header_bytes == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
                width, height = struct.unpack_from("<HH", data, 18)
            else:
                width, height = struct.unpack_from("<ii", data, 18)
            return abs(width), abs(height)  # a negative height is a top-down bitmap
        if data[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff_size(data, "<" if data[:2] == b"II" else ">")
    except struct.error:
        return None
    return None


def _tiff_size(data: bytes, order: str) -> tuple[int, int] | None:
    """The first image's ImageWidth and ImageLength tags (classic TIFF)."""
    ifd = struct.unpack_from(f"{order}I", data, 4)[0]
    count = struct.unpack_from(f"{order}H", data, ifd)[0]
    found: dict[int, int] = {}
    for index in range(count):
        tag, kind, _, value = struct.unpack_from(f"{order}HHI4s", data, ifd + 2 + 12 * index)
        if tag in (_TIFF_WIDTH, _TIFF_LENGTH) and kind in (_TIFF_SHORT, _TIFF_LONG):
            fmt = order + ("H" if kind == _TIFF_SHORT else "I")
            found[tag] = struct.unpack_from(fmt, value)[0]
    if _TIFF_WIDTH in found and _TIFF_LENGTH in found:
        return found[_TIFF_WIDTH], found[_TIFF_LENGTH]
    return None
