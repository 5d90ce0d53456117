#!/usr/bin/env python3
"""Attack a live vision server, one bounded phase per hole, and check what it promises.

    python scripts/attack.py --quick --json attack.json     # the short form (make test)
    python scripts/attack.py --json attack.json             # the long form (make soak)

Starts ``python -m vision_server serve`` (port 0, loopback) with a configuration whose limits are
small, so that the memory bound is tight: ``workers``, ``max_image_pixels``,
``max_buffered_bytes``, ``max_connections`` and 2 s timeouts, a token, and the console, line
and Modbus front-ends on (issue 28) with 2 s timeouts of their own. Then, phase by phase:

==================  ==========================================================================
image_bombs         JPEG/PNG whose headers hide or misstate their size, 16-bit colour, and
                    valid images of exactly ``max_image_pixels`` (decoded: the per-worker
                    peak), from concurrent connections
pre_hello_large     frames of 8 MiB announced before HELLO (a HELLO, an INSPECT), from more
                    connections than ``max_connections``, bodies streamed until the server closes
half_bodies         after HELLO, INSPECT bodies near ``max_frame_bytes`` half sent, then silence
silent              ``max_connections`` connections that say HELLO and nothing more: a good
                    client is refused, then gets in once the idle timeout has closed them
slow_bodies         HELLOs and INSPECT frames dribbled a few bytes at a time
non_readers         pipelined CAPTUREs of large frames (and INSPECTs with overlays) from clients
                    that never read
flood               four times ``max_connections`` connections at once
reload              RELOADs while clients inspect and capture from a folder camera
console_flood       twice ``console.max_connections`` idle and slowloris console connections:
                    past the limit closed at once, the rest after ``request_timeout_s``; the
                    robot's PINGs and INSPECTs answered meanwhile
login_bodies        /api/login declaring 1 GiB or just over 4 KiB (413 at once), bodies that
                    stall or trickle (408 after ``request_timeout_s``)
line_before_token   line connections sending blank, unparsable and over-long lines, never
                    ``A <token>``: closed after ``handshake_timeout_s``; a controller gets in
unread_answers      signed-in line controllers that ask for listings and read nothing: dropped
                    after ``line.write_timeout_s``
modbus_idle         idle, trickling and refused Modbus connections closed after
                    ``modbus.idle_timeout_s``; a polling PLC kept and served
token_guessing      wrong tokens on the binary HELLO, the line ``A`` and the console login:
                    each answered no sooner than the front door's delay; the right token at once
disk_full           a second server whose files may not grow past 256 KiB (RLIMIT_FSIZE):
                    every RESULT correct, ``stored`` false once the log is full, PONG unhealthy
==================  ==========================================================================

After each phase a good client (a fresh ``robot_client.VisionClient``) checks PING, an INSPECT
with a known answer (also on an image of exactly the pixel limit) and a CAPTURE. Per phase the
figures are: requests answered as promised, wrong answers, errors by code, connections refused,
hangs, VmRSS before and after, VmHWM after. At the end the server must exit 0 on SIGTERM with no
traceback on stderr, and its VmHWM must stay below the bound (:func:`memory_bound`)::

    (workers + fast_workers) x max_image_pixels x 12 B  +  constant
    constant = baseline VmRSS (after a warm-up) + 2 x max_buffered_bytes (a body or reply is
               held twice at its peak: bytes and parsed payload, payloads and serialized frame)
               + 2 x max_connections x 1 MiB (per-connection buffers) + 64 MiB (allocator)

Exit status 0 when every promise held, 1 otherwise. Loopback only; bounded in time.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import re
import resource
import signal
import socket
import sqlite3
import struct
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Awaitable, Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

SCRIPTS = Path(__file__).resolve().parent
REPO_ROOT = SCRIPTS.parent
for entry in (REPO_ROOT, SCRIPTS, REPO_ROOT / "tests" / "helpers"):
    if str(entry) not in sys.path:
        sys.path.insert(0, str(entry))

import cv2  # noqa: E402
import hostile_images as hi  # noqa: E402
import numpy as np  # noqa: E402
from soak import (  # noqa: E402
    ALLOCATOR_BYTES,
    CLOSED,
    DECODE_BYTES_PER_PIXEL,
    PER_CONNECTION_BYTES,
    RESET,
    TIMEOUT,
    RawConnection,
    ServerProcess,
    memory_bound_kib,
    status_kib,
)

from protocol import (  # noqa: E402
    Busy,
    Capture,
    CellvisionError,
    ErrorCode,
    Frame,
    Hello,
    ImageEncoding,
    ImagePayload,
    Inspect,
    Message,
    MessageType,
    Ping,
    Pong,
    Reload,
    payload_from_array,
)
from robot_client.client import ReconnectPolicy, VisionClient  # noqa: E402

VERSION = (1, 0)
MIB = 1 << 20
TOKEN = "attack-soak-token"
"""The server's token (``server: auth_token``): every front-end but Modbus asks for it, so the
wrong-token delay of the front door (issue 28) is attacked on each."""
FOLDER_LEVELS = (60, 120, 180)
"""Grey levels of the folder camera's frames: the mean a ``replayed`` RESULT must report."""

CONFIG = """\
server:
  port: 0
  workers: {workers}
  fast_workers: {fast_workers}
  queue_depth: 2
  max_connections: {max_connections}
  max_in_flight: 8
  max_image_pixels: {max_pixels}
  max_frame_bytes: {max_frame_bytes}
  max_buffered_bytes: {max_buffered_bytes}
  handshake_timeout_s: {timeout_s}
  idle_timeout_s: {timeout_s}
  frame_timeout_s: {timeout_s}
  write_timeout_s: {timeout_s}
  capture_timeout_s: 5
  allow_reload: true
  auth_token: {token}
console:
  {{enabled: true, port: 0, max_connections: {console_connections}, request_timeout_s: {timeout_s}}}
line: {{enabled: true, port: 0, max_connections: {line_connections}, write_timeout_s: {timeout_s}}}
modbus: {{enabled: true, port: 0, idle_timeout_s: {timeout_s}}}
results: {{path: results.sqlite3, store_images: none}}
cameras:
  tool: {{source: request}}
  replay: {{source: folder, path: frames}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0, max: 255}}
  - {{name: replayed, type: presence, camera: replay, measure: mean_intensity, min: 0}}
"""


@dataclass(frozen=True)
class Limits:
    """The server's configured limits (bytes, pixels, seconds)."""

    workers: int = 2
    fast_workers: int = 1
    """The fast lane's threads decode images too: they count in the memory bound."""
    max_connections: int = 16
    side: int = 1024
    """The largest accepted image is side x side pixels (``max_image_pixels``)."""
    max_frame_bytes: int = 8 * MIB
    max_buffered_bytes: int = 16 * MIB
    timeout_s: float = 2.0
    console_connections: int = 8
    line_connections: int = 8

    @property
    def max_pixels(self) -> int:
        return self.side * self.side

    def config(self) -> str:
        return CONFIG.format(
            workers=self.workers,
            fast_workers=self.fast_workers,
            max_connections=self.max_connections,
            max_pixels=self.max_pixels,
            max_frame_bytes=self.max_frame_bytes,
            max_buffered_bytes=self.max_buffered_bytes,
            timeout_s=self.timeout_s,
            token=TOKEN,
            console_connections=self.console_connections,
            line_connections=self.line_connections,
        )


def memory_bound(limits: Limits, baseline_kib: int) -> dict[str, int]:
    """The promised ceiling of the server's resident memory, and its parts (KiB): the model
    shared with scripts/soak.py (:func:`soak.memory_bound_kib`)."""
    return memory_bound_kib(
        baseline_kib=baseline_kib,
        decoders=limits.workers + limits.fast_workers,
        max_pixels=limits.max_pixels,
        max_buffered_bytes=limits.max_buffered_bytes,
        max_connections=limits.max_connections,
    )


# ----------------------------------------------------------------------------- bookkeeping


@dataclass
class Phase:
    """What one phase did and saw. ``correct``: answers (or connection ends) exactly as the
    server promises; ``wrong``: anything else (a wrong value, an unexpected code, a connection
    the server should have closed and did not)."""

    name: str
    sent: int = 0
    correct: int = 0
    wrong: int = 0
    busy: int = 0
    refused: int = 0
    """Connections the server refused (BUSY at HELLO, or closed at once by the flood guard)."""
    hangs: int = 0
    errors: Counter[str] = field(default_factory=Counter)
    ends: Counter[str] = field(default_factory=Counter)
    figures: dict[str, Any] = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)
    rss_before_kib: int | None = None
    rss_after_kib: int | None = None
    hwm_after_kib: int | None = None
    seconds: float = 0.0

    def fail(self, text: str) -> None:
        self.wrong += 1
        if len(self.problems) < 20:
            self.problems.append(text)

    def error(self, frame: Frame) -> str:
        name = code_name(frame)
        self.errors[name] += 1
        return name


