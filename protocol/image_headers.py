"""The size of a PNG or JPEG file, read from its header the way the decoder will read it.

A receiver must know how many pixels a compressed image holds *before* it decompresses it
(SPEC §4.3). The only size that matters is the one the decoder will allocate, so these parsers
walk the file as libpng and libjpeg(-turbo) do and refuse, with :class:`BadImage` naming the
cause, every file whose size they cannot establish or where the decoder could read it otherwise.
Nothing here decodes pixels.

How the decoders find the size (facts the parsers mirror):

- PNG (libpng, and OpenCV's own chunk reader in front of it): IHDR must be the first chunk,
  13 bytes; width and height are 1 … 2³¹−1. Chunks up to the first IDAT are
  read in order; an unknown *critical* chunk (upper-case first letter) is an error. APNG's
  ``acTL``/``fcTL`` make OpenCV decode frames into extra full-canvas buffers, so animated PNGs
  are refused.
- JPEG (libjpeg-turbo's ``jdmarker.c``): after ``FF D8`` the reader looks for the next marker by
  skipping any bytes that are not ``FF`` (it warns about "extraneous bytes" and carries on), then
  any number of ``FF`` fill bytes; ``FF 00`` is skipped as garbage too. Segments with a length are
  skipped by that length. The first SOF sets the size for good: a second SOF is an error
  (``JERR_SOF_DUPLICATE``), as is a height of 0 (a height defined later by a DNL marker is not
  supported), a scan before any SOF, or an unknown marker. Only SOF0–3 and SOF9–11 are decoded.
"""

from __future__ import annotations

from dataclasses import dataclass

from .errors import BadImage

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# OpenCV picks its decoder by these first bytes (its JPEG decoder claims FF D8 FF only), so the
# declared encoding is the decoder used: no other format OpenCV reads starts with either.
JPEG_SIGNATURE = b"\xff\xd8\xff"

_PNG_MAX_LENGTH = 2**31 - 1  # PNG's limit for sides and chunk lengths
# PNG colour type -> the bit depths the PNG specification allows for it.
_PNG_DEPTHS = {0: (1, 2, 4, 8, 16), 2: (8, 16), 3: (1, 2, 4, 8), 4: (8, 16), 6: (8, 16)}
_PNG_GRAY_TYPES = (0, 4)  # gray, gray + alpha: decoded as one channel (alpha dropped)
_PNG_CRITICAL = {b"IHDR", b"PLTE", b"IDAT", b"IEND"}
_PNG_ANIMATION = {b"acTL", b"fcTL", b"fdAT"}

# JPEG markers (ITU T.81 Table B.1).
_SOF_DECODED = {0xC0, 0xC1, 0xC2, 0xC3, 0xC9, 0xCA, 0xCB}  # what libjpeg-turbo 3 decodes
_SOF_HIERARCHICAL = {0xC5, 0xC6, 0xC7, 0xCD, 0xCE, 0xCF}  # differential: libjpeg refuses them
_SOI, _EOI, _SOS, _DNL = 0xD8, 0xD9, 0xDA, 0xDC
# Segments libjpeg reads or skips by their length: DHT, DAC, DQT, DRI, DNL (ignored), APPn, COM.
_SEGMENTS = {0xC4, 0xCC, 0xDB, 0xDD, _DNL, 0xFE} | set(range(0xE0, 0xF0))
_PARAMETERLESS = {0x01} | set(range(0xD0, 0xD8))  # TEM, RST0-7


@dataclass(frozen=True)
class ImageHeader:
    """What a decoder will produce for a compressed image, known before decoding it.

    ``channels`` (1 or 3) and ``bits`` (8 or 16 per sample) describe the array
    :func:`protocol.array_from_payload` returns: alpha is dropped, palettes and gray below
    8 bits are expanded to 8.
    """

    width: int
    height: int
    channels: int
    bits: int

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def decoded_bytes(self) -> int:
        """Size in bytes of the decoded array."""
        return self.pixels * self.channels * self.bits // 8


class _Unreadable(ValueError):
    """The header does not establish the size the decoder would use; the text says why."""


def png_header(data: bytes, *, request_id: int = 0) -> ImageHeader:
    """Read a PNG's IHDR and check the chunks before the first IDAT; BadImage names the cause."""
    try:
        return _png_header(data)
    except _Unreadable as exc:
        raise BadImage(f"png blob of {len(data)} bytes: {exc}", request_id=request_id) from None


def jpeg_header(data: bytes, *, request_id: int = 0) -> ImageHeader:
    """Find a JPEG's frame header (SOF) as libjpeg does; BadImage names the cause."""
    try:
        return _jpeg_header(data)
    except _Unreadable as exc:
        raise BadImage(f"jpeg blob of {len(data)} bytes: {exc}", request_id=request_id) from None


def _png_header(data: bytes) -> ImageHeader:
    if not data.startswith(PNG_SIGNATURE):
        raise _Unreadable("no PNG signature (89 50 4E 47 0D 0A 1A 0A)")
    position = len(PNG_SIGNATURE)
    header: ImageHeader | None = None
    while True:
        if position + 8 > len(data):
            raise _Unreadable("it ends before the first IDAT chunk")
        length = int.from_bytes(data[position : position + 4], "big")
        kind = data[position + 4 : position + 8]
        end = position + 12 + length  # length, type, data, CRC
        if not (kind.isascii() and kind.isalpha()):
            raise _Unreadable(f"the chunk at byte {position} has an invalid type {kind!r}")
        name = kind.decode()
        if length > _PNG_MAX_LENGTH:
            raise _Unreadable(f"chunk {name} at byte {position} declares {length} bytes")
        if end > len(data):
            raise _Unreadable(f"chunk {name} at byte {position} is truncated")
        if header is None:
            if kind != b"IHDR":
                raise _Unreadable(f"the first chunk is {name}; IHDR must come first")
            header = _ihdr(data[position + 8 : end - 4])
        elif kind == b"IHDR":
            raise _Unreadable("a second IHDR chunk makes the size ambiguous")
        elif kind in _PNG_ANIMATION:
            raise _Unreadable(f"{name} chunk: animated PNG (APNG) is not accepted")
        elif kind == b"IDAT":
            return header
        elif kind == b"IEND":
            raise _Unreadable("IEND comes before any IDAT chunk: there is no image data")
        elif name[0].isupper() and kind not in _PNG_CRITICAL:
            raise _Unreadable(f"unknown critical chunk {name}")
        position = end


