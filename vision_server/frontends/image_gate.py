"""The image gate of uploaded files: a file is decoded only once its pixel count, and the size
of each pixel, are read from its header and fit the limit.

OpenCV's decoders allocate what a file's header asks for (and more: a tiled or floating-point
TIFF, an HDR or JPEG 2000 file took 2-5x the documented bound; a 249 KB TIFF +976 MiB). So the
gate admits only formats whose headers it reads itself, with the properties that keep the
decoded image within ``max_pixels`` x 3 bytes (8-bit colour; 16-bit gray for depth):

- PNG and JPEG: their headers (SPEC §4.3; :func:`protocol.compressed_header` decides them);
- BMP: width, height and bits per pixel (at most 32) from its info header;
- TIFF: the first image's width and length, in strips (no tiles: a tile may be larger than
  the image), 1 to 4 samples of 8 or 16 bits, unsigned integers (no floating point);
- PNM (PBM, PGM, PPM: ``P1`` to ``P6``): width, height and maximum value from its text header;
- WebP: the canvas of its ``VP8``, ``VP8L`` or ``VP8X`` chunk.

Anything else (HDR, JPEG 2000, AVIF, EXR, ...) is refused as BAD_IMAGE naming the formats
taken; a header that is damaged or too short to say is refused the same way.
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass

from protocol import BadImage, too_large_details
from protocol.errors import ImageTooLarge

ACCEPTED = "PNG, JPEG, BMP, TIFF (8 or 16 bits, in strips), PNM or WebP"

_TIFF_WIDTH, _TIFF_LENGTH = 256, 257
_TIFF_BITS, _TIFF_SAMPLES, _TIFF_SAMPLE_FORMAT = 258, 277, 339
_TIFF_TILE_WIDTH, _TIFF_TILE_LENGTH = 322, 323
_TIFF_BYTE, _TIFF_SHORT, _TIFF_LONG = 1, 3, 4
_TIFF_CODES = {_TIFF_BYTE: "B", _TIFF_SHORT: "H", _TIFF_LONG: "I"}
_PNM = re.compile(
    rb"P([1-6])(?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)(?:(?:\s+|#[^\n]*\n)+(\d+))?"
)


@dataclass(frozen=True)
class Header:
    """What a file's header says: its format, its size in pixels and bits per sample."""

    format: str
    width: int
    height: int
    bits: int = 8

    @property
    def pixels(self) -> int:
        return self.width * self.height


