"""``vision-server serve`` on the example cell (``examples/cell.yaml``) without its fixed ports.

The example listens on the documented defaults (7878 for the binary protocol, 7880 for the web
console), which a server started by hand (the README's "Using it by hand" leaves one running),
``make demo STAY=1`` or another program may hold: a test that served a copy as shipped failed
then, with "the web console (console.port) cannot listen on 127.0.0.1:7880". The tests that
serve a copy of it as a process take their copy and their command line from here: port 0 for
the binary protocol and for every front-end the copy enables (``--console-port 0``, ...), each
bound port read from what ``serve`` prints. tests/test_fixed_ports.py holds the default ports
and starts the server each way.

Importable as ``example_servers`` (pytest's ``pythonpath`` includes tests/helpers).
"""

from __future__ import annotations

import contextlib
import errno
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from vision_server.config import (
    DEFAULT_CONSOLE_PORT,
    DEFAULT_LINE_PORT,
    DEFAULT_MODBUS_PORT,
    ServerSettings,
    load_config,
)

REPO_ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = REPO_ROOT / "examples" / "cell.yaml"
SCENE = REPO_ROOT / "examples" / "scenes" / "grundfos_cell.yaml"
SERVE = [sys.executable, "-m", "vision_server", "serve"]
LISTENING = re.compile(r"vision-server listening on (\S+):(\d+)\n")

DEFAULT_PORTS = {
    "server.port": ServerSettings().port,
    "line.port": DEFAULT_LINE_PORT,
    "console.port": DEFAULT_CONSOLE_PORT,
    "modbus.port": DEFAULT_MODBUS_PORT,
}
"""Each front-end's default port (docs/configuration.md, "Ports"): 7878, 7879, 7880, 5020."""

FRONTENDS = ("console", "line", "modbus")
"""The optional front-ends, each with ``serve --NAME-port N``."""


# ----------------------------------------------------------------------------- copies


def example_cell(folder: Path) -> Path:
    """``examples/cell.yaml`` as shipped, with the scenes it names, copied into
    ``folder/examples`` so that the result log and world state it writes beside itself
    (``../demo-output``) land in ``folder``."""
    cell = folder / "examples"
    cell.mkdir()
    shutil.copy(EXAMPLE, cell / "cell.yaml")
    shutil.copytree(REPO_ROOT / "examples" / "scenes", cell / "scenes")
    return cell / "cell.yaml"


def example_cell_into(folder: Path) -> Path:
    """``examples/cell.yaml`` as ``folder/cell.yaml``, writing its result log and reading its
    world state in ``folder``, the scene named by absolute path (ports as shipped)."""
    text = EXAMPLE.read_text(encoding="utf-8")
    text = text.replace("../demo-output/results.sqlite3", str(folder / "results.sqlite3"))
    text = text.replace("../demo-output/world-state.json", str(folder / "world.json"))
    text = text.replace("scene: scenes/grundfos_cell.yaml", f"scene: {SCENE}")
    path = folder / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    return path


# ----------------------------------------------------------------------------- command lines


def on_any_port(config: Path) -> list[str]:
    """``serve`` options that put every optional front-end ``config`` enables on port 0
    (``--console-port 0`` for the example's console); the binary protocol's ``--port`` is the
    caller's."""
    loaded = load_config(config)
    options: list[str] = []
    for name in FRONTENDS:
        if getattr(loaded, name).enabled:
            options += [f"--{name}-port", "0"]
    return options


def serve_command(config: Path | None = None, *, port: int = 0) -> list[str]:
    """``vision-server serve`` (this Python's) on ``port`` with ``config`` (None: the built-in
    demo), every front-end the configuration enables on port 0."""
    if config is None:
        return [*SERVE, "--port", str(port)]
    return [*SERVE, "--config", str(config), "--port", str(port), *on_any_port(config)]


def on_any_port_as_typed(command: list[str], cwd: Path) -> list[str]:
    """A ``serve`` command line as a user types it (the README's) with ``--port 0`` and port 0
    for each front-end its ``--config`` (relative to ``cwd``) enables."""
    extra = ["--port", "0"]
    if "--config" in command:
        extra += on_any_port(cwd / command[command.index("--config") + 1])
    return [*command, *extra]


def readme_commands() -> list[list[str]]:
    """The commands of the first ``sh`` block under README.md's "## Using it by hand",
    continuation lines joined, comments dropped, each split as the shell would."""
    text = (REPO_ROOT / "README.md").read_text(encoding="utf-8")
    section = text.split("## Using it by hand", 1)[1].split("\n## ", 1)[0]
    match = re.search(r"```sh\n(.*?)```", section, re.S)
    assert match, "README.md: no ```sh block under 'Using it by hand'"
    joined = match.group(1).replace("\\\n", " ")
    return [shlex.split(line, comments=True) for line in joined.splitlines() if line.strip()]


# ----------------------------------------------------------------------------- processes


@contextlib.contextmanager
def vision_server_process(config: Path | None = None) -> Iterator[str]:
    """:func:`serve_command` as a process from the repository; yields its ``HOST:PORT`` once
    it listens (every front-end started); stopped with SIGTERM."""
    serve = subprocess.Popen(
        serve_command(config), cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        assert serve.stdout is not None
        line = serve.stdout.readline()
        match = LISTENING.fullmatch(line)
        assert match, line
        yield f"{match[1]}:{match[2]}"
    finally:
        serve.send_signal(signal.SIGTERM)
        serve.wait(30)
        if serve.stdout is not None:
            serve.stdout.close()


@contextlib.contextmanager
def default_ports_held(host: str = "127.0.0.1") -> Iterator[dict[str, int]]:
    """Listen on every front-end's default port on ``host``, as a server left running by hand
    would; the test is skipped, naming the port, where something else holds one already (run
    tests/test_fixed_ports.py in one worker: ``make test`` gives each file one)."""
    held: list[socket.socket] = []
    try:
        for key, port in DEFAULT_PORTS.items():
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            held.append(sock)
            try:
                sock.bind((host, port))
            except OSError as exc:
                if exc.errno != errno.EADDRINUSE:
                    raise
                pytest.skip(
                    f"{host}:{port} ({key}'s default) is taken by something else (a server, "
                    "or another worker holding the defaults): cannot hold the default ports "
                    "to show that the tests do without them"
                )
            sock.listen()
        yield dict(DEFAULT_PORTS)
    finally:
        for sock in held:
            sock.close()
