"""The C client example (examples/clients/c) is built with the system's ``cc`` and run against
live servers (the built-in demo, a server that requires a token) and against scripted servers
that answer out of order, with unusual JSON, errors and broken frames.

It is the proof that SPEC.md is enough to write a client in C. Where no C compiler exists the
tests skip, saying so; nothing is installed.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import socketserver
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from loopback import server_in_thread

from protocol import HEADER_SIZE, PROTOCOL_VERSION, FrameDecoder, MessageType
from protocol.constants import HEADER, MAGIC
from protocol.frames import Frame

REPO_ROOT = Path(__file__).resolve().parents[2]
SOURCE = REPO_ROOT / "examples" / "clients" / "c"
CFLAGS = ["-std=c11", "-Wall", "-Wextra", "-Werror", "-pedantic"]
T = MessageType

# Exit statuses, as examples/clients/c/README.md documents them.
PASS, FAIL, USAGE, CONNECTION, PROTOCOL, SERVER_ERROR = range(6)


@pytest.fixture(scope="module")
def clients(tmp_path_factory: pytest.TempPathFactory) -> dict[int, Path]:
    """The client built twice: offering protocol 1.0 (the default) and 1.1 (-DCV_MINOR=1)."""
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler: `cc` is not on PATH, so examples/clients/c cannot be built")
    out = tmp_path_factory.mktemp("cvclient")
    built = {}
    for minor in (0, 1):
        binary = out / f"cvclient-1.{minor}"
        sources = [str(SOURCE / name) for name in ("cvclient.c", "cv_wire.c", "cv_json.c")]
        compiled = subprocess.run(
            [cc, *CFLAGS, f"-DCV_MINOR={minor}", "-o", str(binary), *sources],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert compiled.returncode == 0, compiled.stderr  # warnings are errors (-Werror)
        built[minor] = binary
    return built


@pytest.fixture
def cvclient(clients: dict[int, Path]) -> Path:
    return clients[0]


def run_client(
    binary: Path, address: str, *args: str, env: dict[str, str] | None = None
) -> tuple[int, list[str]]:
    """Runs the client; (exit status, its stdout lines), or for a usage error, which it
    reports before doing anything, (USAGE, its stderr lines)."""
    environment = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    environment.update(env or {})
    done = subprocess.run(
        [str(binary), address, *args],
        capture_output=True,
        text=True,
        encoding="utf-8",
        timeout=60,
        env=environment,
    )
    if done.returncode == USAGE:
        assert done.stdout == ""
        return USAGE, done.stderr.splitlines()
    lines = done.stdout.splitlines()
    assert lines, done.stderr
    assert lines[-1] == f"exit {done.returncode}", done.stdout + done.stderr
    return done.returncode, lines


# ----------------------------------------------------------------------------- live servers


@pytest.mark.parametrize(("gray", "status", "verdict"), [(64, PASS, "pass"), (63, FAIL, "fail")])
def test_one_inspection_against_the_builtin_demo(
    cvclient: Path, gray: int, status: int, verdict: str
) -> None:
    """The demo's `brightness` passes a mean gray level of 64..255: the boundary shows that the
    pixels arrived as sent."""
    with server_in_thread() as server:
        port = server.port
        code, lines = run_client(cvclient, f"127.0.0.1:{port}", "--gray", str(gray))
    assert code == status, lines
    assert lines[:5] == [
        f"connected 127.0.0.1 port {port}",
        "hello id=1 versions=[[1,0]] token=no",
        'welcome id=1 version=1.0 server="cellvision"',
        'inspect id=2 inspection="brightness" image=gray8 64x48',
        "ping id=3",
    ]
    # The two answers, in whatever order the server sent them (matched by request id).
    assert sorted(lines[5:7]) == [
        'pong id=3 data="cvclient"',
        f'result id=2 inspection="brightness" verdict={verdict}',
    ]
    assert lines[7:] == ["close sent", 'close received reason="closing"', f"exit {status}"]


def test_a_raw_image_file(cvclient: Path, tmp_path: Path) -> None:
    # 8x4 pixels: rows of 0 and 255 alternate, so the mean is 127.5 (pass); then all 60 (fail).
    image = tmp_path / "part.gray"
    image.write_bytes((b"\x00" * 8 + b"\xff" * 8) * 2)
    dark = tmp_path / "dark.gray"
    dark.write_bytes(b"\x3c" * 32)
    size = ["--width", "8", "--height", "4"]
    with server_in_thread() as server:
        address = f"127.0.0.1:{server.port}"
        passed = run_client(cvclient, address, "--image", str(image), *size)
        failed = run_client(cvclient, address, "--image", str(dark), *size)
    assert passed[0] == PASS
    assert 'result id=2 inspection="brightness" verdict=pass' in passed[1]
    assert failed[0] == FAIL
    assert 'result id=2 inspection="brightness" verdict=fail' in failed[1]
    # 32 bytes are not 9x4 pixels: refused before connecting anywhere.
    short = subprocess.run(
        [str(cvclient), "127.0.0.1:1", "--image", str(dark), "--width", "9", "--height", "4"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert short.returncode == USAGE
    assert "must hold exactly 9x4 = 36 bytes of gray8" in short.stderr
    assert short.stdout == ""


def test_an_unknown_inspection_is_the_servers_error(cvclient: Path) -> None:
    with server_in_thread() as server:
        code, lines = run_client(cvclient, f"127.0.0.1:{server.port}", "--inspection", "nope")
    assert code == SERVER_ERROR
    error = next(line for line in lines if line.startswith("error id=2 "))
    assert error.startswith('error id=2 code=10 name="UNKNOWN_INSPECTION" fatal=false message="')
    assert 'close received reason="closing"' in lines


@contextlib.contextmanager
def vision_server_with_token(token_file: Path) -> Iterator[str]:
    """``vision-server serve --token-file`` (the built-in demo) on port 0; yields HOST:PORT."""
    serve = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--port", "0"]
        + ["--token-file", str(token_file)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert serve.stdout is not None
        line = serve.stdout.readline()
        match = re.match(r"vision-server listening on (\S+):(\d+)", line)
        assert match, line
        yield f"{match[1]}:{match[2]}"
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(30)
        if serve.stdout is not None:
            serve.stdout.close()


def test_a_server_that_requires_a_token(cvclient: Path, tmp_path: Path) -> None:
    server_token = tmp_path / "server.token"
    server_token.write_text("cell-7-secret\n")
    client_token = tmp_path / "client.token"
    client_token.write_text("  cell-7-secret\n")  # surrounding whitespace is not the token
    wrong = tmp_path / "wrong.token"
    wrong.write_text("cell-8\n")
    with vision_server_with_token(server_token) as address:
        none = run_client(cvclient, address)
        from_env = run_client(cvclient, address, env={"CELLVISION_TOKEN": "cell-7-secret"})
        from_option = run_client(cvclient, address, "--token-file", str(client_token))
        from_env_file = run_client(
            cvclient, address, env={"CELLVISION_TOKEN_FILE": str(client_token)}
        )
        wrong_token = run_client(cvclient, address, "--token-file", str(wrong))
        empty = run_client(cvclient, address, env={"CELLVISION_TOKEN": ""})
    for code, lines in (none, wrong_token):
        assert code == SERVER_ERROR, lines
        assert any(
            line.startswith('error id=1 code=8 name="NOT_AUTHENTICATED" fatal=true')
            for line in lines
        ), lines
        assert not any(line.startswith("welcome") for line in lines)
    for code, lines in (from_env, from_option, from_env_file):
        assert code == PASS, lines
        assert "hello id=1 versions=[[1,0]] token=yes" in lines
        assert any(line.endswith("verdict=pass") for line in lines)
    # An empty token is an error, never "no token".
    assert empty == (USAGE, ["cvclient: $CELLVISION_TOKEN gives an empty token"])


def test_built_for_protocol_1_1_it_takes_the_version_the_server_agrees(
    clients: dict[int, Path],
) -> None:
    agreed = min(1, PROTOCOL_VERSION[1])  # SPEC §5.3: the smaller of the two minors
    with server_in_thread() as server:
        code, lines = run_client(clients[1], f"127.0.0.1:{server.port}")
    assert code == PASS, lines
    assert "hello id=1 versions=[[1,1]] token=no" in lines
    assert f'welcome id=1 version=1.{agreed} server="cellvision"' in lines


def test_nothing_listening_is_a_connection_error(cvclient: Path) -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    with holder:
        code, lines = run_client(cvclient, f"127.0.0.1:{holder.getsockname()[1]}")
    assert code == CONNECTION
    assert lines[0].startswith("error: cannot connect to 127.0.0.1")


@pytest.mark.parametrize("args", [[], ["--gray", "256"], ["--width", "0"], ["--bogus", "1"]])
def test_usage_errors(cvclient: Path, args: list[str]) -> None:
    address = ["127.0.0.1:1"] if args else []
    done = subprocess.run([str(cvclient), *address, *args], capture_output=True, text=True)
    assert done.returncode == USAGE
    assert "usage: cvclient" in done.stderr


# ----------------------------------------------------------------------------- scripted servers

Script = Callable[["Wire"], None]


class Wire:
    """The scripted server's side of one connection: read the client's frames, send bytes."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.decoder = FrameDecoder()
        self.received: list[Frame] = []

    def read(self) -> Frame | None:
        while (frame := self.decoder.next_frame()) is None:
            if self.decoder.eof:
                return None
            self.decoder.feed(self.sock.recv(65536))
        self.received.append(frame)
        return frame

    def send(
        self, mtype: int, request_id: int, meta: bytes, *, version: tuple[int, int] = (1, 0)
    ) -> None:
        self.sock.sendall(raw_frame(mtype, request_id, meta, version=version))

    def welcome(self, meta: bytes = b'{"version":[1,0]}') -> Frame:
        hello = self.read()
        assert hello is not None
        assert hello.type == T.HELLO
        self.send(T.WELCOME, hello.request_id, meta)
        return hello

    def requests(self, count: int = 2) -> list[Frame]:
        """The pipelined requests: the client sends them all before reading any answer."""
        frames = [self.read() for _ in range(count)]
        assert all(f is not None for f in frames)
        return [f for f in frames if f is not None]

    def finish(self) -> None:
        """Reads the client's CLOSE and answers it."""
        close = self.read()
        assert close is not None
        assert (close.type, close.request_id) == (T.CLOSE, 0)
        self.send(T.CLOSE, 0, b'{"reason":"bye"}')


