"""The line protocol (protocol/LINE.md) through real sockets on loopback: grammar, errors,
auth, formats, one trigger at a time, many controllers at once, faults."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from dataclasses import replace
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
    real32,
    socket_read_ascii_float,
)
from loopback import Gate, run, wait_until

from vision_server import Catalog
from vision_server.app import App
from vision_server.cameras import FolderCamera, FolderCameraSettings
from vision_server.config import LineSettings, ServerSettings
from vision_server.service import CellRuntime

CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    output: {decimals: 2}
  - name: dark
    type: presence
    camera: shelf
    measure: mean_intensity
    max: 10
    number: 7
line: {enabled: true, port: 0, max_line_bytes: 64}
"""
MEAN = 100.0
"""The grey level of the replayed image: ``bright`` passes, ``dark`` fails."""


def write_cell(tmp_path: Path, extra: str = "", config: str = CONFIG) -> Path:
    (tmp_path / "imgs").mkdir(exist_ok=True)
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), int(MEAN), np.uint8))
    path = tmp_path / "cell.yaml"
    path.write_text(config + extra, encoding="utf-8")
    return path


@contextlib.asynccontextmanager
async def serving(
    tmp_path: Path, *, token: str | None = None, config: str = CONFIG, **line: object
) -> AsyncIterator[App]:
    runtime = CellRuntime(write_cell(tmp_path, config=config))
    settings = replace(runtime.config.line, **line)  # type: ignore[arg-type]
    app = App(runtime.catalog, ServerSettings(port=0, auth_token=token), line=settings)
    try:
        async with app:
            yield app
    finally:
        runtime.close()


class Controller:
    """One controller's connection: send a line, read the answer."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def connect(cls, app: App) -> Controller:
        assert app.line is not None
        return cls(*await asyncio.open_connection("127.0.0.1", app.line.port))

    async def ask(self, line: str) -> str:
        self.writer.write(line.encode("ascii") + b"\r\n")
        await self.writer.drain()
        return await read_line(self.reader)

    def close(self) -> None:
        self.writer.close()


def test_trigger_by_number_and_name_list_ping_and_last_result(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path) as app:
            robot = await Controller.connect(app)
            assert await robot.ask("P") == "OK PONG"
            assert await robot.ask("L") == "OK 2 1=bright 7=dark"
            assert await robot.ask("T 1") == "OK 1 100.00"  # decimals: 2
            assert await robot.ask("R") == "OK 1 100.00"
            assert await robot.ask("t dark") == "OK 0 100.000"  # default 3 decimals, fails
            assert await robot.ask("R") == "OK 0 100.000"
            assert await robot.ask("R bright") == "OK 1 100.00"  # the newest of that one
            assert await robot.ask("Q") == "OK BYE"
            assert await read_line(robot.reader) == ""  # closed
            robot.close()

    run(body())


def test_every_malformed_line_gets_an_error_line_and_the_connection_goes_on(
    tmp_path: Path,
) -> None:
    async def body() -> None:
        async with serving(tmp_path) as app:
            robot = await Controller.connect(app)
            assert (await robot.ask("X 1")).startswith("ER 4 unknown command 'X'")
            assert (await robot.ask("T")).startswith("ER 16 T takes 1 to 8 argument(s), got 0")
            assert (await robot.ask("P now")).startswith("ER 16 ")
            assert (await robot.ask("T 3")).startswith("ER 10 no inspection number 3")
            assert (await robot.ask("T nope")).startswith("ER 10 no inspection named 'nope'")
            assert (await robot.ask("R")).startswith("ER 16 no trigger on this connection")
            assert (await robot.ask("F json")).startswith("ER 16 no format 'json'")
            robot.writer.write(b"T \xff1\n")
            assert (await read_line(robot.reader)).startswith("ER 1 byte 2 of the line is 0xff")
            # Longer than max_line_bytes (64): answered once, skipped up to its LF.
            robot.writer.write(b"T " + b"9" * 200 + b"\n")
            assert (await read_line(robot.reader)).startswith("ER 3 line longer than 64 bytes")
            robot.writer.write(b"\r\n   \n")  # blank lines ask nothing
            assert await robot.ask("T 1") == "OK 1 100.00"  # the connection is intact
            robot.close()

    run(body())


def test_a_token_is_asked_for_as_the_first_line(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, token="s3cret") as app:
            robot = await Controller.connect(app)
            assert (await robot.ask("T 1")).startswith("ER 8 send A <token> first")
            assert await read_line(robot.reader) == ""  # and closed
            robot.close()
            robot = await Controller.connect(app)
            assert (await robot.ask("A wrong")).startswith("ER 8 wrong token")
            assert await read_line(robot.reader) == ""
            robot.close()
            robot = await Controller.connect(app)
            assert await robot.ask("A s3cret") == "OK"
            assert await robot.ask("T 1") == "OK 1 100.00"
            robot.close()

    run(body())


def test_ur_format_is_read_by_socket_read_ascii_float(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, format="ur") as app:
            robot = await Controller.connect(app)
            for _ in range(2):  # the CR LF after the first answer does not disturb the next
                robot.writer.write(b"T 1\n")
                assert await socket_read_ascii_float(robot.reader, 2) == [2.0, 1.0, 100.0]
            # A failure is the negated code, padded to the count the program reads.
            robot.writer.write(b"T 3\n")
            failed = await socket_read_ascii_float(robot.reader, 1)
            assert failed == [1.0, -10.0]  # (-10): unknown inspection
            # A program that reads another count than the answer has sees a failed read.
            robot.writer.write(b"T 1\n")
            bad = await socket_read_ascii_float(robot.reader, 3)
            assert bad[0] == 0.0
            # F switches this connection to text lines; others keep the configured format.
            assert await robot.ask("F text") == "OK TEXT"
            assert await robot.ask("T 7") == "OK 0 100.000"
            robot.close()

    run(body())


CONTROLLER_CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: pose
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    output:
      fields: [value, {name: value, scale: -0.0123, decimals: 4}, {name: value, scale: 1000}]
      decimals: 2
  - name: wide
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    output: {fields: [value, value, value, value, value, value, value, value], decimals: 6}
  - name: huge
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
    output: {fields: [{name: value, scale: 1000000, decimals: 6}]}
line: {enabled: true, port: 0}
"""
POSE = [1.0, 100.0, real32(-1.23), 100000.0]
"""What a controller holds after ``T 1`` (pose): the verdict, then 100.00, -1.2300, 100000.00,
each a 32-bit REAL."""


