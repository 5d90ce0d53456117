"""The conformance suite against live servers: the real one passes, broken ones fail.

The real server runs in a background thread (the suite uses blocking sockets) or as the
``vision-server serve`` process; the broken ones are tiny threaded socket servers.
"""

from __future__ import annotations

import contextlib
import json
import re
import signal
import socket
import socketserver
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from loopback import server_in_thread

from protocol import FrameDecoder, MessageType, Welcome
from protocol.conformance import CHECKS, Target, run_checks
from protocol.conformance.__main__ import _address
from protocol.conformance.__main__ import main as conformance_main

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("auth_token", [None, "cell-7"])
def test_the_reference_server_passes_every_check(auth_token: str | None) -> None:
    with server_in_thread(auth_token=auth_token) as server:
        results = run_checks(Target("127.0.0.1", server.port, 10.0, auth_token))
    assert len(results) >= 25
    assert len(results) == len(CHECKS)
    assert len({r.name for r in results}) == len(results)
    not_passed = [(r.name, r.status, r.detail) for r in results if r.status != "pass"]
    assert not_passed == []
    assert all(r.section.startswith("§") for r in results)


def test_cli_text_report_against_the_reference_server(capsys: pytest.CaptureFixture[str]) -> None:
    with server_in_thread() as server:
        port = server.port
        code = conformance_main([f"127.0.0.1:{port}", "-k", "ping"])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.strip().splitlines()
    assert lines[0].split() == ["check", "section", "result", "detail"]
    assert any(line.split()[:3] == ["ping_pong", "§5.5", "PASS"] for line in lines)
    assert lines[-1] == f"1 passed, 0 failed, 0 skipped against 127.0.0.1:{port}"


def test_cli_json_against_the_vision_server_process() -> None:
    serve = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--port", "0"],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert serve.stdout is not None
        line = serve.stdout.readline()
        match = re.fullmatch(r"vision-server listening on (\S+):(\d+)\n", line)
        assert match, line
        address = f"{match[1]}:{match[2]}"
        checked = subprocess.run(
            [sys.executable, "-m", "protocol.conformance", address, "--json"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert checked.returncode == 0, checked.stdout + checked.stderr
        report = json.loads(checked.stdout)
        assert report["target"] == address
        assert report["failed"] == 0
        assert report["skipped"] == 0
        assert report["passed"] == len(report["results"]) >= 25
        first = report["results"][0]
        assert set(first) == {
            "name",
            "section",
            "description",
            "status",
            "detail",
            "duration_s",
        }
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(30)
        if serve.stdout is not None:
            serve.stdout.close()


# ----------------------------------------------------------------------------- broken servers

Behaviour = Callable[[socket.socket], None]


@contextlib.contextmanager
def broken_server(behaviour: Behaviour) -> Iterator[int]:
    """A threaded TCP server that treats every connection with ``behaviour``."""

    class Handler(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            self.request.settimeout(10.0)
            with contextlib.suppress(OSError):
                behaviour(self.request)

    class Server(socketserver.ThreadingTCPServer):
        daemon_threads = True
        allow_reuse_address = True

    with Server(("127.0.0.1", 0), Handler) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield server.server_address[1]
        finally:
            server.shutdown()
            thread.join(10.0)


def _read_frame(sock: socket.socket, decoder: FrameDecoder) -> Any:
    while (frame := decoder.next_frame()) is None:
        data = sock.recv(65536)
        decoder.feed(data)
        if not data and decoder.next_frame() is None:
            return None
    return frame


def _garbage(sock: socket.socket) -> None:
    _read_frame(sock, FrameDecoder())
    sock.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")


def _silent(sock: socket.socket) -> None:
    while sock.recv(65536):
        pass


def _welcome_then_silent(sock: socket.socket) -> None:
    decoder = FrameDecoder()
    hello = _read_frame(sock, decoder)
    if hello is None or hello.type != MessageType.HELLO:
        return
    welcome = Welcome(hello.request_id, (1, 0), "broken", "0", {"max_in_flight": 4})
    sock.sendall(welcome.to_frame((1, 0)).serialize())
    while sock.recv(65536):
        pass


def _conformance(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "protocol.conformance", f"127.0.0.1:{port}", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize("behaviour", [_garbage, _silent], ids=["garbage", "silent"])
def test_cli_fails_when_the_handshake_fails(behaviour: Behaviour) -> None:
    with broken_server(behaviour) as port:
        checked = _conformance(port, "--json", "--timeout", "0.5")
    assert checked.returncode == 2
    assert "cannot start" in checked.stderr
    assert checked.stdout == ""


def test_cli_reports_failed_checks_of_a_server_that_only_shakes_hands() -> None:
    with broken_server(_welcome_then_silent) as port:
        checked = _conformance(port, "--json", "--timeout", "0.3", "-k", "ping")
    assert checked.returncode == 1, checked.stderr
    report = json.loads(checked.stdout)
    statuses = {r["name"]: r["status"] for r in report["results"]}
    assert statuses == {"ping_pong": "fail"}
    assert report["failed"] == 1
    assert report["passed"] == 0
    assert "no answer" in report["results"][0]["detail"]


def test_cli_fails_when_nothing_listens() -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    with holder:
        checked = _conformance(holder.getsockname()[1])
    assert checked.returncode == 2
    assert "cannot start" in checked.stderr


# ----------------------------------------------------------------------------- address


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:7000", ("127.0.0.1", 7000)),
        ("cell-3", ("cell-3", 7878)),
        (":7001", ("127.0.0.1", 7001)),
        ("[::1]:7002", ("::1", 7002)),
        ("[::1]", ("::1", 7878)),
        ("::1", ("::1", 7878)),
    ],
)
def test_address_forms(text: str, expected: tuple[str, int]) -> None:
    assert _address(text) == expected


@pytest.mark.parametrize("text", ["cell:port", "cell:0", "cell:70000", "[::1"])
def test_bad_address_is_a_usage_error(text: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        conformance_main([text])
    assert exited.value.code == 2
    assert "address" in capsys.readouterr().err