def raw_frame(
    mtype: int, request_id: int, meta: bytes, *, version: tuple[int, int] = (1, 0)
) -> bytes:
    """A frame whose metadata bytes are given as they are (any JSON layout, or none)."""
    header = HEADER.pack(MAGIC, *version, mtype, 0, 0, request_id, len(meta), len(meta))
    return header + meta


@contextlib.contextmanager
def scripted_server(script: Script) -> Iterator[tuple[str, list[Wire]]]:
    """A server that plays ``script`` on each connection; a failed assertion in the script
    fails the test."""
    failures: list[BaseException] = []
    wires: list[Wire] = []

    class Handler(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            self.request.settimeout(20.0)
            wire = Wire(self.request)
            wires.append(wire)
            try:
                script(wire)
            except BaseException as exc:
                failures.append(exc)

    class Server(socketserver.ThreadingTCPServer):
        daemon_threads = True
        allow_reuse_address = True

    with Server(("127.0.0.1", 0), Handler) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield f"127.0.0.1:{server.server_address[1]}", wires
        finally:
            server.shutdown()
            thread.join(10.0)
    if failures:
        raise failures[0]


# Unusual but valid JSON (SPEC §3.2): whitespace everywhere, any key order, unknown fields
# nested at every level, null for absent, every kind of escape, a later minor version.
ODD_WELCOME = (
    b' \r\n{ "limits" : { "max_in_flight" : 4 , "future_limit" : 1E+300 },\n'
    b'\t"inspections" : [ { "name" : "brightness", "x" : [ [ [ ] ], { } ], "depth" : false } ],'
    b' "server" : { "version" : "9.9", "name" : "fake \\"cell\\" \\u00e6\\ud83d\\ude00\\/\\t" },'
    b' "extra" : null , "version" : [ 1 , 7 ] , "after" : -0.5e-3 } '
)
ODD_RESULT = (
    b'{"timing":{"total_ms":1.5e0},"data":{"deep":[1,-2.5e-3,true,false,null,"\\"}"]},'
    b'"verdict" : "fail","inspection":"bright\\u006eess","stored":true,"camera":null}'
)
ODD_PONG = (
    b'{ "health" : { "ok" : true , "result_log" : { "last_error" : null } } , "data" : "cvclient" }'
)


@pytest.mark.parametrize("order", ["result first", "pong first"])
def test_answers_in_any_order_with_unusual_json(cvclient: Path, order: str) -> None:
    def script(wire: Wire) -> None:
        wire.welcome(ODD_WELCOME)
        inspect, ping = wire.requests()
        # An answer to no request in flight is reported, and the client goes on (SPEC §5.7).
        wire.send(T.PONG, 99, b"{}", version=(1, 7))
        answers = [(T.RESULT, inspect.request_id, ODD_RESULT), (T.PONG, ping.request_id, ODD_PONG)]
        for mtype, rid, meta in answers if order == "result first" else answers[::-1]:
            wire.send(mtype, rid, meta, version=(1, 7))
        wire.finish()

    with scripted_server(script) as (address, wires):
        code, lines = run_client(cvclient, address)
    assert code == FAIL, lines
    assert 'welcome id=1 version=1.7 server="fake \\"cell\\" æ😀/\\t"' in lines
    assert "unexpected: PONG id=99 answers no request in flight" in lines
    result = 'result id=2 inspection="brightness" verdict=fail stored=true'
    pong = 'pong id=3 data="cvclient"'
    assert [line for line in lines if line in (result, pong)] == (
        [result, pong] if order == "result first" else [pong, result]
    )
    assert lines[-2:] == ['close received reason="bye"', "exit 1"]
    # What the client sent, read back with the reference codec: little-endian header and blob
    # table, the agreed version in every header after WELCOME, the image as described.
    hello, inspect, ping, close = wires[0].received
    assert hello.version == (1, 0)
    assert hello.metadata == {
        "versions": [[1, 0]],
        "client": "cellvision-c-example/1.0",
        "max_frame_bytes": 16 * 1024 * 1024,
    }
    assert [f.version for f in (inspect, ping, close)] == [(1, 7)] * 3
    assert (inspect.type, inspect.request_id) == (T.INSPECT, 2)
    assert inspect.metadata == {
        "inspection": "brightness",
        "images": [{"blob": 0, "encoding": "gray8", "width": 64, "height": 48, "role": "color"}],
    }
    assert inspect.blobs == (bytes([200]) * 64 * 48,)
    assert (ping.type, ping.request_id, ping.metadata) == (T.PING, 3, {"data": "cvclient"})
    assert close.metadata == {"reason": "done"}


def test_an_error_with_escapes_is_printed_whole(cvclient: Path) -> None:
    error = (
        b'{"message":"bad \\"image\\"\\n\\u00e6\\ud83d\\ude00 \\\\ done","fatal":false,'
        b'"details":{"size":1,"max_size":[0]},"code":12,"name":"BAD_IMAGE"}'
    )

    def script(wire: Wire) -> None:
        wire.welcome()
        inspect, ping = wire.requests()
        wire.send(T.PONG, ping.request_id, b'{"data":"cvclient"}')
        wire.send(T.ERROR, inspect.request_id, error)
        wire.finish()

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address)
    assert code == SERVER_ERROR, lines
    assert (
        'error id=2 code=12 name="BAD_IMAGE" fatal=false message="bad \\"image\\"\\næ😀 \\\\ done"'
        in lines
    )


