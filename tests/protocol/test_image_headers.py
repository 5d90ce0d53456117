"""The size of a PNG/JPEG is known before it is decoded, or the image is refused (SPEC §4.3).

Each trick that can hide or misstate a size is one case. Where the decoder accepts a file, the
parser must find the size the decoder finds (checked against OpenCV on small files).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol import ImageEncoding, ImagePayload, array_from_payload, payload_from_array
from protocol.errors import BadImage, ImageTooLarge
from protocol.image_headers import ImageHeader, jpeg_header, png_header
from protocol.images import compressed_header
from tests.helpers.hostile_images import (
    ihdr,
    insert_before_sof,
    jpeg_segments,
    png,
    png_chunk,
    real_jpeg,
    sof_index,
    stray_byte_bomb,
    with_sof,
)

ROOT = Path(__file__).resolve().parents[2]
LIMIT = 4096 * 4096


def _decode(encoding: str, data: bytes, max_pixels: int = LIMIT) -> np.ndarray:
    return array_from_payload(ImagePayload(encoding, 0, 0, data), max_pixels=max_pixels)


def _opencv_shape(data: bytes) -> tuple[int, ...] | None:
    """What OpenCV alone makes of a (small) file."""
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return None if decoded is None else tuple(decoded.shape[:2])


# ------------------------------------------------------------------------------ PNG: accepted


@pytest.mark.parametrize(
    ("shape", "dtype", "channels"),
    [
        ((5, 7), np.uint8, 1),
        ((5, 7, 3), np.uint8, 3),
        ((5, 7), np.uint16, 1),
        ((5, 7, 3), np.uint16, 3),
        ((5, 7, 4), np.uint8, 3),  # alpha is dropped while decoding
        ((5, 7, 4), np.uint16, 3),
    ],
    ids=["gray8", "bgr8", "gray16", "bgr16", "bgra8", "bgra16"],
)
def test_png_header_matches_the_decoded_array(
    shape: tuple[int, ...], dtype: type, channels: int
) -> None:
    image = (np.arange(np.prod(shape)) % 250).astype(dtype).reshape(shape)
    data = cv2.imencode(".png", image)[1].tobytes()
    bits = 16 if dtype is np.uint16 else 8
    assert png_header(data) == ImageHeader(7, 5, channels, bits)
    decoded = _decode("png", data)
    assert decoded.shape == (5, 7) if channels == 1 else (5, 7, 3)
    assert decoded.dtype == dtype
    np.testing.assert_array_equal(decoded, image if channels == 1 else image[:, :, :3])


def test_png_interlaced_palette_and_low_bit_depths_decode_to_their_header() -> None:
    # 4x2, 1-bit gray, Adam7 interlaced; and 2-bit palette: both expand to 8 bits.
    rows = zlib.compress(b"".join(b"\x00\xa0" for _ in range(4)))
    interlaced = b"\x89PNG\r\n\x1a\n" + ihdr(4, 2, 1, 0, interlace=1)
    interlaced += png_chunk(b"IDAT", rows) + png_chunk(b"IEND", b"")
    assert png_header(interlaced) == ImageHeader(4, 2, 1, 8)
    palette = png(
        4,
        2,
        png_chunk(b"PLTE", bytes(range(12))),
        png_chunk(b"IDAT", zlib.compress(b"\x00\x1b" * 2)),
        png_chunk(b"IEND", b""),
        depth=2,
        colour=3,
    )
    assert png_header(palette) == ImageHeader(4, 2, 3, 8)
    assert _decode("png", palette).shape == (2, 4, 3)


# ------------------------------------------------------------------------------ PNG: refused


def _bomb_png(*before_idat: bytes) -> bytes:
    idat = png_chunk(b"IDAT", zlib.compress(b"\x00" * 9))
    return png(100_000, 100_000, *before_idat, idat, png_chunk(b"IEND", b""))


def test_png_bomb_is_too_large_before_decoding() -> None:
    with pytest.raises(ImageTooLarge) as info:
        _decode("png", _bomb_png(png_chunk(b"tEXt", b"k\x00v")))
    assert info.value.details == {
        "pixels": 10**10,
        "width": 100_000,
        "height": 100_000,
        "max_pixels": LIMIT,
    }


PNG_SIG = b"\x89PNG\r\n\x1a\n"
SMALL_IDAT = png_chunk(b"IDAT", zlib.compress(b"\x00" * 9))


@pytest.mark.parametrize(
    ("data", "cause"),
    [
        # IHDR hidden behind another chunk: libpng refuses, and so do we (no "unknown size").
        (PNG_SIG + png_chunk(b"tEXt", b"a\x00b") + ihdr(99999, 99999) + SMALL_IDAT, "IHDR must"),
        (PNG_SIG + png_chunk(b"IHDR", bytes(12)) + SMALL_IDAT, "not 13"),
        (PNG_SIG + ihdr(2, 2) + ihdr(99999, 99999) + SMALL_IDAT, "second IHDR"),
        (_bomb_png(png_chunk(b"acTL", bytes(8))), "animated PNG"),
        (png(2, 2, png_chunk(b"fcTL", bytes(26)), SMALL_IDAT), "animated PNG"),
        (png(2, 2, png_chunk(b"CgBI", bytes(4)), SMALL_IDAT), "unknown critical chunk CgBI"),
        (png(2, 2, png_chunk(b"IEND", b"")), "IEND comes before any IDAT"),
        (png(2, 2, png_chunk(b"tEXt", b"a\x00b")), "ends before the first IDAT"),
        (png(2, 2, png_chunk(b"tEXt", b"a\x00b"))[:-3], "truncated"),
        (png(2, 2, b"\x00\x00\x00\x01t\x00Xt" + bytes(5), SMALL_IDAT), "invalid type"),
        (png(2, 2, b"\x90\x00\x00\x00tEXt", SMALL_IDAT), "declares"),
        (png(0, 5), "each side"),
        (png(5, 0), "each side"),
        (png(2**31, 1), "each side"),
        (png(2, 2, depth=16, colour=3), "bit depth 16 with colour type 3"),
        (png(2, 2, depth=8, colour=5), "colour type 5"),
        (PNG_SIG + ihdr(2, 2, interlace=2) + SMALL_IDAT, "interlace 2"),
        (PNG_SIG[:-1] + ihdr(2, 2) + SMALL_IDAT, "no PNG signature"),
        (PNG_SIG, "ends before"),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_png_whose_size_is_not_established_is_refused(data: bytes, cause: str) -> None:
    with pytest.raises(BadImage, match=cause) as info:
        _decode("png", data)
    assert "png blob of" in str(info.value)


def test_png_ihdr_crc_is_left_to_libpng() -> None:
    # A bad IHDR CRC hides no size: the announced one is checked, the decoder refuses the rest.
    data = bytearray(png(3, 3))
    data[29] ^= 0xFF
    assert png_header(bytes(data)).pixels == 9
    bomb = bytearray(_bomb_png())
    bomb[29] ^= 0xFF
    with pytest.raises(ImageTooLarge):
        _decode("png", bytes(bomb))


# ----------------------------------------------------------------------------- JPEG: accepted


@pytest.mark.parametrize(
    ("colour", "options"),
    [
        (False, {}),
        (True, {}),
        (True, {"PROGRESSIVE": 1}),
        (False, {"PROGRESSIVE": 1}),
        (True, {"RST_INTERVAL": 1}),
        (True, {"OPTIMIZE": 1}),
        (True, {"SAMPLING_FACTOR": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_411}),
    ],
    ids=["gray", "colour", "progressive", "progressive-gray", "restarts", "optimized", "411"],
)
def test_jpeg_header_matches_the_decoded_array(colour: bool, options: dict[str, int]) -> None:
    data = real_jpeg(21, 13, colour=colour, **options)
    header = jpeg_header(data)
    assert header == ImageHeader(21, 13, 3 if colour else 1, 8)
    assert _decode("jpeg", data).shape == ((13, 21, 3) if colour else (13, 21))


APP1_EXIF = b"\xff\xe1" + (2 + 6 + 40).to_bytes(2, "big") + b"Exif\x00\x00" + bytes(40)
COM = b"\xff\xfe\x00\x07hello"


@pytest.mark.parametrize(
    "junk",
    [
        b"\x00",  # the issue's stray byte
        b"\x12\x34\x56",  # several stray bytes
        b"\xff\xff\xff\xff",  # fill bytes before the marker
        b"\xff\x00",  # a stuffed zero outside entropy data: skipped as garbage
        b"\x00\xff\x00abc\xff\xff",
        APP1_EXIF + COM,  # EXIF and a comment before the frame header
        b"\xff\xd0\xff\x01",  # parameterless markers (RST0, TEM)
        b"\xff\xdc\x00\x04\x00\x08",  # a DNL before SOF: libjpeg skips it
    ],
    ids=["stray", "strays", "fill", "ff00", "mixed", "exif+com", "rst-tem", "dnl-skipped"],
)
def test_jpeg_garbage_between_segments_is_read_as_libjpeg_does(junk: bytes) -> None:
    data = insert_before_sof(real_jpeg(21, 13), junk)
    assert jpeg_header(data).pixels == 21 * 13
    assert _opencv_shape(data) == (13, 21)  # the decoder agrees
    assert _decode("jpeg", data).shape == (13, 21)


@pytest.mark.parametrize("junk", [b"\x00", b"\xab\xcd", b"\xff\xff", b"\xff\x00", APP1_EXIF])
def test_jpeg_bomb_behind_garbage_is_too_large(junk: bytes) -> None:
    # The issue: a ~300-byte JPEG with a stray byte before a SOF announcing 65000 x 65000.
    data = insert_before_sof(with_sof(real_jpeg(), width=65000, height=65000), junk)
    assert len(data) < 500
    with pytest.raises(ImageTooLarge) as info:
        _decode("jpeg", data)
    assert info.value.details == {
        "pixels": 65000 * 65000,
        "width": 65000,
        "height": 65000,
        "max_pixels": LIMIT,
    }


def test_the_issues_bomb_is_too_large() -> None:
    with pytest.raises(ImageTooLarge):
        _decode("jpeg", stray_byte_bomb())


@pytest.mark.parametrize("marker", [0xC0, 0xC1, 0xC2, 0xC3, 0xC9, 0xCA, 0xCB])
def test_every_decodable_sof_kind_gives_its_size(marker: int) -> None:
    # baseline, extended, progressive, lossless, and their arithmetic-coded variants
    data = with_sof(real_jpeg(), width=5000, height=4000, marker=marker)
    assert jpeg_header(data).pixels == 20_000_000
    with pytest.raises(ImageTooLarge):
        _decode("jpeg", data)


def test_the_size_just_under_the_limit_per_side_but_over_in_product_is_too_large() -> None:
    data = with_sof(real_jpeg(), width=4095, height=65000)
    with pytest.raises(ImageTooLarge):
        _decode("jpeg", data, max_pixels=LIMIT)


# ------------------------------------------------------------------------------ JPEG: refused


def _two_sofs() -> bytes:
    segments, rest = jpeg_segments(real_jpeg())
    index = sof_index(segments)
    big = with_sof(real_jpeg(), width=60000, height=60000)
    second = jpeg_segments(big)[0][index]
    return (
        b"\xff\xd8"
        + b"".join(segments[: index + 1])
        + second
        + b"".join(segments[index + 1 :])
        + rest
    )


def _sos_first() -> bytes:
    segments, rest = jpeg_segments(real_jpeg())
    return b"\xff\xd8" + rest


@pytest.mark.parametrize(
    ("data", "cause"),
    [
        (_two_sofs(), "second frame header"),
        (with_sof(real_jpeg(), height=0), "DNL"),
        (with_sof(real_jpeg(), width=0), "width 0"),
        (with_sof(real_jpeg(), marker=0xC5), "hierarchical"),
        (with_sof(real_jpeg(), marker=0xCE), "hierarchical"),
        (with_sof(real_jpeg(), marker=0xC8), "unknown marker FF C8"),
        (with_sof(real_jpeg(), precision=12), "12-bit"),
        (with_sof(real_jpeg(), precision=16, marker=0xC3), "16-bit"),
        (insert_before_sof(real_jpeg(), b"\xff\xf0\x00\x02"), "unknown marker FF F0"),
        (insert_before_sof(real_jpeg(), b"\xff\xd8"), "second start-of-image"),
        (insert_before_sof(real_jpeg(), b"\xff\xd9"), "ends \\(EOI\\)"),
        (insert_before_sof(real_jpeg(), b"\xff\xe1\x00\x01"), "1-byte segment"),
        (insert_before_sof(real_jpeg(), b"\xff\xfe\xff\xff"), "65535-byte segment"),
        (_sos_first(), "before any frame header"),
        (real_jpeg()[:200], "ends before|truncated|segment"),
        (b"\xff\xd8\xff", "ends before"),
        (b"\xff\xd8\x00\xff\xc0" + bytes(20), "no JPEG signature"),
        (b"\xff\xd8\xff\xc0\x00\x0b\x08\x00\x10\x00\x10\x01\x01\x11\x00", "ends before"),
        (b"\xff\xd8\xff\xc0\x00\x11\x08\x00\x10\x00\x10\x01" + bytes(20), "for 1 components"),
    ],
    ids=lambda value: value if isinstance(value, str) else "",
)
def test_jpeg_whose_size_is_not_established_is_refused(data: bytes, cause: str) -> None:
    with pytest.raises(BadImage, match=cause) as info:
        _decode("jpeg", data)
    assert "jpeg blob of" in str(info.value)


def test_four_component_jpeg_is_refused() -> None:
    segments, rest = jpeg_segments(real_jpeg(colour=True))
    index = sof_index(segments)
    sof = segments[index]
    four = sof[:2] + (len(sof) - 2 + 3).to_bytes(2, "big") + sof[4:9] + b"\x04" + sof[10:]
    four += b"\x04\x11\x00"
    data = b"\xff\xd8" + b"".join(segments[:index]) + four + b"".join(segments[index + 1 :]) + rest
    with pytest.raises(BadImage, match="4 components"):
        _decode("jpeg", data)


# ------------------------------------------------------------------- other formats, same bytes


def _other_formats() -> dict[str, bytes]:
    image = np.full((8, 8, 3), 77, np.uint8)
    blobs = {}
    for ext in (".tiff", ".webp", ".bmp", ".pgm", ".ppm", ".pfm", ".hdr", ".jp2", ".ras", ".gif"):
        source = image.astype(np.float32) / 255 if ext in (".pfm", ".hdr") else image
        if ext == ".pgm":
            source = image[:, :, 0]
        ok, buf = cv2.imencode(ext, source)
        if ok:
            blobs[ext] = buf.tobytes()
    return blobs


@pytest.mark.parametrize("encoding", ["png", "jpeg"])
def test_no_other_format_opencv_reads_passes_as_png_or_jpeg(encoding: str) -> None:
    blobs = _other_formats()
    assert len(blobs) >= 8, sorted(blobs)
    for ext, blob in blobs.items():
        assert _opencv_shape(blob) is not None, ext  # OpenCV would decode it, by content...
        with pytest.raises(BadImage, match="no (PNG|JPEG) signature"):
            _decode(encoding, blob)  # ...but not under a png/jpeg label
        # Nor glued behind the other signature: the first bytes pick OpenCV's decoder.
        with pytest.raises(BadImage):
            _decode(
                encoding, (b"\x89PNG\r\n\x1a\n" if encoding == "jpeg" else b"\xff\xd8\xff") + blob
            )


def test_compressed_header_never_answers_unknown() -> None:
    payload = payload_from_array(np.zeros((3, 4), np.uint8), encoding=ImageEncoding.PNG)
    assert compressed_header(payload) == ImageHeader(4, 3, 1, 8)
    with pytest.raises(BadImage):
        compressed_header(ImagePayload("png", 0, 0, payload.data[:20]))


# ------------------------------------------------------------------- parser and decoder agree

FUZZ = """
import json, random, sys
import cv2, numpy as np
from protocol.image_headers import jpeg_header, png_header
from protocol.errors import BadImage
from tests.helpers.hostile_images import real_jpeg

