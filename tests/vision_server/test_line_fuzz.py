"""Hostile lines against the line protocol while a good controller keeps working, then the
binary protocol's conformance suite against the same server (issue 20, "Measured").

The short form (2,000 hostile lines) runs in ``make test``; the long form::

    LINE_FUZZ_LINES=20000 python -m pytest tests/vision_server/test_line_fuzz.py -q

Eight connections send random bytes, lines far over the limit, lines cut off by a closed
connection, bad numbers and bad tokens, without waiting for answers. Meanwhile one controller
triggers inspection 2 (a server camera's) again and again in every format and checks each
answer as that controller would parse it. Every answer the hostile connections get must be a
well-formed ``OK``/``ER`` line, and each burst's closing ping is answered. Afterwards
``python -m protocol.conformance`` (its ``main``) passes against the same server.
"""

from __future__ import annotations

import asyncio
import os
import random
import re
from pathlib import Path

import cv2
import numpy as np
from controllers import (
    eki_stream,
    karel_fields,
    karel_read,
    krl_sread,
    rapid_fields,
    rapid_receive_line,
    read_line,
    socket_read_ascii_float,
)
from loopback import run

from protocol.conformance.__main__ import main as conformance_main
from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import FolderCamera, FolderCameraSettings
from vision_server.config import LineSettings, ServerSettings
from vision_server.service.builtin import MeanIntensityPresence, builtin_catalog

LINES = int(os.environ.get("LINE_FUZZ_LINES", "2000"))
CONNECTIONS = 8
MAX_LINE = 256
ANSWER = re.compile(r"^(OK( [ -~]*)?|ER \d+ [ -~]+)$")
"""What a hostile connection may get back: an OK or an error line (it never switches format)."""
BAD_TOKENS = [
    "X",
    "TT 1",
    "T",
    "T 1 2",
    "T a b",
    "F json",
    "F",
    "A",
    "R 77",
    "R nope",
    "L extra",
    "P P",
    "T nope",
    "t\t1",
    "   ",
]
BAD_NUMBERS = ["-1", "1.5", "99999999999999999999999", "1e3", "0x1", "+1", "", "0", "007"]


def hostile_lines(rng: random.Random, count: int) -> list[bytes]:
    """``count`` lines, each ended by LF, of every hostile kind."""
    lines: list[bytes] = []
    for _ in range(count):
        kind = rng.randrange(5)
        if kind == 0:  # random bytes (any byte, LF included: it cuts lines anywhere)
            line = rng.randbytes(rng.randrange(1, 120))
            if b"q" in line.lower():  # a Q line would end the connection before its probe
                line = line.lower().replace(b"q", b"?")
        elif kind == 1:  # far over the limit
            line = bytes(rng.choice(b"T 1PLR9 ") for _ in range(rng.randrange(MAX_LINE, 5000)))
        elif kind == 2:
            line = f"T {rng.choice(BAD_NUMBERS)}".encode()
        elif kind == 3:
            line = rng.choice(BAD_TOKENS).encode()
        else:  # well-formed requests between the rest, pipelined
            line = rng.choice([b"T 1", b"R", b"L", b"P", b"R 1", b"T part"])
        lines.append(line + (b"\r\n" if rng.random() < 0.5 else b"\n"))
    return lines


async def drain(reader: asyncio.StreamReader, bad: list[str]) -> list[str]:
    """Read a hostile connection's answers until it closes; keep the malformed ones."""
    answers: list[str] = []
    while line := await reader.readline():
        text = line.decode("ascii", "replace").rstrip("\r\n")
        answers.append(text)
        if not ANSWER.match(text):
            bad.append(text)
    return answers


