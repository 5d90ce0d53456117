"""The suite does not need the default ports (issue 28): with 127.0.0.1:7878, 7879, 7880 and
5020 held, as a server left running by hand holds them (README, "Using it by hand"), every way
the tests serve the example cell still comes up.

Five tests failed that way before: the conformance suite against examples/cell.yaml (twice),
the reliability test that restarts the server on the example cell, and the README's by-hand
flow (twice): each gave ``serve`` ``--port 0`` but left the example's console on 7880. Each
way below is the one those tests use (tests/helpers/example_servers.py), so that a copy or a
command line that binds a default port again fails here, in seconds, whatever else runs.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest
from console_server import TOKEN, console_server
from example_servers import (
    DEFAULT_PORTS,
    LISTENING,
    REPO_ROOT,
    default_ports_held,
    example_cell,
    example_cell_into,
    on_any_port_as_typed,
    readme_commands,
    serve_command,
    vision_server_process,
)

from robot_client import SyncVisionClient

TIMEOUT_S = 120


@pytest.fixture
def default_ports() -> Iterator[dict[str, int]]:
    """The four default ports held for the test (skipped where another program holds one)."""
    with default_ports_held() as held:
        yield held


def _answers(address: str, token: str | None = None) -> None:
    """The server at ``address`` (not on a default port) lists the example's inspections."""
    host, port = address.rsplit(":", 1)
    assert int(port) not in DEFAULT_PORTS.values()
    with SyncVisionClient(host, int(port), auth_token=token) as client:
        assert "magnet_check" in {i["name"] for i in client.list_inspections()}


def _all_listening(command: list[str], cwd: Path) -> list[str]:
    """Start ``command`` (a ``serve``), check it answers, stop it; what it printed on stdout:
    the binary protocol's listening line, then one for each other front-end."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), *sys.path])}
    with tempfile.TemporaryFile("w+") as stderr:
        process = subprocess.Popen(
            command, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=stderr, text=True
        )
        assert process.stdout is not None
        try:
            first = process.stdout.readline()
            listening = LISTENING.fullmatch(first)
            if listening is not None:
                _answers(f"{listening[1]}:{listening[2]}")
        finally:
            process.send_signal(signal.SIGTERM)
            # On through the same reader: its readline() may hold the lines after the first.
            rest = process.stdout.read()
            process.stdout.close()
            process.wait(TIMEOUT_S)
            stderr.seek(0)
            errors = stderr.read()
    assert listening is not None, f"serve did not start: {first!r} {errors}"
    assert process.returncode == 0, errors
    return [first, *rest.splitlines(keepends=True)]


def test_the_default_ports_are_the_documented_ones() -> None:
    assert DEFAULT_PORTS == {
        "server.port": 7878,
        "line.port": 7879,
        "console.port": 7880,
        "modbus.port": 5020,
    }


def test_the_conformance_suites_example_cell(tmp_path: Path, default_ports: object) -> None:
    """tests/protocol/test_conformance_live.py: examples/cell.yaml as shipped, as a process."""
    with vision_server_process(example_cell(tmp_path)) as address:
        _answers(address)


def test_the_restarted_example_cell_of_the_reliability_test(
    tmp_path: Path, default_ports: object
) -> None:
    """tests/test_reliability_faults.py: the copy writing into tmp, on a port of its own."""
    lines = _all_listening(serve_command(example_cell_into(tmp_path), port=0), REPO_ROOT)
    console = [line for line in lines if "web console on" in line]
    assert len(console) == 1, lines
    assert not console[0].rstrip().endswith(f":{DEFAULT_PORTS['console.port']}/"), console


def test_the_readmes_serve_command(tmp_path: Path, default_ports: object) -> None:
    """tests/test_readme_flow.py: the README's command line as typed, in a folder holding the
    example (there, a copy of the checkout), with the ports made 0."""
    example_cell(tmp_path)
    (serve,) = [c for c in readme_commands() if c[1:2] == ["serve"]]
    assert serve[0] == ".venv/bin/vision-server"
    command = [sys.executable, "-m", "vision_server", *serve[1:]]
    lines = _all_listening(on_any_port_as_typed(command, tmp_path), tmp_path)
    assert any(re.search(r"web console on http://127\.0\.0\.1:\d+/", line) for line in lines)


def test_the_console_tests_example_cell(tmp_path: Path, default_ports: object) -> None:
    """tests/helpers/console_server.py: the copy it rewrites to ports 0, served in a thread."""
    with console_server(tmp_path) as running:
        assert running.app.port not in DEFAULT_PORTS.values()
        assert not running.url.endswith(f":{DEFAULT_PORTS['console.port']}/")
        _answers(f"127.0.0.1:{running.app.port}", TOKEN)