seeds = [real_jpeg(16, 8), real_jpeg(9, 7, colour=True, PROGRESSIVE=1),
         cv2.imencode(".png", np.arange(48, dtype=np.uint8).reshape(6, 8))[1].tobytes(),
         cv2.imencode(".png", np.zeros((5, 3, 4), np.uint16))[1].tobytes()]
rng = random.Random(1234)
disagreements, accepted = [], 0
for round in range(int(sys.argv[1])):
    seed = bytearray(rng.choice(seeds))
    for _ in range(rng.randint(1, 3)):
        at = rng.randrange(len(seed))
        action = rng.random()
        if action < 0.5:
            seed[at] = rng.randrange(256)
        elif action < 0.75:
            seed[at:at] = bytes([rng.choice([0, 0xFF, rng.randrange(256)])])
        else:
            del seed[at]
    data = bytes(seed)
    parse = png_header if data[:1] == b"\\x89" else jpeg_header
    try:
        header = parse(data)
    except BadImage:
        header = None
    # OpenCV alone, fenced (OPENCV_IO_MAX_IMAGE_PIXELS) so that a disagreement cannot hurt.
    try:
        decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        decoded = None
    if header is not None:
        accepted += 1
    if decoded is not None and header is not None:
        if decoded.shape[:2] != (header.height, header.width):
            disagreements.append([data.hex(), decoded.shape[:2], [header.width, header.height]])
print(json.dumps({"accepted": accepted, "disagreements": disagreements}))
"""


def test_parser_and_opencv_agree_on_the_size_of_mutated_files() -> None:
    # In a child process whose OpenCV refuses more than 4096 pixels: a mutated header that the
    # decoder read as huge must not take this machine's memory.
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENCV_IO_MAX_IMAGE_PIXELS": "4096"}
    run = subprocess.run(
        [sys.executable, "-c", FUZZ, "800"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    report = json.loads(run.stdout.splitlines()[-1])
    assert report["accepted"] > 200  # the mutations left many files readable
    assert report["disagreements"] == []


def test_a_jpeg_that_announces_a_huge_image_and_ends_before_its_scan_is_bad_image() -> None:
    """SPEC §4.3: the size counts only once the file is shown to reach its scan; a file that
    ends before it is BAD_IMAGE whatever its SOF announces (it could never be decoded)."""
    whole = with_sof(real_jpeg(), width=65000, height=65000)
    cut = whole[: whole.index(b"\xff\xda")]  # everything before the scan (SOS)
    with pytest.raises(BadImage, match="ends before"):
        _decode("jpeg", cut)
    with pytest.raises(ImageTooLarge):  # the same header with its scan: too large
        _decode("jpeg", whole)
