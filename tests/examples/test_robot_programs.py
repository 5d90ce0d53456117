"""The example robot programs in examples/robots/ against a real server: a test client performs
each program's socket calls in the program's order and reads the answers as that controller's
functions do (tests/helpers/controllers.py)."""

from __future__ import annotations

import asyncio
import re
from pathlib import Path

import cv2
import numpy as np
from controllers import read_line, socket_read_ascii_float
from loopback import run

from vision_server.app import App
from vision_server.runtime import CellRuntime
from vision_server.settings import ServerSettings

ROBOTS = Path(__file__).resolve().parents[2] / "examples" / "robots"
CALL = re.compile(
    r'(socket_send_line)\("([^"]*)"|(socket_read_line)\(|(socket_read_ascii_float)\((\d+)'
)

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


def test_the_ur_program_gets_its_verdict_and_value(tmp_path: Path) -> None:
    text = (ROBOTS / "ur" / "vision_check.script").read_text(encoding="utf-8")
    script = "\n".join(line.split("#", 1)[0] for line in text.splitlines())  # no comments
    calls = [m.groups() for m in CALL.finditer(script)]
    assert calls, "the script makes no socket calls"
    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), 100, np.uint8))
    (tmp_path / "cell.yaml").write_text(CELL, encoding="utf-8")
    runtime = CellRuntime(tmp_path / "cell.yaml")

    async def body() -> list[object]:
        app = App(runtime.catalog, ServerSettings(port=0), line=runtime.config.line)
        async with app:
            assert app.line is not None
            reader, writer = await asyncio.open_connection("127.0.0.1", app.line.port)
            got: list[object] = []
            for send, text, read_line_call, read_floats, count in calls:
                if send:
                    writer.write(text.encode("ascii") + b"\n")  # socket_send_line adds LF
                elif read_line_call:
                    got.append(await read_line(reader, 2.0))
                elif read_floats:
                    got.append(await socket_read_ascii_float(reader, int(count), 12.0))
            writer.close()
            return got

    try:
        answers = run(body())
    finally:
        runtime.close()
    # What the program's branches test: the count read, then a verdict of 1 and the value.
    assert answers == ["OK UR", [2.0, 1.0, 100.0]]
