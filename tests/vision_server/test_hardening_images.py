"""Issue 13, hole 1: the pixel limit cannot be bypassed by a PNG/JPEG that hides its size.

A real ``vision-server serve`` process, hostile INSPECT frames over a real socket, as an attacker
would send them (no token set). Each is refused with a typed error naming the cause, the
connection and the server stay up, and the server's peak RSS (VmHWM) stays below

    baseline + workers x max_image_pixels x DECODE_BYTES_PER_PIXEL + SLACK_BYTES

where baseline is the server's VmHWM once it has answered a first request, before anything
hostile; DECODE_BYTES_PER_PIXEL is the largest peak that decoding an accepted image costs
(measured with OpenCV 5.0: baseline JPEG 6, progressive JPEG 9, 16-bit colour PNG 12 bytes per
pixel); SLACK_BYTES covers frame buffers and allocator noise for these small frames.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from protocol import ErrorCode, ImagePayload, Inspect, MessageType, Ping
from protocol.conformance.peer import Peer, Target
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
LISTENING = re.compile(r"vision-server listening on 127\.0\.0\.1:(\d+)\n")
MAX_PIXELS = 1024 * 1024
WORKERS = 2
DECODE_BYTES_PER_PIXEL = 12
SLACK_BYTES = 48 * 2**20
# Far beyond the bound when decoded (144 MB gray, 432 MB progressive colour), under OpenCV's
# default limit of 2**30 pixels: without the fix, the server decodes them.
BOMB_SIDE = 12000

CONFIG = f"""\
server: {{max_image_pixels: {MAX_PIXELS}, workers: {WORKERS}, queue_depth: 24}}
results: {{enabled: false}}
cameras: {{tool: {{source: request}}}}
inspections:
  - {{name: brightness, type: presence, camera: tool, measure: mean_intensity, min: 0}}