async def attacker(port: int, lines: list[bytes], rng: random.Random, bad: list[str]) -> int:
    """Send ``lines`` in bursts without waiting for answers, each burst ended by a ping whose
    answer must be the connection's last; now and then cut a line off by closing the
    connection, then connect again. Returns how many answers came."""
    answered = 0
    index = 0
    while index < len(lines):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        draining = asyncio.create_task(drain(reader, bad))
        burst = lines[index : index + rng.randrange(20, 200)]
        index += len(burst)
        for line in burst:
            writer.write(line)
        writer.write(b"\nP\n")  # the LF ends whatever the burst left open
        if rng.random() < 0.3:  # a half-sent line, then the connection drops
            writer.write(b"T 1 and then noth")
        await writer.drain()
        writer.write_eof()  # the server answers what it has, then sees the end
        answers = await draining
        writer.close()
        answered += len(answers)
        if not answers or answers[-1] != "OK PONG":
            bad.append(f"a burst's last answer is {answers[-1:]!r}, not the ping's")
    return answered


async def good_controller(port: int, done: asyncio.Event) -> list[str]:
    """Trigger inspection 2 in every format until ``done``; returns the failures."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    failures: list[str] = []
    rounds = 0

    async def ask(text: str) -> None:
        writer.write(text.encode("ascii") + b"\n")
        await writer.drain()

    while not done.is_set() or rounds < 5:
        fmt = ["text", "ur", "abb", "kuka", "fanuc"][rounds % 5]
        rounds += 1
        await ask(f"F {fmt}")
        ack = await read_line(reader)
        await ask("T 2")
        if fmt == "text":
            got: object = await read_line(reader)
            ok = got == "OK 1 100.000"
        elif fmt == "ur":
            got = await socket_read_ascii_float(reader, 2, 12.0)
            ok = got == [2.0, 1.0, 100.0]
        elif fmt == "abb":
            got = await rapid_receive_line(reader)
            ok = rapid_fields(got or "", 2) == [1.0, 100.0]
        elif fmt == "kuka":
            got = await eki_stream(reader)
            ok = krl_sread(got or "", "%d %f") == [1.0, 100.0]
        else:
            got = await karel_read(reader, 26, 80)
            ok = karel_fields(got or "", 2) == [1.0, 100.0]
        if ack != f"OK {fmt.upper()}" or not ok:
            failures.append(f"{fmt}: {ack!r} then {got!r}")
    writer.close()
    return failures


def test_hostile_lines_disturb_neither_a_good_controller_nor_the_binary_protocol(
    tmp_path: Path,
) -> None:
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), 100, np.uint8))
    camera = FolderCamera("shelf", FolderCameraSettings(tmp_path / "imgs"))
    camera.open()
    builtin = builtin_catalog()
    catalog = Catalog.build(
        [*builtin.cameras.values(), camera],
        [*builtin.inspections.values(), MeanIntensityPresence("part", "shelf", 10.0, 255.0)],
    )
    line = LineSettings(enabled=True, port=0, max_line_bytes=MAX_LINE, max_connections=16)
    app = App(catalog, ServerSettings(port=0, workers=2), line=line)
    rng = random.Random(20)
    per_connection = [hostile_lines(rng, LINES // CONNECTIONS) for _ in range(CONNECTIONS)]

    async def body() -> tuple[list[str], list[str], list[str], int]:
        async with app:
            assert app.line is not None
            port = app.line.port
            done = asyncio.Event()
            good = asyncio.create_task(good_controller(port, done))
            bad: list[str] = []
            answered = await asyncio.gather(
                *(
                    attacker(port, lines, random.Random(i), bad)
                    for i, lines in enumerate(per_connection)
                )
            )
            done.set()
            failures = await good
            # Afterwards: a fresh controller, and the binary protocol's conformance suite.
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"L\nT 2\n")
            after = [await read_line(reader), await read_line(reader)]
            writer.close()
            conformance = await asyncio.to_thread(conformance_main, [f"127.0.0.1:{app.port}"])
            assert sum(answered) >= LINES // 2, "most hostile lines are answered"
            return failures, bad, after, conformance

    try:
        failures, bad, after, conformance = run(body(), timeout_s=60.0 + LINES / 50)
    finally:
        camera.close()
    assert failures == []
    assert bad == []
    assert after == ["OK 2 1=brightness 2=part", "OK 1 100.000"]
    assert conformance == 0, "the conformance suite failed (its report is above)"