def _ihdr(body: bytes) -> ImageHeader:
    """IHDR's 13 bytes of data. Its CRC is left to libpng, which refuses a bad one while reading
    the header, before it allocates anything: a bad CRC hides no size."""
    if len(body) != 13:
        raise _Unreadable(f"IHDR holds {len(body)} bytes, not 13")
    width = int.from_bytes(body[0:4], "big")
    height = int.from_bytes(body[4:8], "big")
    depth, colour, compression, filtering, interlace = body[8:13]
    if not (0 < width <= _PNG_MAX_LENGTH and 0 < height <= _PNG_MAX_LENGTH):
        raise _Unreadable(f"IHDR announces {width}x{height}: each side must be 1 .. 2**31-1")
    if depth not in _PNG_DEPTHS.get(colour, ()):
        raise _Unreadable(f"IHDR: bit depth {depth} with colour type {colour} is not valid PNG")
    if compression or filtering or interlace not in (0, 1):
        raise _Unreadable(
            f"IHDR: compression {compression}, filter {filtering}, interlace {interlace} "
            "are not valid PNG"
        )
    channels = 1 if colour in _PNG_GRAY_TYPES else 3
    return ImageHeader(width, height, channels, 16 if depth == 16 else 8)


def _jpeg_header(data: bytes) -> ImageHeader:
    if not data.startswith(JPEG_SIGNATURE):
        raise _Unreadable("no JPEG signature (FF D8 FF)")
    position = 2
    header: ImageHeader | None = None
    while True:
        marker, at, position = _next_marker(data, position)
        if marker == _SOS:
            if header is None:
                raise _Unreadable(f"a scan (SOS) at byte {at} comes before any frame header")
            return header
        if marker in _PARAMETERLESS:
            continue
        if marker == _SOI:
            raise _Unreadable(f"a second start-of-image marker at byte {at}")
        if marker == _EOI:
            raise _Unreadable(f"the image ends (EOI) at byte {at} before any scan")
        if not (marker in _SOF_DECODED or marker in _SOF_HIERARCHICAL or marker in _SEGMENTS):
            raise _Unreadable(f"unknown marker FF {marker:02X} at byte {at}")
        if position + 2 > len(data):
            raise _Unreadable(f"the segment of marker FF {marker:02X} at byte {at} is truncated")
        length = int.from_bytes(data[position : position + 2], "big")
        end = position + length
        if length < 2 or end > len(data):
            raise _Unreadable(
                f"marker FF {marker:02X} at byte {at} declares a {length}-byte segment, "
                f"{len(data) - position} bytes remain"
            )
        if marker in _SOF_DECODED or marker in _SOF_HIERARCHICAL:
            if header is not None:
                raise _Unreadable(f"a second frame header (SOF) at byte {at}: size ambiguous")
            header = _sof(marker, data[position + 2 : end], at)
        position = end


def _next_marker(data: bytes, position: int) -> tuple[int, int, int]:
    """(marker code, offset of its FF, offset after it), found as libjpeg's ``next_marker``:
    bytes other than FF are skipped, then FF fill bytes; FF 00 is skipped as garbage."""
    while True:
        start = data.find(b"\xff", position)
        if start < 0:
            raise _Unreadable("it ends before a frame header and scan were found")
        code = start + 1
        while code < len(data) and data[code] == 0xFF:
            code += 1
        if code >= len(data):
            raise _Unreadable("it ends before a frame header and scan were found")
        if data[code] != 0x00:
            return data[code], code - 1, code + 1
        position = code + 1


def _sof(marker: int, body: bytes, at: int) -> ImageHeader:
    """A frame header's parameters (after the length): P, Y, X, Nf, then 3 bytes per component."""
    if len(body) < 6:
        raise _Unreadable(f"the frame header at byte {at} is {len(body)} bytes, too short")
    precision = body[0]
    height = int.from_bytes(body[1:3], "big")
    width = int.from_bytes(body[3:5], "big")
    components = body[5]
    if marker in _SOF_HIERARCHICAL:
        raise _Unreadable(
            f"frame header SOF{marker - 0xC0} ({width}x{height}) at byte {at}: hierarchical "
            "(differential) JPEG is not supported"
        )
    if height == 0:
        raise _Unreadable(
            f"the frame header at byte {at} gives height 0 (defined later by a DNL marker): "
            "the size must be known before decoding"
        )
    if width == 0:
        raise _Unreadable(f"the frame header at byte {at} gives width 0")
    if len(body) != 6 + 3 * components:
        raise _Unreadable(
            f"the frame header at byte {at} has {len(body)} bytes of parameters for "
            f"{components} components (needs {6 + 3 * components})"
        )
    if precision != 8:
        raise _Unreadable(f"{precision}-bit samples: only 8-bit JPEG is accepted")
    if components not in (1, 3):
        raise _Unreadable(f"{components} components: only gray (1) or colour (3) is accepted")
    return ImageHeader(width, height, components, 8)