"""


def _vm(pid: int, field: str) -> int:
    """A /proc/PID/status memory figure, in bytes."""
    status = Path(f"/proc/{pid}/status").read_text()
    match = re.search(rf"^{field}:\s+(\d+) kB$", status, re.MULTILINE)
    assert match, status
    return int(match[1]) * 1024


@pytest.fixture
def server(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], int]]:
    config = tmp_path / "cell.yaml"
    config.write_text(CONFIG)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for name in ("OPENCV_IO_MAX_IMAGE_PIXELS", "OPENCV_IO_MAX_IMAGE_WIDTH"):
        env.pop(name, None)  # the server must set them itself
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--port", "0", "--config", str(config)],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        match = LISTENING.fullmatch(line)
        assert match, (
            f"unexpected first line {line!r}; stderr: {proc.stderr and proc.stderr.read()}"
        )
        yield proc, int(match[1])
    finally:
        proc.kill()
        proc.communicate(timeout=30)


def _peer(port: int) -> Peer:
    peer = Peer(Target("127.0.0.1", port, timeout_s=60.0))
    peer.handshake()
    return peer


def _inspect(request_id: int, encoding: str, data: bytes) -> Inspect:
    return Inspect(request_id, "brightness", (ImagePayload(encoding, 0, 0, data),))


def _two_sofs() -> bytes:
    segments, rest = jpeg_segments(real_jpeg())
    index = sof_index(segments)
    big = jpeg_segments(with_sof(real_jpeg(), width=BOMB_SIDE, height=BOMB_SIDE))[0][index]
    joined = b"".join(segments[: index + 1]) + big + b"".join(segments[index + 1 :])
    return b"\xff\xd8" + joined + rest


EXIF = b"\xff\xe1\x00\x30Exif\x00\x00" + bytes(40)
IDAT = png_chunk(b"IDAT", b"x\x9c" + bytes(8))
HOSTILE = [
    # (label, encoding, blob, code, words the message must contain)
    (
        "stray-byte",
        "jpeg",
        stray_byte_bomb(BOMB_SIDE, BOMB_SIDE),
        ErrorCode.IMAGE_TOO_LARGE,
        f"{BOMB_SIDE}x{BOMB_SIDE}",
    ),
    (
        "stray-bytes+fill+exif",
        "jpeg",
        insert_before_sof(
            with_sof(real_jpeg(), width=BOMB_SIDE, height=BOMB_SIDE),
            b"\x12\x34" + EXIF + b"\xff\xff\x00",
        ),
        ErrorCode.IMAGE_TOO_LARGE,
        f"{BOMB_SIDE}x{BOMB_SIDE}",
    ),
    (
        "progressive",
        "jpeg",
        insert_before_sof(
            with_sof(real_jpeg(colour=True, PROGRESSIVE=1), width=BOMB_SIDE, height=BOMB_SIDE),
            b"\x00",
        ),
        ErrorCode.IMAGE_TOO_LARGE,
        f"{BOMB_SIDE}x{BOMB_SIDE}",
    ),
    (
        "under-per-side-over-in-product",
        "jpeg",
        stray_byte_bomb(1023, 60000),
        ErrorCode.IMAGE_TOO_LARGE,
        "1023x60000",
    ),
    (
        "dnl-height",
        "jpeg",
        insert_before_sof(with_sof(real_jpeg(), width=BOMB_SIDE, height=0), b"\x00"),
        ErrorCode.BAD_IMAGE,
        "DNL",
    ),
    ("two-sofs", "jpeg", _two_sofs(), ErrorCode.BAD_IMAGE, "second frame header"),
    (
        "png-ihdr-not-first",
        "png",
        b"\x89PNG\r\n\x1a\n" + png_chunk(b"tEXt", b"a\x00b") + ihdr(BOMB_SIDE, BOMB_SIDE) + IDAT,
        ErrorCode.BAD_IMAGE,
        "IHDR must come first",
    ),
    (
        "apng",
        "png",
        png(4, 4, png_chunk(b"acTL", bytes(8)), IDAT),
        ErrorCode.BAD_IMAGE,
        "animated PNG",
    ),
    (
        "png-bomb",
        "png",
        png(BOMB_SIDE, BOMB_SIDE, IDAT),
        ErrorCode.IMAGE_TOO_LARGE,
        f"{BOMB_SIDE}x{BOMB_SIDE}",
    ),
    (
        "tiff-as-png",
        "png",
        cv2.imencode(".tiff", np.zeros((8, 8), np.uint8))[1].tobytes(),
        ErrorCode.BAD_IMAGE,
        "no PNG signature",
    ),
    (
        "16-bit-colour-png",
        "png",
        cv2.imencode(".png", np.zeros((1024, 1024, 3), np.uint16))[1].tobytes(),
        ErrorCode.BAD_IMAGE,
        "must be 8-bit",
    ),
]


def test_hostile_images_are_refused_and_memory_stays_bounded(
    server: tuple[subprocess.Popen[str], int],
) -> None:
    proc, port = server
    # OpenCV's own limit is the configured one: the CLI re-executed itself (same PID) to set it.
    environ = Path(f"/proc/{proc.pid}/environ").read_bytes().split(b"\0")
    assert f"OPENCV_IO_MAX_IMAGE_PIXELS={MAX_PIXELS}".encode() in environ

    with _peer(port) as peer:
        # A legitimate image at the limit, so that the baseline includes a real decode path.
        ok = cv2.imencode(".jpg", np.full((1024, 1024, 3), 200, np.uint8))[1].tobytes()
        peer.send(_inspect(2, "jpeg", ok))
        peer.expect(MessageType.RESULT, request_id=2)
        baseline = _vm(proc.pid, "VmHWM")

        for index, (label, encoding, blob, code, words) in enumerate(HOSTILE, start=10):
            assert len(blob) < 1024 or label == "16-bit-colour-png", (label, len(blob))
            peer.send(_inspect(index, encoding, blob))
            error = peer.expect_error(code, request_id=index, fatal=False)
            assert words in error.metadata["message"], (label, error.metadata["message"])
            peer.send(Ping(index + 1000, label))
            peer.expect(MessageType.PONG, request_id=index + 1000)

    # Four at once, on four connections, each pipelining every bomb.
    bombs = [h for h in HOSTILE if h[3] is ErrorCode.IMAGE_TOO_LARGE]
    failures: list[BaseException] = []

    def attack() -> None:
        try:
            with _peer(port) as peer:
                for index, (_, encoding, blob, _, _) in enumerate(bombs, start=100):
                    peer.send(_inspect(index, encoding, blob))
                answered = set()
                for _ in bombs:  # pipelined: answers come in any order
                    error = peer.expect_error(ErrorCode.IMAGE_TOO_LARGE, fatal=False)
                    answered.add(error.request_id)
                assert answered == set(range(100, 100 + len(bombs)))
        except BaseException as exc:  # reported below, in the test's thread
            failures.append(exc)

    threads = [threading.Thread(target=attack) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    assert not failures, failures

    with _peer(port) as peer:  # the server is still up and answers
        peer.send(Ping(7, "still here"))
        peer.expect(MessageType.PONG, request_id=7)
    assert proc.poll() is None

    peak = _vm(proc.pid, "VmHWM")
    bound = baseline + WORKERS * MAX_PIXELS * DECODE_BYTES_PER_PIXEL + SLACK_BYTES
    assert peak <= bound, (
        f"peak RSS {peak / 2**20:.0f} MiB > bound {bound / 2**20:.0f} MiB "
        f"(baseline {baseline / 2**20:.0f} MiB)"
    )