def code_name(frame: Frame) -> str:
    code = frame.metadata.get("code")
    try:
        return ErrorCode(int(code)).name
    except (ValueError, TypeError):
        return f"untyped:{code}"


def wire(message: Message, request_id: int | None = None) -> bytes:
    frame = message.to_frame(VERSION)
    if request_id is not None and request_id != frame.request_id:
        frame = Frame(frame.type, request_id, frame.metadata, frame.blobs, frame.version)
    return frame.serialize()


def header(mtype: MessageType, request_id: int, meta: bytes, body_length: int) -> bytes:
    """A frame header (SPEC §3.1) announcing ``body_length`` bytes, then the metadata."""
    return (
        struct.pack("<4sBBHHHIII", b"CVIS", 1, 0, mtype, 0, 1, request_id, len(meta), body_length)
        + meta
    )


async def open_raw(port: int) -> RawConnection:
    return await RawConnection.open("127.0.0.1", port)


async def hello(conn: RawConnection, phase: Phase, hang_s: float, **kwargs: Any) -> str:
    """HELLO on a raw connection: "welcome", "refused" (BUSY at connect) or what else came."""
    kwargs.setdefault("auth_token", TOKEN)
    conn.send(wire(Hello(1, ((1, 0),), "attack", **kwargs)))
    answer = await conn.next(hang_s)
    if isinstance(answer, Frame) and answer.type == MessageType.WELCOME:
        return "welcome"
    if isinstance(answer, Frame) and code_name(answer) == "BUSY":
        phase.refused += 1
        return "refused"
    if answer == TIMEOUT:
        phase.hangs += 1
        phase.fail("no answer to HELLO")
        return "hang"
    if isinstance(answer, str):  # reset or closed at once: the flood guard
        phase.refused += 1
        return "refused"
    phase.fail(f"HELLO answered with {answer.type!r} {answer.metadata}")
    return "other"


async def until_end(conn: RawConnection, phase: Phase, hang_s: float) -> tuple[str, list[Frame]]:
    """Read until the server ends the connection: ("closed" | "reset" | TIMEOUT, frames)."""
    frames: list[Frame] = []
    while True:
        answer = await conn.next(hang_s)
        if isinstance(answer, str):
            if answer == TIMEOUT:
                phase.hangs += 1
            return answer, frames
        frames.append(answer)


def close_reason(frames: list[Frame]) -> str | None:
    for frame in frames:
        if frame.type == MessageType.CLOSE:
            return str(frame.metadata.get("reason", ""))
    return None


# ----------------------------------------------------------------------------- images


def flat_png(side: int, level: int, *, colour: bool = True, bits: int = 8) -> bytes:
    dtype = np.uint16 if bits == 16 else np.uint8
    shape = (side, side, 3) if colour else (side, side)
    ok, buf = cv2.imencode(".png", np.full(shape, level, dtype))
    assert ok
    return bytes(buf.tobytes())


