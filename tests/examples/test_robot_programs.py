"""The example robot programs in examples/robots/ against a real server: a test client performs
each program's socket calls in the program's order and reads the answers as that controller's
functions do (tests/helpers/controllers.py). Each program declares the format it switches to
and how many numbers it reads (``cellvision: format F, numbers N``); that must be what the
server answers for the example inspection."""

from __future__ import annotations

import asyncio
import re
import xml.etree.ElementTree as ET
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
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

from vision_server.app import App
from vision_server.config import ServerSettings
from vision_server.frontends.line import answerable
from vision_server.service import CellRuntime

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"
CALL = re.compile(
    r'(socket_send_line)\("([^"]*)"|(socket_read_line)\(|(socket_read_ascii_float)\((\d+)'
)
DECLARED = re.compile(r"cellvision: format (\w+), numbers (\d+)")

CELL = """\
server: {port: 0}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - {name: part_present, type: presence, camera: shelf, measure: mean_intensity, min: 10,
     number: 1, output: {fields: [value], decimals: 2}}
line: {enabled: true, port: 0}
"""
EXPECTED = [1.0, 100.0]
"""What every example reads for inspection 1 on the grey image: pass, and its mean of 100."""

Conversation = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[list[object]]]


def program(*parts: str, comment: str) -> tuple[str, str, int]:
    """The example's text without comments, and the format and count it declares."""
    text = (ROBOTS.joinpath(*parts)).read_text(encoding="utf-8")
    found = DECLARED.search(text)
    assert found, f"{'/'.join(parts)} declares no 'cellvision: format F, numbers N'"
    code = "\n".join(line.split(comment, 1)[0] for line in text.splitlines())
    return code, found.group(1), int(found.group(2))


@contextmanager
def cell(tmp_path: Path) -> Iterator[CellRuntime]:
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), 100, np.uint8))
    (tmp_path / "cell.yaml").write_text(CELL, encoding="utf-8")
    runtime = CellRuntime(tmp_path / "cell.yaml")
    try:
        yield runtime
    finally:
        runtime.close()


def converse(tmp_path: Path, numbers: int, conversation: Conversation) -> list[object]:
    """Run ``conversation`` on one connection to a real server for the example cell; checks
    first that the example reads as many numbers as the server answers (the verdict and the
    values the inspection's output declares)."""
    with cell(tmp_path) as runtime:
        output = answerable(runtime.catalog.inspection("part_present")).output
        assert numbers == 1 + len(output.fields), "the program reads another count"

        async def body() -> list[object]:
            app = App(runtime.catalog, ServerSettings(port=0), line=runtime.config.line)
            async with app:
                assert app.line is not None
                reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
                try:
                    return await conversation(reader, writer)
                finally:
                    writer.close()

        return run(body())


def test_the_ur_program_gets_its_verdict_and_value(tmp_path: Path) -> None:
    script, fmt, numbers = program("ur", "vision_check.script", comment="#")
    calls = [m.groups() for m in CALL.finditer(script)]
    assert calls, "the script makes no socket calls"
    assert ("socket_send_line", f"F {fmt}", None, None, None) in calls

    async def conversation(
        reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> list[object]:
        got: list[object] = []
        for send, text, read_line_call, read_floats, count in calls:
            if send:
                writer.write(text.encode("ascii") + b"\n")  # socket_send_line adds LF
            elif read_line_call:
                got.append(await read_line(reader, 2.0))
            elif read_floats:
                assert int(count) == numbers
                got.append(await socket_read_ascii_float(reader, int(count), 12.0))
        return got

    # What the program's branches test: the count read, then a verdict of 1 and the value.
    assert converse(tmp_path, numbers, conversation) == ["OK UR", [2.0, *EXPECTED]]


def test_the_abb_module_gets_its_verdict_and_value(tmp_path: Path) -> None:
    module, fmt, numbers = program("abb", "VisionCheck.mod", comment="!")
    main = module.split("PROC vision_check()", 1)[1].split("ENDPROC", 1)[0]
    sends = [
        s.replace("\\0A", "\n") for s in re.findall(r'SocketSend vision \\Str:="([^"]*)"', main)
    ]
    assert sends == [f"F {fmt}\n", "T 1\n"]
    assert main.count("ReceiveLine;") == len(sends)  # one answer line read after each request
    assert main.count("StrToVal(") == numbers

    async def conversation(
        reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> list[object]:
        got: list[object] = []
        for line in sends:
            writer.write(line.encode("ascii"))
            got.append(await rapid_receive_line(reader))
        return got

    answers = converse(tmp_path, numbers, conversation)
    assert answers[0] == "OK ABB\r\n"
    assert rapid_fields(str(answers[-1]), numbers) == EXPECTED


def test_the_kuka_program_gets_its_verdict_and_value(tmp_path: Path) -> None:
    krl, fmt, numbers = program("kuka", "vision_check.src", comment=";")
    config = ET.parse(ROBOTS / "kuka" / "VisionCheck.xml").getroot()
    element = config.find("RECEIVE/RAW/ELEMENT")
    assert element is not None
    assert (element.get("Type"), element.get("EOS")) == ("STREAM", "13,10")
    size = int(element.get("Size", "0"))
    assert re.search(rf"DECL CHAR answer\[{size}\]", krl), "answer[] is not the stream's Size"
    requests = re.findall(r'^\s*Ask\("([^"]*)"\)', krl, re.MULTILINE)
    assert requests == [f"F {fmt}", "T 1"]
    found = re.search(r'SREAD\(answer\[\], st, offset, "([^"]*)"', krl)
    assert found
    sread_format = found.group(1)
    assert sread_format.count("%") == numbers

    async def conversation(
        reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> list[object]:
        got: list[object] = []
        for request in requests:
            writer.write(request.encode("ascii") + b"\r\n")  # Ask appends CR LF
            got.append(await eki_stream(reader, size))
        return got

    answers = converse(tmp_path, numbers, conversation)
    assert answers[0] == "OK KUKA"
    assert krl_sread(str(answers[-1]), sread_format) == EXPECTED


def test_the_fanuc_program_gets_its_verdict_and_value(tmp_path: Path) -> None:
    karel, fmt, numbers = program("fanuc", "vision_check.kl", comment="--")
    declared = re.search(r"answer : STRING\[(\d+)\]", karel)
    assert declared
    steps = re.findall(
        r"WRITE vision \('([^']*)', CHR\(13\), CHR\(10\)\)|READ vision \(answer::(\d+)\)", karel
    )
    assert steps[0] == (f"F {fmt}", "")
    assert karel.count("CNV_STR_REAL(") == numbers
    assert int(steps[-1][1]) == 12 * numbers + 2  # the answer's fixed length

    async def conversation(
        reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> list[object]:
        got: list[object] = []
        for text, length in steps:
            if length:
                got.append(await karel_read(reader, int(length), int(declared.group(1))))
            else:
                writer.write(text.encode("ascii") + b"\r\n")
        return got

    answers = converse(tmp_path, numbers, conversation)
    assert answers[0] == "OK FANUC\r\n"
    assert karel_fields(str(answers[-1]), numbers) == EXPECTED
