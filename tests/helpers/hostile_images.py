"""Hand-built PNG and JPEG files for the pixel-limit tests: well-formed ones, and ones that hide
or misstate their size (SPEC §4.3). Built from OpenCV's own small files, re-assembled."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

# -------------------------------------------------------------------------------------- PNG


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def ihdr(width: int, height: int, depth: int = 8, colour: int = 0, interlace: int = 0) -> bytes:
    return png_chunk(
        b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    )


def png(width: int, height: int, *chunks: bytes, depth: int = 8, colour: int = 0) -> bytes:
    """A PNG whose IHDR says width x height, then ``chunks`` (default: a tiny IDAT, IEND)."""
    body = chunks or (png_chunk(b"IDAT", zlib.compress(b"\x00" * 9)), png_chunk(b"IEND", b""))
    return b"\x89PNG\r\n\x1a\n" + ihdr(width, height, depth, colour) + b"".join(body)


def png_chunks(data: bytes) -> list[bytes]:
    """A real PNG split into its chunks (each with length and CRC), signature dropped."""
    chunks, position = [], 8
    while position < len(data):
        length = int.from_bytes(data[position : position + 4], "big")
        chunks.append(data[position : position + 12 + length])
        position += 12 + length
    return chunks


# ------------------------------------------------------------------------------------- JPEG


def real_jpeg(width: int = 16, height: int = 8, *, colour: bool = False, **options: int) -> bytes:
    """A JPEG from OpenCV; ``options``: IMWRITE_JPEG_* names without the prefix, e.g.
    ``PROGRESSIVE=1``, ``RST_INTERVAL=1``."""
    rng = np.random.default_rng(width * 1000 + height)
    shape = (height, width, 3) if colour else (height, width)
    image = rng.integers(0, 255, shape, dtype=np.uint8)
    params = [cv2.IMWRITE_JPEG_QUALITY, 90]
    for name, value in options.items():
        params += [getattr(cv2, f"IMWRITE_JPEG_{name}"), value]
    ok, buf = cv2.imencode(".jpg", image, params)
    assert ok
    return bytes(buf.tobytes())


def jpeg_segments(data: bytes) -> tuple[list[bytes], bytes]:
    """A well-formed JPEG as (segments from after SOI up to SOS, each with its marker; the rest
    from SOS on)."""
    segments, position = [], 2
    while data[position + 1] != 0xDA:
        length = int.from_bytes(data[position + 2 : position + 4], "big")
        segments.append(data[position : position + 2 + length])
        position += 2 + length
    return segments, data[position:]


def sof_index(segments: list[bytes]) -> int:
    return next(i for i, s in enumerate(segments) if 0xC0 <= s[1] <= 0xCF and s[1] != 0xC4)


def with_sof(
    data: bytes,
    *,
    width: int | None = None,
    height: int | None = None,
    marker: int | None = None,
    precision: int | None = None,
) -> bytes:
    """``data`` with its frame header changed: size, SOF kind, sample precision."""
    segments, rest = jpeg_segments(data)
    index = sof_index(segments)
    sof = bytearray(segments[index])
    if marker is not None:
        sof[1] = marker
    if precision is not None:
        sof[4] = precision
    if height is not None:
        sof[5:7] = height.to_bytes(2, "big")
    if width is not None:
        sof[7:9] = width.to_bytes(2, "big")
    segments[index] = bytes(sof)
    return b"\xff\xd8" + b"".join(segments) + rest


def insert_before_sof(data: bytes, junk: bytes) -> bytes:
    segments, rest = jpeg_segments(data)
    index = sof_index(segments)
    return b"\xff\xd8" + b"".join(segments[:index]) + junk + b"".join(segments[index:]) + rest


def stray_byte_bomb(width: int = 65000, height: int = 65000) -> bytes:
    """The issue's attack: a small JPEG, one stray byte before a SOF that announces
    width x height (the old scanner gave up at the stray byte and decoded unchecked)."""
    return insert_before_sof(with_sof(real_jpeg(), width=width, height=height), b"\x00")