def test_abb_format_is_read_by_socket_receive_and_str_to_val(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, config=CONTROLLER_CONFIG) as app:
            robot = await Controller.connect(app)
            assert await robot.ask("F abb") == "OK ABB"
            for _ in range(2):  # answer after answer, as a RAPID loop reads them
                robot.writer.write(b"T 1\n")
                answer = await rapid_receive_line(robot.reader)
                assert answer == "1,100.00,-1.2300,100000.00\r\n"
                assert rapid_fields(answer, 4) == POSE
            # A failure: the negated code, then a 0 for each value (the count stays).
            robot.writer.write(b"T 9\n")
            assert rapid_fields(await rapid_receive_line(robot.reader) or "", 1) == [-10.0]
            # 9 fields of 10 characters do not fit RAPID's 80: refused, never cut.
            robot.writer.write(b"T 2\n")
            assert await rapid_receive_line(robot.reader) == "-16\r\n"
            robot.close()

    run(body())


def test_kuka_format_is_read_by_an_eki_stream_and_sread(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, config=CONTROLLER_CONFIG, format="kuka") as app:
            robot = await Controller.connect(app)
            for _ in range(2):
                robot.writer.write(b"T pose\n")
                answer = await eki_stream(robot.reader)
                assert answer == "1 100.00 -1.2300 100000.00"
                assert answer is not None
                assert krl_sread(answer, "%d %f %f %f") == POSE
            robot.writer.write(b"T 2\n")
            wide = await eki_stream(robot.reader)
            assert wide is not None
            assert krl_sread(wide, "%d" + " %f" * 8) == [1.0] + [100.0] * 8
            robot.writer.write(b"T 9\n")
            assert krl_sread(await eki_stream(robot.reader) or "", "%d") == [-10.0]
            robot.close()

    run(body())


def test_fanuc_format_is_read_by_karel_read_and_cnv_str_real(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, config=CONTROLLER_CONFIG, format="fanuc") as app:
            robot = await Controller.connect(app)
            length = 4 * 12 + 2  # four fields of 12 characters and CR LF
            for _ in range(2):
                robot.writer.write(b"T 1\n")
                answer = await karel_read(robot.reader, length, declared=80)
                assert answer == "000000000001000000100.00-000001.2300000100000.00\r\n"
                assert answer is not None
                assert karel_fields(answer, 4) == POSE
            # A failure keeps the length the program reads: -21 would read as -00000000021.
            robot.writer.write(b"T 9\n")
            unknown = await karel_read(robot.reader, 12 + 2, declared=80)
            assert unknown is not None
            assert karel_fields(unknown, 1) == [-10.0]
            # 100000000.000000 has 16 characters: refused rather than cut.
            robot.writer.write(b"T 3\n")
            huge = await karel_read(robot.reader, 12 + 2, declared=80)
            assert huge is not None
            assert karel_fields(huge, 1) == [-16.0]
            robot.close()

    run(body())


def gate_app(
    tmp_path: Path, gate: Gate, *, server: ServerSettings | None = None, **line: object
) -> tuple[App, FolderCamera]:
    write_cell(tmp_path)
    camera = FolderCamera("shelf", FolderCameraSettings(tmp_path / "imgs"))
    camera.open()
    gate = replace(gate, camera="shelf") if gate.camera != "shelf" else gate
    catalog = Catalog.build([camera], [gate])
    settings = LineSettings(enabled=True, port=0, **line)  # type: ignore[arg-type]
    served = server or ServerSettings(port=0, workers=4)
    return App(catalog, served, line=settings), camera