def flat_jpeg(width: int, height: int, level: int, *, progressive: bool = False) -> bytes:
    params = [cv2.IMWRITE_JPEG_QUALITY, 95, cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
    ok, buf = cv2.imencode(".jpg", np.full((height, width, 3), level, np.uint8), params)
    assert ok
    return bytes(buf.tobytes())


@dataclass(frozen=True)
class ImageCase:
    """An image sent to ``bright``, and what the server must answer: a RESULT with ``level``
    as the mean (±1 for JPEG), or an ERROR with one of ``codes``."""

    name: str
    payload: ImagePayload
    level: int | None = None
    codes: frozenset[str] = frozenset()


def image_cases(side: int) -> list[ImageCase]:
    """Hostile images (tests/helpers/hostile_images.py) and images of exactly the limit."""
    png_e, jpeg_e = ImageEncoding.PNG, ImageEncoding.JPEG
    small_png = flat_png(8, 0, colour=False)
    chunks = hi.png_chunks(small_png)
    too_large = frozenset({"IMAGE_TOO_LARGE"})
    unknown_size = frozenset({"BAD_IMAGE"})

    def case(name: str, data: bytes, enc: ImageEncoding, **kwargs: Any) -> ImageCase:
        return ImageCase(name, ImagePayload(enc, 0, 0, data), **kwargs)

    return [
        case("jpeg_stray_byte_65000", hi.stray_byte_bomb(), jpeg_e, codes=too_large),
        case(
            "jpeg_sof_just_over",
            hi.with_sof(hi.real_jpeg(colour=True), width=side + 1, height=side),
            jpeg_e,
            codes=too_large,
        ),
        case("jpeg_no_sof", b"\xff\xd8\xff\xd9", jpeg_e, codes=unknown_size),
        case("png_ihdr_100000x70000", hi.png(100_000, 70_000), png_e, codes=too_large),
        case(
            "png_ihdr_not_first",
            b"\x89PNG\r\n\x1a\n" + hi.png_chunk(b"tEXt", b"k\x00v") + b"".join(chunks),
            png_e,
            codes=unknown_size,
        ),
        case("png_truncated_ihdr", small_png[:20], png_e, codes=unknown_size),
        case(
            "png_16bit_colour_at_limit",
            flat_png(side, 1000, bits=16),
            png_e,
            codes=frozenset({"BAD_IMAGE"}),
        ),
        case("png_at_limit", flat_png(side, 77), png_e, level=77),
        case("jpeg_at_limit", flat_jpeg(side, side, 128), jpeg_e, level=128),
        case(
            "jpeg_progressive_at_limit",
            flat_jpeg(side, side, 200, progressive=True),
            jpeg_e,
            level=200,
        ),
        ImageCase(
            "raw_bgr8_at_limit", payload_from_array(np.full((side, side, 3), 33, np.uint8)), 33
        ),
    ]


def judge_inspect(phase: Phase, case: ImageCase, answer: Frame | str) -> None:
    if isinstance(answer, str):
        if answer == TIMEOUT:
            phase.hangs += 1
        phase.fail(f"{case.name}: no answer ({answer})")
        return
    if answer.type == MessageType.ERROR:
        name = phase.error(answer)
        if name == "BUSY":
            phase.busy += 1
        elif name in case.codes:
            phase.correct += 1
        else:
            phase.fail(f"{case.name}: {name} {answer.metadata.get('message')}")
        return
    if answer.type == MessageType.RESULT and case.level is not None:
        value = answer.metadata.get("data", {}).get("value")
        if isinstance(value, int | float) and abs(value - case.level) <= 1.0:
            phase.correct += 1
            return
    phase.fail(f"{case.name}: answered {MessageType(answer.type).name} {answer.metadata}")


# ----------------------------------------------------------------------------- the good client


async def good_check(port: int, limits: Limits, phase: Phase, hang_s: float) -> bool:
    """A fresh well-behaved client: PING, INSPECTs with known answers (one at the pixel limit),
    a CAPTURE. Retries a refused connection or BUSY for up to ``hang_s``; True when all was
    answered correctly."""
    deadline = time.monotonic() + hang_s
    while True:
        client = VisionClient(
            "127.0.0.1",
            port,
            client_name="attack-good",
            auth_token=TOKEN,
            request_timeout_s=hang_s,
            connect_timeout_s=hang_s,
            reconnect=ReconnectPolicy(attempts=0),
        )
        try:
            await client.connect()
            token = f"good-{time.monotonic_ns()}"
            answer = await client.request(lambda rid, t=token: Ping(rid, t))
            ok = isinstance(answer, Pong) and answer.data == token
            for level, shape in ((17, (48, 64)), (201, (120, 160, 3))):
                result = await client.inspect("bright", np.full(shape, level, np.uint8))
                ok = ok and result.data.get("value") == float(level)
            big = np.full((limits.side, limits.side, 3), 91, np.uint8)
            result = await client.inspect("bright", big, encoding=ImageEncoding.PNG)
            ok = ok and result.data.get("value") == 91.0
            frames = await client.capture("replay")
            ok = ok and len(frames.images) == 1
            level = int(np.frombuffer(frames.images[0].data, np.uint8)[0])
            ok = ok and level in FOLDER_LEVELS
            phase.sent += 6
            if ok:
                phase.correct += 6
                phase.figures["good_checks"] = phase.figures.get("good_checks", 0) + 1
            else:
                phase.fail("the good client got a wrong answer")
            return ok
        except Busy:
            phase.refused += 1
        except (CellvisionError, OSError) as exc:
            phase.ends[f"good:{type(exc).__name__}"] += 1
            if time.monotonic() > deadline:
                phase.fail(f"the good client failed: {type(exc).__name__}: {exc}")
                return False
        finally:
            await client.close()
        if time.monotonic() > deadline:
            phase.fail("the good client was refused for the whole phase")
            return False
        await asyncio.sleep(0.1)


async def health(port: int, hang_s: float) -> dict[str, Any]:
    """The server's health report (PONG), over a raw connection (retried while refused)."""
    deadline = time.monotonic() + hang_s
    while time.monotonic() < deadline:
        conn = await open_raw(port)
        try:
            scratch = Phase("health")
            if await hello(conn, scratch, hang_s) == "welcome":
                conn.send(wire(Ping(2, "health")))
                answer = await conn.next(hang_s)
                if isinstance(answer, Frame) and answer.type == MessageType.PONG:
                    return dict(answer.metadata.get("health") or {})
        finally:
            await conn.aclose()
        await asyncio.sleep(0.1)
    raise RuntimeError("no health report within the bound")


async def wait_for(
    probe: Callable[[], Awaitable[bool]], bound_s: float, interval_s: float = 0.1
) -> bool:
    """Poll ``probe`` until it holds (True) or ``bound_s`` passed (False)."""
    deadline = time.monotonic() + bound_s
    while True:
        if await probe():
            return True
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(interval_s)


async def settled(port: int, hang_s: float, *, connections: int = 1) -> bool:
    """Wait until the server holds no body bytes and at most ``connections`` connections
    (the probe's own)."""

    async def probe() -> bool:
        admission = (await health(port, hang_s)).get("admission", {})
        return bool(
            admission.get("buffered_bytes") == 0 and admission.get("connections", 99) <= connections
        )

    return await wait_for(probe, hang_s)


# ----------------------------------------------------------------------------- the attacks


@dataclass(frozen=True)
class Run:
    """What every phase needs: the server's port, its limits, the size of the run."""

    port: int
    limits: Limits
    scale: int
    """1 for the short form; more rounds and connections in the long one."""
    hang_s: float
    console_port: int = 0
    line_port: int = 0
    modbus_port: int = 0


async def image_bombs(run: Run, phase: Phase) -> None:
    cases = image_cases(run.limits.side)
    rounds = 2 * run.scale
    phase.figures["cases"] = [c.name for c in cases]

    async def client(index: int) -> None:
        conn = await open_raw(run.port)
        try:
            if await hello(conn, phase, run.hang_s) != "welcome":
                return
            for rid, case in enumerate((cases[index:] + cases[:index]) * rounds, start=2):
                phase.sent += 1
                conn.send(wire(Inspect(rid, "bright", (case.payload,))))
                judge_inspect(phase, case, await conn.next(run.hang_s))
        finally:
            await conn.aclose()

    await asyncio.gather(*(client(i) for i in range(2 * run.limits.workers + 2)))


async def pre_hello_large(run: Run, phase: Phase) -> None:
    """8 MiB announced before HELLO: a HELLO (over the 64 KiB handshake limit) and an INSPECT.
    The server must refuse at the header and close, whatever the body does."""
    size = 8 * MIB
    chunk = bytes(256 * 1024)

    async def client(index: int) -> None:
        conn = await open_raw(run.port)
        kind = MessageType.HELLO if index % 2 == 0 else MessageType.INSPECT
        expected = {"FRAME_TOO_LARGE", "NOT_AUTHENTICATED", "BUSY"}
        phase.sent += 1
        try:
            conn.send(header(kind, 1, b"{}", size))
            sent = 0
            with contextlib.suppress(ConnectionError, OSError):
                while sent < size - 2 and not conn.writer.is_closing():
                    conn.send(chunk)
                    sent += len(chunk)
                    await conn.writer.drain()
            end, frames = await until_end(conn, phase, run.hang_s)
            phase.ends[end] += 1
            codes = [phase.error(f) for f in frames if f.type == MessageType.ERROR]
            phase.figures["body_bytes_sent_max"] = max(
                phase.figures.get("body_bytes_sent_max", 0), sent
            )
            if "BUSY" in codes:
                phase.refused += 1
            if end == TIMEOUT:
                phase.fail(f"{kind.name} of 8 MiB before HELLO: the connection stayed open")
            elif codes and set(codes) <= expected or end == "reset":
                # A reset: the server closed while we were still writing the refused body;
                # its ERROR may then be lost in the reset (TCP), never a WELCOME.
                phase.correct += 1
            else:
                phase.fail(f"{kind.name} of 8 MiB before HELLO answered {codes} then {end}")
        finally:
            await conn.aclose()

    await asyncio.gather(*(client(i) for i in range(2 * run.limits.max_connections * run.scale)))


async def half_bodies(run: Run, phase: Phase) -> None:
    """After HELLO, INSPECT bodies of ~6 MiB half sent, then silence: at most
    max_buffered_bytes of them are admitted, the rest BUSY at the header; the frame timeout
    closes every one."""
    length = run.limits.max_frame_bytes - 2 * MIB
    meta = b'{"inspection": "bright"}'
    n = run.limits.max_connections - 2
    admitted_bound = run.limits.max_buffered_bytes // length

    async def client(index: int) -> None:
        conn = await open_raw(run.port)
        try:
            if await hello(conn, phase, run.hang_s) != "welcome":
                return
            phase.sent += 1
            conn.send(header(MessageType.INSPECT, 2, meta, length))
            half = length // 2
            with contextlib.suppress(ConnectionError, OSError):
                for _ in range(half // (256 * 1024)):
                    conn.send(bytes(256 * 1024))
                    await conn.writer.drain()
            end, frames = await until_end(conn, phase, run.hang_s)
            phase.ends[end] += 1
            codes = [phase.error(f) for f in frames if f.type == MessageType.ERROR]
            reason = close_reason(frames) or ""
            if "BUSY" in codes:
                phase.busy += 1
            else:
                phase.figures["admitted"] = phase.figures.get("admitted", 0) + 1
            if end != TIMEOUT and "frame was not complete" in reason and set(codes) <= {"BUSY"}:
                phase.correct += 1
            else:
                phase.fail(f"half-sent body: {codes}, CLOSE {reason!r}, then {end}")
        finally:
            await conn.aclose()

    await asyncio.gather(*(client(i) for i in range(n)))
    report = await health(run.port, run.hang_s)
    admission = report.get("admission", {})
    phase.figures["buffered_bytes_peak"] = admission.get("buffered_bytes_peak")
    phase.figures["buffer_refusals"] = admission.get("buffer_refusals")
    if phase.figures.get("admitted", 0) > admitted_bound:
        admitted = phase.figures["admitted"]
        phase.fail(f"{admitted} bodies admitted, the budget holds {admitted_bound}")
    if (admission.get("buffered_bytes_peak") or 0) > run.limits.max_buffered_bytes:
        phase.fail(f"buffered_bytes_peak {admission.get('buffered_bytes_peak')} over the budget")


async def silent(run: Run, phase: Phase) -> None:
    """Every connection slot held by a client that said HELLO and nothing more."""
    conns = [await open_raw(run.port) for _ in range(run.limits.max_connections)]
    try:
        states = await asyncio.gather(*(hello(c, phase, run.hang_s) for c in conns))
        held = [c for c, s in zip(conns, states, strict=True) if s == "welcome"]
        phase.figures["held"] = len(held)
        # Half of them first have one request answered (then no request is in flight: the
        # idle timeout must start again).
        image = payload_from_array(np.full((8, 8), 9, np.uint8))
        for conn in held[::2]:
            phase.sent += 1
            conn.send(wire(Inspect(2, "bright", (image,))))
            answer = await conn.next(run.hang_s)
            if isinstance(answer, Frame) and answer.type == MessageType.RESULT:
                phase.correct += 1
            else:
                phase.fail(f"an INSPECT before the silence was answered {answer!r}")
        # A good client now: refused while the slots are held (BUSY at HELLO).
        probe = await open_raw(run.port)
        state = await hello(probe, phase, run.hang_s)
        await probe.aclose()
        phase.figures["good_client_while_held"] = state
        if state == "welcome" and len(held) == run.limits.max_connections:
            phase.fail("a connection beyond max_connections was served")
        ends = await asyncio.gather(*(until_end(c, phase, run.hang_s) for c in held))
        for end, frames in ends:
            phase.sent += 1
            phase.ends[end] += 1
            reason = close_reason(frames) or ""
            if end != TIMEOUT and reason.startswith("idle for"):
                phase.correct += 1
            else:
                phase.fail(f"silent connection: CLOSE {reason!r} then {end}")
    finally:
        for conn in conns:
            await conn.aclose()


async def slow_bodies(run: Run, phase: Phase) -> None:
    """HELLOs and INSPECTs dribbled 64 bytes every 100 ms (slower than any frame timeout)."""
    image = np.full((120, 160, 3), 5, np.uint8)
    inspect = wire(Inspect(2, "bright", (payload_from_array(image),)))
    hello_frame = wire(Hello(1, ((1, 0),), "slow", auth_token=TOKEN))

    async def client(index: int) -> None:
        conn = await open_raw(run.port)
        try:
            before_hello = index % 2 == 0
            if not before_hello and await hello(conn, phase, run.hang_s) != "welcome":
                return
            data = hello_frame if before_hello else inspect
            phase.sent += 1

            async def dribble() -> None:
                with contextlib.suppress(ConnectionError, OSError):
                    for at in range(0, len(data) - 1, 64):
                        conn.send(data[at : min(at + 64, len(data) - 1)])
                        await conn.writer.drain()
                        await asyncio.sleep(0.1)

            writer = asyncio.create_task(dribble())
            end, frames = await until_end(conn, phase, run.hang_s)
            writer.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await writer
            phase.ends[end] += 1
            reason = close_reason(frames) or ""
            codes = [phase.error(f) for f in frames if f.type == MessageType.ERROR]
            want = "no HELLO within" if before_hello else "frame was not complete"
            # An INSPECT may be BUSY at its header (the pool is full): its body is then skipped,
            # and the frame timeout closes the connection all the same.
            if end != TIMEOUT and want in reason and set(codes) <= {"BUSY"}:
                phase.busy += len(codes)
                phase.correct += 1
            elif before_hello and end != TIMEOUT and codes == ["BUSY"]:
                phase.refused += 1  # over max_connections: refused once its HELLO was in
                phase.correct += 1
            else:
                phase.fail(f"slow {'HELLO' if before_hello else 'INSPECT'}: {codes} {reason!r}")
        finally:
            await conn.aclose()

    tasks = [client(i) for i in range(min(4 * run.scale, run.limits.max_connections - 2))]
    await asyncio.gather(*tasks, good_check(run.port, run.limits, phase, run.hang_s))


async def non_readers(run: Run, phase: Phase) -> None:
    """Clients that pipeline large CAPTUREs (2 raw frames of side x side x 3 bytes) or INSPECTs
    with an overlay, and never read: the server must drop them after its write timeout, hold
    no more than its budget meanwhile, and refuse a CAPTURE larger than the client accepts."""
    n = max(2, run.limits.max_connections // 2 - 2)
    noisy = np.random.default_rng(7).integers(0, 256, (run.limits.side, run.limits.side, 3))
    jpeg = payload_from_array(noisy.astype(np.uint8), encoding=ImageEncoding.JPEG)
    conns: list[RawConnection] = []
    for index in range(n):
        conn = await open_raw(run.port)
        if await hello(conn, phase, run.hang_s) != "welcome":
            await conn.aclose()
            continue
        conns.append(conn)
        for rid in range(2, 2 + 8 + 4):
            phase.sent += 1
            if index % 2 == 0:
                conn.send(wire(Capture(rid, "replay", 2)))
            else:
                conn.send(wire(Inspect(rid, "bright", (jpeg,), overlay=True)))
    peak = 0

    async def dropped() -> bool:
        nonlocal peak
        admission = (await health(run.port, run.hang_s)).get("admission", {})
        peak = max(peak, int(admission.get("buffered_bytes_peak") or 0))
        return bool(admission.get("connections", 99) <= 1)

    gone = await wait_for(dropped, run.hang_s + 4 * run.limits.timeout_s, 0.2)
    phase.figures["dropped_all"] = gone
    phase.figures["buffered_bytes_peak"] = peak
    if not gone:
        phase.hangs += 1
        phase.fail("non-reading clients were not dropped")
    if peak > run.limits.max_buffered_bytes:
        phase.fail(f"buffered_bytes_peak {peak} over the budget")
    # A client that reads but accepts only 1 MiB frames: its CAPTURE must be refused, not sent.
    small = await open_raw(run.port)
    if await hello(small, phase, run.hang_s, max_frame_bytes=MIB) == "welcome":
        phase.sent += 1
        small.send(wire(Capture(2, "replay", 2)))
        answer = await small.next(run.hang_s)
        if isinstance(answer, Frame) and phase.error(answer) == "INVALID_ARGUMENT":
            phase.correct += 1
        else:
            phase.fail(f"a CAPTURE over the client's max_frame_bytes was answered {answer!r}")
    await small.aclose()
    for conn in conns:
        end, frames = await until_end(conn, phase, run.hang_s)
        phase.ends[end] += 1
        for frame in frames:
            if frame.type == MessageType.ERROR:
                if phase.error(frame) == "BUSY":
                    phase.busy += 1
                    phase.correct += 1
                else:
                    phase.fail(f"a non-reader got {code_name(frame)}")
            elif frame.type in (MessageType.FRAMES, MessageType.RESULT):
                phase.correct += 1
        phase.figures["answers_before_drop"] = phase.figures.get("answers_before_drop", 0) + len(
            frames
        )
        await conn.aclose()


async def flood(run: Run, phase: Phase) -> None:
    """Four times max_connections connections at once, half of them silent."""
    n = 4 * run.limits.max_connections * run.scale

    async def client(index: int) -> None:
        phase.sent += 1
        try:
            conn = await open_raw(run.port)
        except OSError:
            phase.refused += 1
            phase.ends["connect_failed"] += 1
            phase.correct += 1
            return
        try:
            if index % 2 == 0:
                state = await hello(conn, phase, run.hang_s)
                phase.ends[state] += 1
                if state in ("welcome", "refused"):
                    phase.correct += 1
                conn.send(wire(Ping(2, "x")))
                return
            end, frames = await until_end(conn, phase, run.hang_s)
            reason = close_reason(frames) or ""
            codes = [phase.error(f) for f in frames if f.type == MessageType.ERROR]
            phase.ends[f"silent:{end}"] += 1
            if end == TIMEOUT:
                phase.fail("a silent connection of the flood stayed open")
            elif reason.startswith("no HELLO") or "BUSY" in codes or not frames:
                if "BUSY" in codes or not frames:
                    phase.refused += 1
                phase.correct += 1
            else:
                phase.fail(f"a silent connection of the flood got {codes} {reason!r}")
        finally:
            await conn.aclose()

    await asyncio.gather(*(client(i) for i in range(n)))


async def reload_under_load(run: Run, phase: Phase) -> None:
    """RELOADs while clients INSPECT (folder camera) and CAPTURE: every answer correct; a
    CAMERA_UNAVAILABLE is a camera closed under a running request (counted, must be 0)."""
    stop = asyncio.Event()
    reloads = 10 * run.scale

    async def worker(index: int) -> None:
        policy = ReconnectPolicy(attempts=3)
        async with VisionClient(
            "127.0.0.1", run.port, request_timeout_s=run.hang_s, reconnect=policy, auth_token=TOKEN
        ) as client:
            while not stop.is_set():
                phase.sent += 1
                try:
                    if index % 2 == 0:
                        result = await client.inspect("replayed")
                        ok = result.data.get("value") in {float(v) for v in FOLDER_LEVELS}
                    else:
                        frames = await client.capture("replay", count=2)
                        first = np.frombuffer(frames.images[0].data, np.uint8)[0]
                        ok = len(frames.images) == 2 and int(first) in FOLDER_LEVELS
                except Busy:
                    phase.busy += 1
                    phase.errors["BUSY"] += 1
                    await asyncio.sleep(0.02)
                    continue
                except CellvisionError as exc:
                    phase.errors[exc.code.name] += 1
                    phase.fail(f"{'INSPECT' if index % 2 == 0 else 'CAPTURE'}: {exc}")
                    continue
                if ok:
                    phase.correct += 1
                else:
                    phase.fail("a wrong value under reload")

    async def reloader() -> None:
        try:
            async with VisionClient(
                "127.0.0.1", run.port, request_timeout_s=run.hang_s, auth_token=TOKEN
            ) as client:
                for _ in range(reloads):
                    answer = await client.request(lambda rid: Reload(rid))
                    phase.figures["reloads"] = phase.figures.get("reloads", 0) + 1
                    if answer.TYPE != MessageType.RELOADED:
                        phase.fail(f"RELOAD answered {answer.TYPE.name}")
                    await asyncio.sleep(0.05)
        finally:
            stop.set()

    await asyncio.gather(reloader(), *(worker(i) for i in range(4)))
    phase.figures["camera_unavailable"] = phase.errors.get("CAMERA_UNAVAILABLE", 0)


# ----------------------------------------------------------------------------- the other doors
# Issue 28 ("One front door"): the console, the line protocol and Modbus go through the same
# door as the binary protocol. Each phase below attacks one of its promises on a live server.


async def open_tcp(port: int, rcvbuf: int | None = None) -> tuple[Any, Any]:
    """A plain TCP connection (reader, writer); ``rcvbuf`` shrinks the receive buffer before
    connecting, so that answers left unread fill the server's side sooner."""
    if rcvbuf is None:
        return await asyncio.open_connection("127.0.0.1", port)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.setblocking(False)
    await asyncio.get_running_loop().sock_connect(sock, ("127.0.0.1", port))
    return await asyncio.open_connection(sock=sock)


async def until_closed(
    reader: Any, since: float, bound_s: float, first: list[float] | None = None
) -> tuple[str, float, bytes]:
    """Read until the server ends the connection: (CLOSED | RESET | TIMEOUT, seconds since
    ``since``, what came); the seconds to the first byte are appended to ``first``."""
    data = bytearray()
    try:
        async with asyncio.timeout(bound_s):
            while True:
                chunk = await reader.read(1 << 16)
                if not chunk:
                    return CLOSED, time.monotonic() - since, bytes(data)
                if not data and first is not None:
                    first.append(time.monotonic() - since)
                data += chunk
    except TimeoutError:
        return TIMEOUT, time.monotonic() - since, bytes(data)
    except (ConnectionError, OSError):
        return RESET, time.monotonic() - since, bytes(data)


async def shut(writer: Any) -> None:
    writer.close()
    with contextlib.suppress(Exception):
        await writer.wait_closed()


def http_head(method: str, path: str, length: int | None = None, **headers: str) -> bytes:
    """A request head from the console's own host, one request per connection; a body is
    JSON (the console's cross-site rule lets a JSON body through without an Origin)."""
    lines = [f"{method} {path} HTTP/1.1", "Host: 127.0.0.1", "Connection: close"]
    if length is not None:
        lines += ["Content-Type: application/json", f"Content-Length: {length}"]
    lines += [f"{k.replace('_', '-')}: {v}" for k, v in headers.items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def http_status(data: bytes) -> int | None:
    try:
        return int(data.split(b" ", 2)[1])
    except (IndexError, ValueError):
        return None


async def login(port: int, token: str, bound_s: float) -> tuple[int | None, float]:
    """POST /api/login with ``token``: (status, seconds)."""
    body = json.dumps({"token": token}).encode()
    started = time.monotonic()
    reader, writer = await open_tcp(port)
    try:
        writer.write(http_head("POST", "/api/login", len(body)) + body)
        _, seconds, data = await until_closed(reader, started, bound_s)
        return http_status(data), seconds
    finally:
        await shut(writer)


def judge_timeout(phase: Phase, what: str, end: str, seconds: float, timeout_s: float) -> bool:
    """A connection the server must close after ``timeout_s`` (not before, not much later:
    2 s of slack for a loaded machine)."""
    phase.figures.setdefault("closed_after_s", []).append(round(seconds, 2))
    if end == TIMEOUT:
        phase.hangs += 1
        phase.fail(f"{what}: still open after {seconds:.1f} s")
        return False
    if not timeout_s - 0.25 <= seconds <= timeout_s + 2.0:
        phase.fail(f"{what}: closed after {seconds:.2f} s, the timeout is {timeout_s:g} s")
        return False
    phase.correct += 1
    return True


async def robot_meanwhile(run: Run, phase: Phase, stop: asyncio.Event) -> None:
    """The robot on the binary protocol while another front-end is attacked: PINGs and
    INSPECTs with known answers, each answered right and in time (the slowest is a figure;
    over 2 s is a failure)."""
    slowest = 0.0
    count = 0
    async with VisionClient(
        "127.0.0.1", run.port, request_timeout_s=run.hang_s, auth_token=TOKEN
    ) as client:
        while not stop.is_set():
            count += 1
            level = count % 256
            started = time.monotonic()
            phase.sent += 1
            try:
                if count % 2:
                    pong = await client.request(lambda rid, t=str(count): Ping(rid, t))
                    ok = isinstance(pong, Pong) and pong.data == str(count)
                else:
                    result = await client.inspect("bright", np.full((48, 64), level, np.uint8))
                    ok = result.data.get("value") == float(level)
            except Busy:
                phase.busy += 1
                continue
            except CellvisionError as exc:
                phase.fail(f"the robot's request failed: {exc}")
                continue
            slowest = max(slowest, time.monotonic() - started)
            if ok:
                phase.correct += 1
            else:
                phase.fail("the robot got a wrong answer")
            await asyncio.sleep(0.05)
    phase.figures["robot_requests"] = count
    phase.figures["robot_slowest_s"] = round(slowest, 3)
    if slowest > 2.0:
        phase.fail(f"a robot request took {slowest:.2f} s during the attack")


async def console_flood(run: Run, phase: Phase) -> None:
    """Idle and slowloris console connections, twice ``console.max_connections``: those past
    the limit closed at once, the others after ``request_timeout_s`` however they trickle;
    the robot served meanwhile."""
    limit = run.limits.console_connections
    timeout_s = run.limits.timeout_s
    total = 2 * limit * run.scale
    slow = max(2, limit // 3)
    stop = asyncio.Event()
    robot = asyncio.create_task(robot_meanwhile(run, phase, stop))
    trickle = b"GET /api/server HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: " + b"a" * 4096

    async def dribble(writer: Any) -> None:
        # A header byte every 0.2 s: the whole head would take minutes.
        with contextlib.suppress(ConnectionError, OSError):
            for byte in trickle:
                writer.write(bytes([byte]))
                await writer.drain()
                await asyncio.sleep(0.2)

    opened: list[tuple[bool, float, Any, Any]] = []
    try:
        reset_at_connect = 0
        for index in range(total):
            try:
                reader, writer = await open_tcp(run.console_port)
            except OSError:
                # Closed (reset) before our connect() returned: past the limit, at once.
                reset_at_connect += 1
                continue
            opened.append((index < slow, time.monotonic(), reader, writer))
        dribblers = [asyncio.create_task(dribble(w)) for is_slow, _, _, w in opened if is_slow]
        ends = await asyncio.gather(
            *(until_closed(r, since, run.hang_s) for _, since, r, _ in opened)
        )
        for task in dribblers:
            task.cancel()
        at_once = reset_at_connect
        phase.sent += reset_at_connect
        phase.refused += reset_at_connect
        phase.correct += reset_at_connect
        phase.ends["reset_at_connect"] = reset_at_connect
        for (is_slow, _, _, _), (end, seconds, _) in zip(opened, ends, strict=True):
            phase.sent += 1
            phase.ends[f"{'slow' if is_slow else 'idle'}:{end}"] += 1
            if end != TIMEOUT and seconds < timeout_s / 2:
                at_once += 1
                phase.refused += 1
                phase.correct += 1
            else:
                judge_timeout(phase, "a console connection", end, seconds, timeout_s)
        phase.figures["connections"] = total
        phase.figures["closed_at_once"] = at_once
        if at_once < total - limit:
            phase.fail(f"{at_once} connections closed at once, {total - limit} were past the limit")
    finally:
        stop.set()
        await robot
        for _, _, _, writer in opened:
            await shut(writer)


async def login_bodies(run: Run, phase: Phase) -> None:
    """/api/login with a body too large (declared: 1 GB, or just over 4 KiB) and with bodies
    that stall or trickle: 413 at once, 408 after ``request_timeout_s``; then the right token
    signs in."""
    timeout_s = run.limits.timeout_s

    async def attempt(kind: str) -> None:
        started = time.monotonic()
        reader, writer = await open_tcp(run.console_port)
        phase.sent += 1
        try:
            feeder: asyncio.Task[None] | None = None
            if kind == "huge":
                writer.write(http_head("POST", "/api/login", 1 << 30) + bytes(64 * 1024))
            elif kind == "over_4k":
                body = json.dumps({"token": "x" * 4096}).encode()
                writer.write(http_head("POST", "/api/login", len(body)) + body)
            elif kind == "stalled":
                writer.write(http_head("POST", "/api/login", 200) + b'{"token": "')
            else:  # trickling: a body byte every 0.25 s, never done in time

                async def feed() -> None:
                    with contextlib.suppress(ConnectionError, OSError):
                        for _ in range(200):
                            writer.write(b" ")
                            await writer.drain()
                            await asyncio.sleep(0.25)

                writer.write(http_head("POST", "/api/login", 200))
                feeder = asyncio.create_task(feed())
            first: list[float] = []
            end, seconds, data = await until_closed(reader, started, run.hang_s, first)
            if feeder is not None:
                feeder.cancel()
            status = http_status(data)
            answered = first[0] if first else seconds
            phase.ends[f"{kind}:{status}"] += 1
            # The answer is what is promised in time; the close may come up to another
            # request_timeout_s later (the server waits that long for the unread body).
            phase.figures.setdefault(f"{kind}_closed_after_s", []).append(round(seconds, 2))
            if end == TIMEOUT or seconds > 2 * timeout_s + 2.0:
                phase.hangs += 1
                phase.fail(f"{kind} login body: the connection open after {seconds:.1f} s")
            elif kind in ("huge", "over_4k"):
                phase.figures.setdefault("413_after_s", []).append(round(answered, 2))
                if status == 413 and answered < 1.0:
                    phase.correct += 1
                else:
                    phase.fail(f"{kind} login body: {status} after {answered:.2f} s ({end})")
            elif status == 408:
                judge_timeout(phase, f"{kind} login body", end, answered, timeout_s)
            else:
                phase.fail(f"{kind} login body: {status} after {answered:.2f} s ({end})")
        finally:
            await shut(writer)

    kinds = ["huge", "huge", "over_4k", "stalled", "stalled", "trickle", "trickle"]
    for _ in range(run.scale):
        await asyncio.gather(*(attempt(kind) for kind in kinds))
    status, seconds = await login(run.console_port, TOKEN, run.hang_s)
    phase.sent += 1
    phase.figures["good_login"] = [status, round(seconds, 3)]
    if status == 200:
        phase.correct += 1
    else:
        phase.fail(f"the right token after the attack: {status}")


async def line_exchange(port: int, lines: list[bytes], bound_s: float) -> list[bytes]:
    """Send ``lines`` one at a time on a new line-protocol connection, an answer line each
    (without its CR LF)."""
    reader, writer = await open_tcp(port)
    answers: list[bytes] = []
    try:
        async with asyncio.timeout(bound_s):
            for line in lines:
                writer.write(line)
                answers.append((await reader.readline()).rstrip(b"\r\n"))
    except (TimeoutError, ConnectionError, OSError):
        pass
    finally:
        await shut(writer)
    return answers


async def good_controller(run: Run, phase: Phase, when: str) -> None:
    """A controller that signs in and pings: ``OK`` then ``OK PONG``."""
    started = time.monotonic()
    answers = await line_exchange(run.line_port, [f"A {TOKEN}\n".encode(), b"P\n"], run.hang_s)
    phase.sent += 1
    phase.figures[f"good_controller_{when}_s"] = round(time.monotonic() - started, 3)
    if answers == [b"OK", b"OK PONG"]:
        phase.correct += 1
    else:
        phase.fail(f"the good controller {when}: {answers}")


async def line_before_token(run: Run, phase: Phase) -> None:
    """Line connections sending blank, unparsable and over-long lines but never ``A
    <token>``: each closed ``handshake_timeout_s`` after connecting with ``ER 8``; a good
    controller signs in meanwhile and afterwards."""
    timeout_s = run.limits.timeout_s
    junk = (b"\n", b"\r\n", b"#?!\x01\n", b"X" * 300 + b"\n", b"   \n")
    n = (run.limits.line_connections - 2) * run.scale

    async def attacker(index: int) -> None:
        started = time.monotonic()
        try:
            reader, writer = await open_tcp(run.line_port)
        except OSError:
            phase.fail("a line connection was refused by the kernel")
            return

        async def send() -> None:
            with contextlib.suppress(ConnectionError, OSError):
                for turn in range(1000):
                    writer.write(junk[(index + turn) % len(junk)])
                    await writer.drain()
                    await asyncio.sleep(0.1)

        sender = asyncio.create_task(send())
        phase.sent += 1
        try:
            end, seconds, data = await until_closed(reader, started, run.hang_s)
        finally:
            sender.cancel()
            await shut(writer)
        last = data.rstrip(b"\r\n").rsplit(b"\n", 1)[-1]
        phase.ends[last[:24].decode(errors="replace")] += 1
        if last.startswith(b"ER 20"):  # over line.max_connections in the long form
            phase.refused += 1
            phase.correct += 1
        elif last.startswith(b"ER 8 no A <token>"):
            judge_timeout(phase, "a line connection without A", end, seconds, timeout_s)
        else:
            phase.fail(f"a line connection without A ended with {last[:60]!r} ({end})")

    attackers = asyncio.gather(*(attacker(i) for i in range(n)))
    await asyncio.sleep(timeout_s / 2)
    await good_controller(run, phase, "during")
    await attackers
    await good_controller(run, phase, "after")


async def unread_answers(run: Run, phase: Phase) -> None:
    """Signed-in line controllers that request listings and never read them: each dropped
    ``line.write_timeout_s`` after its answers stopped moving. (The console's own write
    timeout, 30 s, is a constant: too long for this soak.)"""
    timeout_s = run.limits.timeout_s
    n = 2 * run.scale

    async def client() -> None:
        reader, writer = await open_tcp(run.line_port, rcvbuf=4096)
        phase.sent += 1
        try:
            writer.write(f"A {TOKEN}\n".encode())
            if (await reader.readline()).rstrip() != b"OK":
                phase.fail("a non-reader could not sign in")
                return
            # Listings, a bounded number: answers of some 4 MB, more than the kernel takes in
            # on our side however small our receive buffer (with 0.5 MB, all of it was taken
            # in at times: the server then rightly had nothing unsent), not so many that
            # answering them keeps the server busy past our wait.
            requests = 150_000
            writer.write(b"L\n" * requests)
            await writer.drain()
            stopped_reading = time.monotonic()
            phase.figures.setdefault("requests_sent", []).append(requests)
            # The server must drop it on its own: wait past its write timeout, then read. A
            # connection not dropped would be answered to the end, then stay open (no EOF
            # before line.idle_timeout_s, 300 s).
            # (the server's write timeout, then the front door's watchdog's own turn, with room
            # for a loaded machine)
            await asyncio.sleep(2 * timeout_s + 6.0)
            end, seconds, data = await until_closed(reader, stopped_reading, run.hang_s)
            phase.ends[end] += 1
            phase.figures.setdefault("answer_bytes_before_drop", []).append(len(data))
            if end == TIMEOUT:
                phase.hangs += 1
                phase.fail("a controller that read nothing was not dropped")
            else:
                phase.correct += 1
        finally:
            await shut(writer)

    await asyncio.gather(*(client() for _ in range(n)))
    await good_controller(run, phase, "after")


def modbus_read(tid: int, unit: int = 1) -> bytes:
    """Read holding registers: one register at address 0 (MODBUS.md §2)."""
    return struct.pack(">HHHBBHH", tid, 0, 6, unit, 3, 0, 1)


async def modbus_idle(run: Run, phase: Phase) -> None:
    """Idle Modbus connections, ones trickling a frame a byte at a time, and ones whose every
    request is refused (a wrong unit id): each closed ``modbus.idle_timeout_s`` after its
    connect; a PLC polling all the while keeps its connection and every answer."""
    timeout_s = run.limits.timeout_s
    stop = asyncio.Event()

    async def attacker(kind: str) -> None:
        started = time.monotonic()
        reader, writer = await open_tcp(run.modbus_port)

        async def send() -> None:
            with contextlib.suppress(ConnectionError, OSError):
                for turn in range(1000):
                    if kind == "trickle":  # 12 bytes a frame: one done every 3.6 s
                        frame = modbus_read(turn // 12 + 1)
                        writer.write(frame[turn % 12 : turn % 12 + 1])
                    else:  # unit 9 is not this device: exception 0x0B, not served
                        writer.write(modbus_read(turn + 1, unit=9))
                    await writer.drain()
                    await asyncio.sleep(0.3)

        sender = asyncio.create_task(send()) if kind != "idle" else None
        phase.sent += 1
        try:
            end, seconds, _ = await until_closed(reader, started, run.hang_s)
        finally:
            if sender is not None:
                sender.cancel()
            await shut(writer)
        phase.ends[f"{kind}:{end}"] += 1
        judge_timeout(phase, f"a {kind} Modbus connection", end, seconds, timeout_s)

    async def plc() -> None:
        reader, writer = await open_tcp(run.modbus_port)
        polls = 0
        try:
            while not stop.is_set():
                polls += 1
                phase.sent += 1
                writer.write(modbus_read(polls & 0xFFFF))
                try:
                    async with asyncio.timeout(run.hang_s):
                        answer = await reader.readexactly(11)
                except (TimeoutError, asyncio.IncompleteReadError, ConnectionError, OSError):
                    phase.fail(f"the polling PLC lost its answer at poll {polls}")
                    return
                tid, _, length, _, function, count = struct.unpack(">HHHBBB", answer[:9])
                if (tid, length, function, count) == (polls & 0xFFFF, 5, 3, 2):
                    phase.correct += 1
                else:
                    phase.fail(f"the polling PLC got {answer.hex()}")
                await asyncio.sleep(0.25)
        finally:
            phase.figures["plc_polls"] = polls
            await shut(writer)

    poller = asyncio.create_task(plc())
    kinds = ["idle", "idle", "trickle", "trickle", "refused", "refused"] * run.scale
    try:
        await asyncio.gather(*(attacker(kind) for kind in kinds))
    finally:
        stop.set()
        await poller


AUTH_DELAY_MIN_S = 0.1
AUTH_DELAY_MAX_S = 5.0


async def token_guessing(run: Run, phase: Phase) -> None:
    """Wrong tokens on the binary HELLO, the line ``A`` and the console login, two guessers
    on each, for a fixed window: every guess refused, each wrong answer delayed as the front
    door promises (loopback is one host: the n-th wrong token waits 0.1 s x 2^(n-1), at most
    5 s), so the guess rate stays low; then the right token signs in on each at once."""
    window_s = 5.0 * run.scale
    answered: list[tuple[float, float, str]] = []

    # Each guess ends "refused" (the wrong-token answer), "closed" (the connection ended
    # first: the handshake timeout, shorter here than the longest delay, closed it; to a
    # guesser that too says "wrong", the right token being answered at once) or "accepted".
    async def guess_binary(token: str) -> str:
        conn = await open_raw(run.port)
        try:
            conn.send(wire(Hello(1, ((1, 0),), "guess", auth_token=token)))
            answer = await conn.next(run.hang_s + AUTH_DELAY_MAX_S)
            if isinstance(answer, Frame) and answer.type == MessageType.WELCOME:
                return "accepted"
            if isinstance(answer, Frame) and code_name(answer) == "NOT_AUTHENTICATED":
                # The handshake timeout's CLOSE says NOT_AUTHENTICATED too: told apart by
                # its message.
                message = str(answer.metadata.get("message", ""))
                return "closed" if "within" in message else "refused"
            return "closed" if answer in (CLOSED, RESET) else f"other:{answer!r:.40}"
        finally:
            await conn.aclose()

    async def guess_line(token: str) -> str:
        answers = await line_exchange(
            run.line_port, [f"A {token}\n".encode()], run.hang_s + AUTH_DELAY_MAX_S
        )
        if answers and answers[0].startswith(b"OK"):
            return "accepted"
        if answers and answers[0] == b"ER 8 wrong token":
            return "refused"
        if not answers or answers[0] == b"" or answers[0].startswith(b"ER 8 no A"):
            return "closed"
        return "other"

    async def guess_console(token: str) -> str:
        status, _ = await login(run.console_port, token, run.hang_s + AUTH_DELAY_MAX_S)
        if status == 200:
            return "accepted"
        return "refused" if status == 401 else "closed" if status in (None, 408) else "other"

    guessers: dict[str, Callable[[str], Awaitable[str]]] = {
        "binary": guess_binary,
        "line": guess_line,
        "console": guess_console,
    }

    async def guesser(door: str, index: int) -> None:
        for turn in range(10_000):
            started = time.monotonic()
            phase.sent += 1
            outcome = await guessers[door](f"guess-{index}-{turn}")
            phase.ends[f"{door}:{outcome}"] += 1
            if outcome in ("refused", "closed"):
                answered.append((started, time.monotonic() - started, door))
            else:
                phase.fail(f"a wrong token on {door}: {outcome}")

    tasks = [asyncio.create_task(guesser(d, i)) for d in guessers for i in range(2)]
    await asyncio.sleep(window_s)
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    # Sorted by when they were sent, the k-th wrong token is the host's k-th failure at the
    # earliest; concurrent ones may be counted in another order, so the k-th is promised only
    # the delay of failure k - len(tasks).
    answered.sort()
    too_fast = 0
    for k, (_, seconds, _) in enumerate(answered, start=1):
        rank = k - len(tasks)
        if rank >= 1:
            promised = min(
                AUTH_DELAY_MIN_S * 2.0 ** (rank - 1), AUTH_DELAY_MAX_S, run.limits.timeout_s
            )
            if seconds < 0.9 * promised:
                too_fast += 1
                phase.fail(f"wrong token {k} answered after {seconds:.2f} s, {promised:g} s due")
            else:
                phase.correct += 1
    phase.figures["guesses_answered"] = len(answered)
    phase.figures["guesses_per_s"] = round(len(answered) / window_s, 2)
    phase.figures["window_s"] = window_s
    phase.figures["slowest_wrong_answer_s"] = round(max((s for _, s, _ in answered), default=0), 2)
    if len(answered) < len(tasks):
        phase.fail(f"only {len(answered)} wrong tokens were answered at all")
    # The right token, on each front-end, right after: no delay.
    timings: dict[str, float] = {}
    started = time.monotonic()
    conn = await open_raw(run.port)
    state = await hello(conn, phase, run.hang_s)
    await conn.aclose()
    timings["binary"] = time.monotonic() - started
    ok = {"binary": state == "welcome"}
    started = time.monotonic()
    answers = await line_exchange(run.line_port, [f"A {TOKEN}\n".encode()], run.hang_s)
    timings["line"] = time.monotonic() - started
    ok["line"] = answers == [b"OK"]
    status, timings["console"] = await login(run.console_port, TOKEN, run.hang_s)
    ok["console"] = status == 200
    phase.figures["right_token_s"] = {k: round(v, 3) for k, v in timings.items()}
    for door, good in ok.items():
        phase.sent += 1
        if good and timings[door] < 1.0:
            phase.correct += 1
        else:
            phase.fail(f"the right token on {door}: ok={good} after {timings[door]:.2f} s")


# ----------------------------------------------------------------------------- disk full

FILE_SIZE_LIMIT = 256 * 1024


def _small_files() -> None:
    """In the child before exec: files stop growing at FILE_SIZE_LIMIT (write() gets EFBIG,
    as on a full disk)."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT, FILE_SIZE_LIMIT))


async def disk_full(workdir: Path, limits: Limits, scale: int, hang_s: float) -> Phase:
    """A second server whose disk is 'full': pipelined INSPECTs are all answered with the right
    value, the ones not logged say ``stored: false``, PONG says unhealthy, the log holds exactly
    the rows acknowledged ``stored: true``."""
    phase = Phase("disk_full")
    started = time.monotonic()
    server = ServerProcess(workdir, config_text=limits.config(), preexec_fn=_small_files)
    server.write_config()
    port = server.start()
    phase.rss_before_kib = server.rss_kib()
    stored: Counter[str] = Counter()
    try:
        async with VisionClient(
            "127.0.0.1", port, request_timeout_s=hang_s, auth_token=TOKEN
        ) as client:
            for round_ in range(3 * scale):
                levels = [(round_ * 37 + i) % 256 for i in range(100)]
                results = await asyncio.gather(
                    *(client.inspect("bright", np.full((48, 64), v, np.uint8)) for v in levels),
                    return_exceptions=True,
                )
                for level, result in zip(levels, results, strict=True):
                    phase.sent += 1
                    if isinstance(result, Busy):
                        phase.busy += 1
                        phase.errors["BUSY"] += 1
                    elif isinstance(result, BaseException):
                        phase.fail(f"INSPECT failed: {result!r}")
                    elif result.data.get("value") != float(level):
                        phase.fail(f"wrong value {result.data.get('value')} for {level}")
                    else:
                        phase.correct += 1
                        stored[str(result.stored).lower()] += 1
            pong = await client.request(lambda rid: Ping(rid, "health"))
            assert isinstance(pong, Pong)
            report = pong.health or {}
        phase.figures["stored"] = dict(stored)
        phase.figures["health_ok"] = report.get("ok")
        phase.figures["result_log"] = report.get("result_log")
        if stored["false"] == 0:
            phase.fail("the disk never filled: no RESULT said stored: false")
        if report.get("ok") is not False:
            phase.fail("PONG said healthy after results were lost")
        failed = (report.get("result_log") or {}).get("failed")
        if failed != stored["false"]:
            phase.fail(f"health counts {failed} lost rows, clients saw {stored['false']}")
    finally:
        phase.rss_after_kib = server.rss_kib()
        phase.hwm_after_kib = status_kib(server.pid, "VmHWM")
        code = server.stop()
    with contextlib.closing(sqlite3.connect(workdir / "results.sqlite3")) as db:
        rows = db.execute("SELECT COUNT(*) FROM results").fetchone()[0]
    phase.figures["rows_in_log"] = rows
    if rows != stored["true"]:
        phase.fail(f"{rows} rows in the log, {stored['true']} RESULTs said stored: true")
    phase.figures["exit_code"] = code
    tracebacks = server.stderr_text().count("Traceback")
    phase.figures["tracebacks"] = tracebacks
    if code != 0 or tracebacks:
        phase.fail(f"the disk-full server exited {code} with {tracebacks} tracebacks")
    phase.seconds = round(time.monotonic() - started, 2)
    return phase


# ----------------------------------------------------------------------------- the run


class RssSampler:
    """VmRSS of a process sampled every 50 ms in a thread (the peak per phase)."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(0.05):
            value = status_kib(self.pid, "VmRSS")
            if value is not None:
                self.peak = max(self.peak, value)

    def take_peak(self) -> int:
        peak, self.peak = self.peak, 0
        return peak

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


PHASES: tuple[tuple[str, Callable[[Run, Phase], Awaitable[None]]], ...] = (
    ("image_bombs", image_bombs),
    ("pre_hello_large", pre_hello_large),
    ("half_bodies", half_bodies),
    ("silent", silent),
    ("slow_bodies", slow_bodies),
    ("non_readers", non_readers),
    ("flood", flood),
    ("reload", reload_under_load),
    ("console_flood", console_flood),
    ("login_bodies", login_bodies),
    ("line_before_token", line_before_token),
    ("unread_answers", unread_answers),
    ("modbus_idle", modbus_idle),
    # Last: its wrong tokens leave loopback at the door's longest delay for wrong tokens.
    ("token_guessing", token_guessing),
)


async def attack(
    server: ServerProcess,
    limits: Limits,
    *,
    scale: int,
    hang_s: float,
    only: set[str],
    ports: dict[str, int],
) -> tuple[list[Phase], dict[str, Any]]:
    run = Run(server.port, limits, scale, hang_s, **ports)
    warmup = Phase("warmup")
    for _ in range(2):
        await good_check(run.port, limits, warmup, hang_s)
    baseline = server.rss_kib() or 0
    bound = memory_bound(limits, baseline)
    sampler = RssSampler(server.pid)
    phases = [warmup]
    peak_seen = [status_kib(server.pid, "VmHWM") or 0]
    try:
        for name, body in PHASES:
            if only and name not in only:
                continue
            phase = Phase(name)
            phase.rss_before_kib = server.rss_kib()
            sampler.take_peak()
            started = time.monotonic()
            try:
                async with asyncio.timeout(20 * hang_s * scale):
                    await body(run, phase)
            except TimeoutError:
                phase.hangs += 1
                phase.fail("the phase did not finish within its bound")
            if not await settled(run.port, hang_s + 4 * limits.timeout_s):
                phase.fail("the server still held connections or bytes after the phase")
            after = Phase(f"{name}:after")
            await good_check(run.port, limits, after, hang_s)
            phase.figures["good_after"] = after.correct == after.sent and after.wrong == 0
            if after.wrong:
                phase.fail(f"a good client after the phase: {after.problems}")
            phase.seconds = round(time.monotonic() - started, 2)
            phase.rss_after_kib = server.rss_kib()
            phase.hwm_after_kib = status_kib(server.pid, "VmHWM")
            phase.figures["rss_peak_sampled_kib"] = sampler.take_peak()
            if not server.alive():
                phase.fail("the server died")
                phases.append(phase)
                break
            # VmHWM is updated lazily by the kernel; the sampled VmRSS peak may be higher.
            phase.hwm_after_kib = max(
                phase.hwm_after_kib or 0, phase.figures["rss_peak_sampled_kib"]
            )
            peak_seen[0] = max(peak_seen[0], phase.hwm_after_kib)
            if (phase.hwm_after_kib or 0) > bound["bound"]:
                phase.fail(f"VmHWM {phase.hwm_after_kib} KiB over the bound {bound['bound']} KiB")
            phases.append(phase)
            print(f"  {summary_line(phase)}", flush=True)
    finally:
        sampler.close()
    return phases, {"baseline_rss_kib": baseline, "memory_bound_kib": bound, "peak": peak_seen[0]}


def summary_line(phase: Phase) -> str:
    errors = ", ".join(f"{k} {v}" for k, v in sorted(phase.errors.items())) or "none"
    return (
        f"{phase.name:16s} sent {phase.sent:5d}  correct {phase.correct:5d}  wrong {phase.wrong}"
        f"  busy {phase.busy}  refused {phase.refused}  hangs {phase.hangs}  errors: {errors}"
        f"  RSS {phase.rss_before_kib}->{phase.rss_after_kib} KiB, HWM {phase.hwm_after_kib} KiB"
        f"  ({phase.seconds} s)"
    )


FRONTEND_LINES = {
    "console_port": re.compile(r"web console on https?://[^:/]+:(\d+)"),
    "line_port": re.compile(r"line protocol on \S+:(\d+)"),
    "modbus_port": re.compile(r"Modbus TCP on \S+:(\d+)"),
}


def frontend_ports(server: ServerProcess) -> dict[str, int]:
    """The other front-ends' ports: ``serve`` prints them right after its "listening on" line,
    the one :meth:`ServerProcess.start` waited for, in this order."""
    assert server.proc is not None
    assert server.proc.stdout is not None
    ports: dict[str, int] = {}
    while len(ports) < len(FRONTEND_LINES):
        line = server.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the server printed no port for {set(FRONTEND_LINES) - set(ports)}")
        for key, pattern in FRONTEND_LINES.items():
            match = pattern.search(line)
            if match:
                ports[key] = int(match[1])
    return ports


def frames_folder(workdir: Path) -> None:
    frames = workdir / "frames"
    frames.mkdir(parents=True, exist_ok=True)
    for i, level in enumerate(FOLDER_LEVELS):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((768, 1024, 3), level, np.uint8))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="the short form (make test)")
    parser.add_argument("--scale", type=int, default=None, help="rounds (default 1 quick, 10)")
    parser.add_argument("--only", default="", help="comma-separated phases (default: all)")
    parser.add_argument("--hang-s", type=float, default=20.0, help="no answer this long: a hang")
    parser.add_argument("--json", type=Path, default=Path("attack.json"))
    args = parser.parse_args(argv)
    scale = args.scale or (1 if args.quick else 10)
    only = {p for p in args.only.split(",") if p}
    limits = Limits()
    started = time.monotonic()
    load_start = os.getloadavg()[0]
    problems: list[str] = []
    with tempfile.TemporaryDirectory(prefix="cellvision-attack-") as tmp:
        workdir = Path(tmp) / "main"
        workdir.mkdir()
        server = ServerProcess(workdir, config_text=limits.config())
        server.write_config()
        frames_folder(workdir)  # large frames in place of the small ones write_config made
        server.start()
        ports = frontend_ports(server)
        print(f"server pid {server.pid} on port {server.port} {ports}; limits {asdict(limits)}")
        try:
            phases, memory = asyncio.run(
                attack(server, limits, scale=scale, hang_s=args.hang_s, only=only, ports=ports)
            )
            hwm = max(status_kib(server.pid, "VmHWM") or 0, memory.pop("peak"))
        finally:
            exit_code = server.stop()
        stderr = server.stderr_text()
        if not only or "disk_full" in only:
            (Path(tmp) / "disk").mkdir()
            disk = asyncio.run(disk_full(Path(tmp) / "disk", limits, scale, args.hang_s))
            print(f"  {summary_line(disk)}", flush=True)
            phases.append(disk)
    tracebacks = stderr.count("Traceback")
    bound = memory["memory_bound_kib"]["bound"]
    for phase in phases:
        problems += [f"{phase.name}: {p}" for p in phase.problems]
        if phase.wrong and not phase.problems:
            problems.append(f"{phase.name}: {phase.wrong} wrong")
        if phase.hangs:
            problems.append(f"{phase.name}: {phase.hangs} hangs")
    if hwm is None or hwm > bound:
        problems.append(f"VmHWM {hwm} KiB over the bound {bound} KiB")
    if exit_code != 0:
        problems.append(f"the server exited {exit_code} on SIGTERM")
    if tracebacks:
        problems.append(f"{tracebacks} tracebacks on the server's stderr")
    summary = {
        "passed": not problems,
        "problems": problems,
        "quick": args.quick,
        "scale": scale,
        "limits": asdict(limits),
        "constants": {
            "decode_bytes_per_pixel": DECODE_BYTES_PER_PIXEL,
            "per_connection_bytes": PER_CONNECTION_BYTES,
            "allocator_bytes": ALLOCATOR_BYTES,
        },
        **memory,
        "vm_hwm_kib": hwm,
        "server": {
            "exit_code": exit_code,
            "tracebacks": tracebacks,
            "stderr_tail": stderr.splitlines()[-60:],
        },
        "seconds": round(time.monotonic() - started, 1),
        "load_average": [round(load_start, 2), round(os.getloadavg()[0], 2)],
        "phases": {p.name: phase_dict(p) for p in phases},
    }
    args.json.write_text(json.dumps(summary, indent=2, default=str) + "\n")
    print(
        f"memory: baseline {memory['baseline_rss_kib']} KiB, VmHWM {hwm} KiB, bound {bound} KiB "
        f"({memory['memory_bound_kib']})"
    )
    print(f"server exit {exit_code}, tracebacks {tracebacks}; {summary['seconds']} s")
    print("PASSED" if not problems else "FAILED: " + "; ".join(problems))
    print(f"summary written to {args.json}")
    return 0 if not problems else 1


def phase_dict(phase: Phase) -> dict[str, Any]:
    out = asdict(phase)
    out["errors"] = dict(phase.errors)
    out["ends"] = dict(phase.ends)
    return out


if __name__ == "__main__":
    sys.exit(main())
