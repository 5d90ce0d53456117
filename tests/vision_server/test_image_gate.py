"""The image gate of uploaded files (vision_server/frontends/image_gate.py): a file is decoded
only when its header gives its size and sample size, within the limit; formats that hide them
are refused before any decoder runs. Files made by OpenCV's own encoders and by hand; the
console tests send them as a browser would."""

from __future__ import annotations

import struct
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from console_server import Browserless, console_server

from protocol import BadImage
from protocol.errors import ImageTooLarge
from vision_server.frontends.image_gate import check_upload, read_header

GRAY = np.tile(np.arange(64, dtype=np.uint8)[None, :] * 3, (48, 1))
COLOUR = np.dstack([GRAY, GRAY // 2, 255 - GRAY])


def encoded(suffix: str, image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(suffix, image)
    assert ok, suffix
    return data.tobytes()


def tiff(tags: list[tuple[int, int, int]], *, order: str = "<") -> bytes:
    """A classic TIFF of one IFD whose SHORT/LONG tags are ``(tag, type, value)``."""
    magic = b"II*\x00" if order == "<" else b"MM\x00*"
    ifd = struct.pack(f"{order}H", len(tags))
    for tag, kind, value in sorted(tags):
        packed = struct.pack(f"{order}H", value) + b"\0\0" if kind == 3 else None
        packed = packed or struct.pack(f"{order}I", value)
        ifd += struct.pack(f"{order}HHI", tag, kind, 1) + packed
    return magic + struct.pack(f"{order}I", 8) + ifd + b"\0\0\0\0"


@pytest.mark.parametrize(
    ("suffix", "image", "fmt", "bits"),
    [
        (".bmp", COLOUR, "BMP", 8),
        (".tiff", COLOUR, "TIFF", 8),
        (".tiff", GRAY.astype(np.uint16) * 200, "TIFF", 16),
        (".pgm", GRAY, "PNM", 8),
        (".ppm", COLOUR, "PNM", 8),
        (".pgm", GRAY.astype(np.uint16) * 200, "PNM", 16),
        (".webp", COLOUR, "WebP", 8),
    ],
)
def test_the_gate_reads_the_size_of_every_format_it_takes(
    suffix: str, image: np.ndarray, fmt: str, bits: int
) -> None:
    header = read_header(encoded(suffix, image), "f")
    assert (header.format, header.width, header.height, header.bits) == (fmt, 64, 48, bits)


def test_lossless_and_extended_webp_are_read_too() -> None:
    ok, data = cv2.imencode(".webp", COLOUR, [cv2.IMWRITE_WEBP_QUALITY, 101])
    assert ok
    lossless = data.tobytes()
    assert lossless[12:16] == b"VP8L"
    assert (read_header(lossless, "f").width, read_header(lossless, "f").height) == (64, 48)
    extended = (
        b"RIFF\0\0\0\0WEBPVP8X"
        + b"\x0a\0\0\0"
        + b"\x10\0\0\0"
        + ((5000 - 1).to_bytes(3, "little") + (4000 - 1).to_bytes(3, "little"))
    )
    assert read_header(extended, "f").pixels == 5000 * 4000


@pytest.mark.parametrize(
    ("data", "cause"),
    [
        (encoded(".hdr", COLOUR.astype(np.float32) / 255), "not a format whose size"),
        (encoded(".tiff", COLOUR.astype(np.float32)), "floating-point"),
        (tiff([(256, 4, 64), (257, 4, 48), (322, 3, 16), (323, 3, 16)]), "tiled TIFF"),
        (tiff([(256, 4, 64), (257, 4, 48), (258, 3, 32)]), "of 32 bits"),
        # BYTE-typed tags that libtiff reads: a float TIFF must not pass as the defaults
        (tiff([(256, 4, 64), (257, 4, 48), (258, 1, 32), (339, 1, 3)]), "floating-point"),
        (tiff([(256, 4, 64), (257, 4, 48), (258, 2, 32)]), "tag 258 the gate cannot read"),
        (tiff([(256, 4, 64), (257, 4, 48), (277, 3, 9), (258, 3, 8)]), "9 samples"),
        (tiff([(256, 4, 64)]), "without its width and length"),
        (tiff([(256, 4, 0), (257, 4, 48)]), "size of 0x48"),
        (b"II*\x00\xff\xff\x00\x00", "cut short"),
        (b"P6\n64 48\n70000\n", "maximum value of 70000"),
        (b"\x00\x00\x00\x0cjP  \r\n\x87\n", "not a format whose size"),  # JPEG 2000
        (b"\x00\x00\x00\x1cftypavif", "not a format whose size"),  # AVIF
        (b"GIF89a", "not a format whose size"),
    ],
)
def test_formats_that_hide_their_size_are_refused_before_decoding(data: bytes, cause: str) -> None:
    with pytest.raises(BadImage, match=cause):
        check_upload(data, name="the uploaded file", max_pixels=4096 * 4096)


def test_a_header_over_the_limit_is_refused_before_decoding() -> None:
    huge = tiff([(256, 4, 100_000), (257, 4, 100_000), (258, 3, 8)])
    with pytest.raises(ImageTooLarge, match="100000x100000"):
        check_upload(huge, name="f", max_pixels=4096 * 4096)
    bmp = bytearray(encoded(".bmp", GRAY))
    struct.pack_into("<ii", bmp, 18, 70_000, -70_000)
    with pytest.raises(ImageTooLarge, match="70000x70000"):
        check_upload(bytes(bmp), name="f", max_pixels=4096 * 4096)


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Browserless]:
    with console_server(tmp_path_factory.mktemp("gate")) as running:
        c = Browserless(running.url)
        assert c.login().status == 200
        yield c


def _tried(client: Browserless, data: bytes) -> tuple[int, str]:
    reply = client.try_("magnet_check", {"source": "upload"}, data)
    body = reply.json()
    return reply.status, body["error"]["code"] if "error" in body else body["verdict"]


@pytest.mark.parametrize("suffix", [".bmp", ".tiff", ".ppm", ".webp", ".png"])
def test_the_console_inspects_every_format_the_gate_takes(client: Browserless, suffix: str) -> None:
    image = np.full((768, 1024, 3), 40, np.uint8)
    status, verdict = _tried(client, encoded(suffix, image))
    assert status == 200
    assert verdict in ("pass", "fail")


@pytest.mark.parametrize(
    ("data", "status", "code"),
    [
        (encoded(".tiff", np.zeros((48, 64), np.float32)), 400, "BAD_IMAGE"),
        (encoded(".hdr", np.zeros((48, 64, 3), np.float32)), 400, "BAD_IMAGE"),
        (tiff([(256, 4, 100_000), (257, 4, 100_000), (258, 3, 8)]), 413, "IMAGE_TOO_LARGE"),
    ],
)
def test_the_console_refuses_what_the_gate_refuses(
    client: Browserless, data: bytes, status: int, code: str
) -> None:
    assert _tried(client, data) == (status, code)