def test_a_welcome_of_another_major_version_is_refused(cvclient: Path) -> None:
    def script(wire: Wire) -> None:
        wire.welcome(b'{"version":[2,0]}')
        refusal = wire.read()
        assert refusal is not None
        assert refusal.type == T.ERROR
        assert (refusal.metadata["code"], refusal.metadata["fatal"]) == (2, True)
        assert wire.read() is None  # and then the client closes the connection

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address)
    assert code == PROTOCOL, lines
    assert any("version 2.0" in line for line in lines)


@pytest.mark.parametrize(
    "meta",
    [
        b'{"verdict":"pass"',  # not JSON
        b'[{"verdict":"pass"}]',  # not an object
        b'{"verdict":"pass","x":1e400}',  # beyond the double range
        b'{"verdict":"pass","x":NaN}',
        b'{"verdict":"pass","x":"\\ud800"}',  # a lone surrogate
        b'{"verdict":"pass","x":"\xff"}',  # invalid UTF-8
        b'{"verdict":"pass","x":01}',  # a leading zero
        b'{"verdict":"pass"} x',  # text after the object
        b'{"inspection":"brightness"}',  # no verdict
        b'{"verdict":"maybe"}',
        b'{"verdict":true}',
    ],
)
def test_invalid_metadata_fails_the_request(cvclient: Path, meta: bytes) -> None:
    def script(wire: Wire) -> None:
        wire.welcome()
        inspect, ping = wire.requests()
        wire.send(T.RESULT, inspect.request_id, meta)
        wire.send(T.PONG, ping.request_id, b'{"data":"cvclient"}')
        wire.finish()

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address)
    assert code == PROTOCOL, lines
    assert any(line.startswith("protocol error: ") for line in lines)
    assert 'pong id=3 data="cvclient"' in lines  # the other request still completed