def test_a_trigger_waits_for_a_busy_server_instead_of_being_refused(tmp_path: Path) -> None:
    """Controllers wait for their answer: with the only worker held, a second controller's
    trigger waits for the slot (within its deadline) and is answered, not refused BUSY."""
    gate = Gate(camera="shelf")

    async def body() -> None:
        server = ServerSettings(port=0, workers=1, queue_depth=0, fast_workers=0)
        app, camera = gate_app(tmp_path, gate, server=server)
        async with app:
            first, second = await Controller.connect(app), await Controller.connect(app)
            first.writer.write(b"T gate\n")
            await wait_until(lambda: gate.entered == 1, "the first trigger runs")
            second.writer.write(b"T gate\n")
            await wait_until(lambda: app.service.pool.waiting == 1, "the second one waits")
            gate.release.set()
            assert await read_line(first.reader) == "OK 1"
            assert await read_line(second.reader) == "OK 1"
            assert app.service.busy_count == 0
            first.close()
            second.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_one_trigger_at_a_time_per_connection_and_many_controllers_at_once(
    tmp_path: Path,
) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate)
        async with app:
            first = await Controller.connect(app)
            # Two triggers and a ping sent at once: the second waits for the first's answer.
            first.writer.write(b"T gate\nT 1\nP\n")
            await wait_until(lambda: gate.entered == 1, "the first trigger runs")
            # Meanwhile other controllers are served, and a dropped one and a half-sent line
            # disturb nobody.
            others = [await Controller.connect(app) for _ in range(5)]
            dropped = await Controller.connect(app)
            dropped.writer.write(b"T ga")
            dropped.writer.transport.abort()
            half = await Controller.connect(app)
            half.writer.write(b"T 1")
            answers = await asyncio.gather(*(c.ask("P") for c in others))
            assert answers == ["OK PONG"] * 5
            assert gate.entered == 1  # the second trigger of `first` has not started
            gate.release.set()
            assert await read_line(first.reader) == "OK 1"  # Gate has no summary values
            assert await read_line(first.reader) == "OK 1"
            assert await read_line(first.reader) == "OK PONG"
            assert gate.entered == 2
            for c in [first, half, *others]:
                c.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_a_timed_out_trigger_answers_with_an_error_line(tmp_path: Path) -> None:
    gate = Gate(camera="shelf")

    async def body() -> None:
        app, camera = gate_app(tmp_path, gate, deadline_s=0.2)
        async with app:
            robot = await Controller.connect(app)
            answer = await robot.ask("T gate")
            assert answer.startswith("ER 21 not done within the request's deadline of 200 ms")
            gate.release.set()
            await wait_until(lambda: gate.finished == 1, "the late run ended")
            assert await robot.ask("P") == "OK PONG"
            robot.close()
        camera.close()

    try:
        run(body())
    finally:
        gate.release.set()


def test_idle_and_half_sent_lines_time_out_with_an_error_line(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, idle_timeout_s=0.2) as app:
            robot = await Controller.connect(app)
            robot.writer.write(b"T 1")  # never finished
            line = await read_line(robot.reader)
            assert line.startswith("ER 21 no complete line for 0.2 s; closing")
            assert await read_line(robot.reader) == ""
            robot.close()

    run(body())


def test_connections_beyond_the_limit_are_refused_with_an_error_line(tmp_path: Path) -> None:
    async def body() -> None:
        async with serving(tmp_path, max_connections=1) as app:
            first = await Controller.connect(app)
            assert await first.ask("P") == "OK PONG"
            second = await Controller.connect(app)
            assert (await read_line(second.reader)).startswith("ER 20 too many connections")
            second.close()
            first.close()

    run(body())


def test_output_and_number_errors_name_the_file_line_and_key(tmp_path: Path) -> None:
    from vision_server.config import ConfigError, load_config

    base = CONFIG.replace("    output: {decimals: 2}\n", "    output: {fields: [value, u]}\n")
    try:
        load_config(write_cell(tmp_path, config=base))
    except ConfigError as exc:
        text = str(exc)
    else:
        raise AssertionError("an unknown output field was accepted")
    assert "cell.yaml:11 inspections[0] (name='bright') -> output -> fields[1]" in text
    assert "presence results have no summary value 'u' (there are: value)" in text

    clash = CONFIG.replace("    number: 7\n", "    number: 1\n")
    try:
        load_config(write_cell(tmp_path, config=clash))
    except ConfigError as exc:
        text = str(exc)
    else:
        raise AssertionError("two inspections with number 1 were accepted")
    assert "inspections[1] (name='dark') -> number" in text
    assert "number 1 (its number:), which inspection 'bright' already has" in text