def check_upload(data: bytes, *, name: str, max_pixels: int | None) -> Header | None:
    """Admit an uploaded file for decoding, or raise BAD_IMAGE (a format or header the gate
    cannot read) or IMAGE_TOO_LARGE (more pixels than ``max_pixels``). None for PNG and JPEG,
    whose headers the payload decoder checks itself."""
    if data.startswith((b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff")):
        return None
    header = read_header(data, name)
    if max_pixels is not None and header.pixels > max_pixels:
        raise ImageTooLarge(
            f"{name} is {header.width}x{header.height} = {header.pixels} pixels, more than "
            f"the limit of {max_pixels}",
            details=too_large_details(header.width, header.height, max_pixels),
        )
    return header


def read_header(data: bytes, name: str) -> Header:
    """The header of a BMP, TIFF, PNM or WebP file; BAD_IMAGE for anything else."""
    try:
        if data.startswith(b"BM"):
            return _bmp(data, name)
        if data[:4] in (b"II*\x00", b"MM\x00*"):
            return _tiff(data, "<" if data[:2] == b"II" else ">", name)
        if data[:1] == b"P" and data[1:2] in b"123456":
            return _pnm(data, name)
        if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
            return _webp(data, name)
    except struct.error:
        raise BadImage(f"{name}: its header is cut short") from None
    raise BadImage(
        f"{name} is not a format whose size can be read before decoding it; send {ACCEPTED}"
    )


def _sane(header: Header, name: str) -> Header:
    if header.width <= 0 or header.height <= 0:
        raise BadImage(f"{name}: its header gives a size of {header.width}x{header.height}")
    return header


def _bmp(data: bytes, name: str) -> Header:
    info = struct.unpack_from("<I", data, 14)[0]
    if info == 12:  # OS/2 BITMAPCOREHEADER: 16-bit sizes
        width, height, _planes, bits = struct.unpack_from("<HHHH", data, 18)
    else:
        width, height, _planes, bits = struct.unpack_from("<iiHH", data, 18)
    if bits not in (1, 4, 8, 16, 24, 32):
        raise BadImage(f"{name}: a BMP of {bits} bits per pixel")
    return _sane(Header("BMP", abs(width), abs(height), min(bits, 8)), name)


def _tiff(data: bytes, order: str, name: str) -> Header:
    ifd = struct.unpack_from(f"{order}I", data, 4)[0]
    count = struct.unpack_from(f"{order}H", data, ifd)[0]
    tags: dict[int, tuple[int, int, bytes]] = {}
    for index in range(count):
        tag, kind, number, value = struct.unpack_from(f"{order}HHI4s", data, ifd + 2 + 12 * index)
        tags[tag] = (kind, number, value)
    if _TIFF_TILE_WIDTH in tags or _TIFF_TILE_LENGTH in tags:
        raise BadImage(f"{name}: a tiled TIFF; send it in strips ({ACCEPTED})")
    width = _tiff_values(tags, _TIFF_WIDTH, order, data, name)
    length = _tiff_values(tags, _TIFF_LENGTH, order, data, name)
    if not width or not length:
        raise BadImage(f"{name}: a TIFF without its width and length")
    samples = (_tiff_values(tags, _TIFF_SAMPLES, order, data, name) or [1])[0]
    formats = _tiff_values(tags, _TIFF_SAMPLE_FORMAT, order, data, name) or [1]
    bits = max(_tiff_values(tags, _TIFF_BITS, order, data, name) or [1])
    if any(f != 1 for f in formats):
        raise BadImage(f"{name}: a TIFF of floating-point or signed samples; send 8 or 16 bits")
    if not 1 <= samples <= 4 or bits not in (1, 8, 16):
        raise BadImage(f"{name}: a TIFF of {samples} samples of {bits} bits per pixel")
    return _sane(Header("TIFF", width[0], length[0], bits), name)


def _tiff_values(
    tags: dict[int, tuple[int, int, bytes]], tag: int, order: str, data: bytes, name: str
) -> list[int]:
    """A BYTE, SHORT or LONG tag's values (in the entry when they fit in its 4 bytes, else at
    the offset it holds); [] when the tag is absent. A tag of another type, or with more
    values than a pixel has samples, is refused: libtiff may read what the gate cannot, and
    a default assumed here (1 bit, unsigned) let a float TIFF through."""
    if tag not in tags:
        return []
    kind, number, value = tags[tag]
    if kind not in _TIFF_CODES or not 1 <= number <= 16:
        raise BadImage(f"{name}: a TIFF whose tag {tag} the gate cannot read (type {kind})")
    code = _TIFF_CODES[kind]
    if number * struct.calcsize(code) <= 4:
        return list(struct.unpack_from(f"{order}{number}{code}", value))
    offset = struct.unpack_from(f"{order}I", value)[0]
    return list(struct.unpack_from(f"{order}{number}{code}", data, offset))


def _pnm(data: bytes, name: str) -> Header:
    match = _PNM.match(data[:1024])
    if match is None:
        raise BadImage(f"{name}: a PNM header that cannot be read")
    kind, width, height = int(match[1]), int(match[2]), int(match[3])
    maxval = 1 if kind in (1, 4) else int(match[4] or 0)
    if not 1 <= maxval <= 65535:
        raise BadImage(f"{name}: a PNM with a maximum value of {maxval}")
    return _sane(Header("PNM", width, height, 16 if maxval > 255 else 8), name)


def _webp(data: bytes, name: str) -> Header:
    chunk = data[12:16]
    if chunk == b"VP8 ":
        if data[23:26] != b"\x9d\x01\x2a":
            raise BadImage(f"{name}: a WebP whose frame header cannot be read")
        width, height = struct.unpack_from("<HH", data, 26)
        return _sane(Header("WebP", width & 0x3FFF, height & 0x3FFF), name)
    if chunk == b"VP8L":
        if data[20:21] != b"\x2f":
            raise BadImage(f"{name}: a WebP whose lossless header cannot be read")
        bits = struct.unpack_from("<I", data, 21)[0]
        return _sane(Header("WebP", (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1), name)
    if chunk == b"VP8X":
        width = int.from_bytes(data[24:27], "little") + 1
        height = int.from_bytes(data[27:30], "little") + 1
        if len(data) < 30:
            raise struct.error
        return _sane(Header("WebP", width, height), name)
    raise BadImage(f"{name}: a WebP of an unknown kind ({chunk!r})")


__all__ = ["ACCEPTED", "Header", "check_upload", "read_header"]