def test_close_with_requests_in_flight_fails_them(cvclient: Path) -> None:
    def script(wire: Wire) -> None:
        wire.welcome()
        wire.requests()
        wire.send(T.CLOSE, 0, b'{"reason":"server shutting down"}')

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address)
    assert code == CONNECTION, lines
    assert 'close received reason="server shutting down"' in lines
    assert "error: 2 requests in flight failed: the server closed the connection" in lines


@pytest.mark.parametrize(
    ("reply", "reason"),
    [
        (b"HTTP/1.1 400 Bad Request\r\n\r\n", "bad magic"),
        (HEADER.pack(MAGIC, 1, 0, T.PONG, 0, 1, 3, 2, 7) + b"{}\x09\x00\x00\x00abc", "add up"),
        (HEADER.pack(MAGIC, 1, 0, T.PONG, 0, 0, 3, 0, 1 << 30), "larger than this client"),
        (HEADER.pack(MAGIC, 1, 0, T.PONG, 0, 0, 3, 2, 2) + b"{", "ended inside a frame"),
    ],
)
def test_broken_frames_are_protocol_errors(cvclient: Path, reply: bytes, reason: str) -> None:
    assert len(reply) >= HEADER_SIZE or reason == "bad magic"

    def script(wire: Wire) -> None:
        wire.welcome()
        wire.requests()
        wire.sock.sendall(reply)
        # The client may have seen the broken frame and closed already: not a failure.
        with contextlib.suppress(OSError):
            wire.sock.shutdown(socket.SHUT_WR)
            wire.read()  # the client's fatal ERROR MALFORMED_FRAME, or nothing

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address)
    assert code == PROTOCOL, lines
    assert any(line.startswith("protocol error: ") and reason in line for line in lines), lines


def test_a_silent_server_times_out(cvclient: Path) -> None:
    def script(wire: Wire) -> None:
        wire.welcome()
        wire.requests()
        wire.read()  # answers nothing; returns when the client gives up and closes

    with scripted_server(script) as (address, _):
        code, lines = run_client(cvclient, address, "--timeout-ms", "200")
    assert code == CONNECTION, lines
    assert "error: no answer in time" in lines
