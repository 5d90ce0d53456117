"""``vision-server serve`` as a process: it listens, answers, and stops cleanly on a signal."""

from __future__ import annotations

import asyncio
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from protocol import NotAuthenticated
from robot_client.client import ReconnectPolicy, VisionClient
from vision_server.cli import build_parser

REPO_ROOT = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"vision-server listening on (\S+):(\d+)\n")


def _serve(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--port", "0", *args],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture
def serve_process() -> Iterator[list[subprocess.Popen[str]]]:
    started: list[subprocess.Popen[str]] = []
    yield started
    for proc in started:  # whatever the test did, leave no server behind
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)


def _port(proc: subprocess.Popen[str]) -> int:
    assert proc.stdout is not None
    line = proc.stdout.readline()
    match = LISTENING.fullmatch(line)
    assert match, f"unexpected first line {line!r}"
    assert match[1] == "127.0.0.1"
    return int(match[2])


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_serve_answers_then_stops_on_a_signal(
    sig: signal.Signals, serve_process: list[subprocess.Popen[str]]
) -> None:
    proc = _serve()
    serve_process.append(proc)
    port = _port(proc)

    async def use_it() -> None:
        async with VisionClient("127.0.0.1", port, request_timeout_s=10.0) as client:
            assert client.welcome is not None
            assert client.welcome.server_name == "cellvision"
            assert [i["name"] for i in await client.list_inspections()] == ["brightness"]

    asyncio.run(use_it())
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert out == ""  # nothing after the listening line


def test_serve_with_an_auth_token(serve_process: list[subprocess.Popen[str]]) -> None:
    proc = _serve("--auth-token", "t0k")
    serve_process.append(proc)
    port = _port(proc)

    async def use_it() -> None:
        async with VisionClient("127.0.0.1", port, auth_token="t0k") as client:
            assert await client.ping() >= 0.0
        refused = VisionClient("127.0.0.1", port, reconnect=ReconnectPolicy(attempts=0))
        with pytest.raises(NotAuthenticated):
            await refused.connect()

    asyncio.run(use_it())
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=30)
    assert proc.returncode == 0


def test_a_port_in_use_is_a_clear_error() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run(
            [sys.executable, "-m", "vision_server", "serve", "--port", str(port)],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert done.returncode == 1
    assert done.stdout == ""
    assert done.stderr.startswith(f"vision-server: cannot listen on 127.0.0.1:{port}: ")
    assert "Traceback" not in done.stderr


def test_parser_defaults() -> None:
    """Options left out come from the configuration file (or ServerSettings' defaults:
    127.0.0.1:7878), so the parser itself leaves them unset."""
    args = build_parser().parse_args(["serve"])
    assert (args.host, args.port, args.auth_token, args.config) == (None, None, None, None)
    with pytest.raises(SystemExit):
        build_parser().parse_args([])
