"""``vision-server serve``'s listening options (issue 28): ``--console-port N`` /
``--no-console``, ``--line-port N`` / ``--no-line``, ``--modbus-port N`` / ``--no-modbus`` override
the configuration file for one run, as ``--host`` / ``--port`` do for the binary protocol.

Each is run as the real process on loopback. The configuration puts the front-end on a port the
test holds itself, so a server that ignored the option could not start; with ``--NAME-port 0``
the bound port is read from the line ``serve`` prints and spoken to in the front-end's own
protocol. A port option for a front-end the file does not enable, two front-ends on one port
and a port out of range are usage errors (exit 2) before anything listens, naming the keys.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from protocol.cli import ExitCode

ROOT = Path(__file__).resolve().parents[2]
CELL = """\
server: {port: 0}
results: {enabled: false}
cameras:
  tool: {source: request}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 10}
"""
PRINTED = {
    "console": re.compile(r"vision-server: web console on http://127\.0\.0\.1:(\d+)/\n"),
    "line": re.compile(r"vision-server: line protocol on 127\.0\.0\.1:(\d+)\n"),
    "modbus": re.compile(r"vision-server: Modbus TCP on 127\.0\.0\.1:(\d+)\n"),
}
"""What ``serve`` prints for each front-end once everything listens (its bound port)."""
FRONTENDS = list(PRINTED)


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *sys.path])
    return env


def _vision_server(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vision_server", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(),
    )


@contextmanager
def _held_port() -> Iterator[int]:
    """A loopback port this test listens on: nobody else can."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        sock.listen()
        yield int(sock.getsockname()[1])


def _cell(tmp_path: Path, **sections: int) -> Path:
    """The cell with each named front-end enabled on the given port."""
    enabled = (f"{name}: {{enabled: true, port: {port}}}\n" for name, port in sections.items())
    text = CELL + "".join(enabled)
    path = tmp_path / "cell.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@contextmanager
def _serving(*args: str, frontends: int = 0) -> Iterator[list[str]]:
    """``serve ARGS`` until the block ends: yields what it printed once it listens, the binary
    protocol's line and one for each of the other ``frontends`` (printed right after it).
    Nothing else may be printed before it stops."""
    with tempfile.TemporaryFile("w+") as stderr:
        proc = subprocess.Popen(
            [sys.executable, "-m", "vision_server", "serve", *args],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
            env=_env(),
        )
        assert proc.stdout is not None
        try:
            first = proc.stdout.readline()
            started = first.startswith("vision-server listening on 127.0.0.1:")
            if started:
                yield [first, *(proc.stdout.readline() for _ in range(frontends))]
        finally:
            proc.send_signal(signal.SIGTERM)
            # On through the same reader: its readline() may hold lines not yet returned.
            rest = proc.stdout.read()
            proc.stdout.close()
            proc.wait(60)
            stderr.seek(0)
            errors = stderr.read()
    assert started, f"serve did not start: {first!r} {errors}"
    assert proc.returncode == 0, errors
    assert rest == "", rest  # no front-end beyond those expected


def _bound(lines: list[str], name: str) -> int:
    matches = [m for m in map(PRINTED[name].fullmatch, lines) if m]
    assert len(matches) == 1, lines
    return int(matches[0][1])


def _speaks(name: str, port: int) -> None:
    """One exchange in the front-end's own protocol on ``port``."""
    if name == "console":
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/inspections", timeout=30) as r:
            assert [i["name"] for i in json.load(r)["inspections"]] == ["bright"]
        return
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        if name == "line":
            sock.sendall(b"P\n")
            assert sock.makefile("rb").readline() == b"OK PONG\r\n"
        else:  # Modbus TCP: read holding register 0 of unit 1
            sock.sendall(struct.pack(">HHHBBHH", 7, 0, 6, 1, 3, 0, 1))
            answer = sock.recv(256)
            transaction, _, _, unit, function = struct.unpack(">HHHBB", answer[:8])
            assert (transaction, unit, function) == (7, 1, 3), answer


# ----------------------------------------------------------------------------- moving one


@pytest.mark.parametrize("name", FRONTENDS)
def test_a_port_option_moves_the_front_end_the_file_enables(tmp_path: Path, name: str) -> None:
    """The file's port is held by the test: the server comes up only because ``--NAME-port 0``
    moved the front-end, whose bound port it prints."""
    with _held_port() as taken:
        config = _cell(tmp_path, **{name: taken})
        with _serving("--config", str(config), f"--{name}-port", "0", frontends=1) as lines:
            port = _bound(lines, name)
            assert port != taken
            _speaks(name, port)


def test_every_front_end_moved_at_once(tmp_path: Path) -> None:
    with _held_port() as a, _held_port() as b, _held_port() as c:
        config = _cell(tmp_path, console=a, line=b, modbus=c)
        options = [o for name in FRONTENDS for o in (f"--{name}-port", "0")]
        with _serving("--config", str(config), *options, frontends=3) as lines:
            for name in FRONTENDS:
                _speaks(name, _bound(lines, name))


def test_a_given_port_is_the_one_it_listens_on(tmp_path: Path) -> None:
    """A fixed port from the command line, not only 0: free one, then give it."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free = int(probe.getsockname()[1])
    with _held_port() as taken:
        config = _cell(tmp_path, line=taken)
        with _serving("--config", str(config), "--line-port", str(free), frontends=1) as lines:
            assert _bound(lines, "line") == free
            _speaks("line", free)


# ----------------------------------------------------------------------------- switching off


@pytest.mark.parametrize("name", FRONTENDS)
def test_no_front_end_leaves_it_off(tmp_path: Path, name: str) -> None:
    """``--no-NAME``: the file enables the front-end on a port the test holds; the server
    starts without it (no line printed for it) and serves the others."""
    others = [n for n in FRONTENDS if n != name]
    with _held_port() as taken:
        config = _cell(tmp_path, **{name: taken, **{n: 0 for n in others}})
        with _serving("--config", str(config), f"--no-{name}", frontends=2) as lines:
            assert not any(PRINTED[name].fullmatch(line) for line in lines), lines
            for other in others:
                _speaks(other, _bound(lines, other))


def test_no_front_end_is_allowed_where_the_file_has_it_off(tmp_path: Path) -> None:
    """Switching off what is off changes nothing (scripts may always pass --no-modbus)."""
    with _serving("--config", str(_cell(tmp_path)), "--no-console", "--no-line", "--no-modbus"):
        pass


# ----------------------------------------------------------------------------- refused


@pytest.mark.parametrize("name", FRONTENDS)
def test_a_port_for_a_front_end_the_file_does_not_enable_is_a_usage_error(
    tmp_path: Path, name: str
) -> None:
    """A port option does not enable a front-end (its other keys live in the file): exit 2,
    the key named, nothing listening."""
    done = _vision_server("serve", "--config", str(_cell(tmp_path)), f"--{name}-port", "0")
    assert done.returncode == ExitCode.USAGE, done.stderr
    assert done.stdout == ""
    assert done.stderr.startswith(f"vision-server serve: --{name}-port: "), done.stderr
    assert f"({name}.enabled is not true)" in done.stderr
    assert str(_cell(tmp_path)) in done.stderr


def test_a_port_for_the_built_in_demo_is_a_usage_error() -> None:
    done = _vision_server("serve", "--console-port", "0")
    assert done.returncode == ExitCode.USAGE, done.stderr
    assert done.stdout == ""
    assert "the built-in demo (no --config or $CELLVISION_CONFIG)" in done.stderr
    assert "console.enabled: true" in done.stderr


@pytest.mark.parametrize(
    ("sections", "options", "clash"),
    [
        # Onto the binary protocol's port.
        ({"console": 0}, ("--port", "{p}", "--console-port", "{p}"),
         "console.port 127.0.0.1:{p} is also server.port (127.0.0.1:{p})"),
        # Onto another front-end's port from the file.
        ({"console": 0, "line": "{p}"}, ("--console-port", "{p}"),
         "line.port 127.0.0.1:{p} is also console.port (127.0.0.1:{p})"),
        # Two options onto one port.
        ({"line": 0, "modbus": 0}, ("--line-port", "{p}", "--modbus-port", "{p}"),
         "modbus.port 127.0.0.1:{p} is also line.port (127.0.0.1:{p})"),
    ],
)  # fmt: skip
def test_two_front_ends_on_one_port_are_refused_naming_both(
    tmp_path: Path, sections: dict[str, object], options: tuple[str, ...], clash: str
) -> None:
    """The file's rule, applied after the options: exit 2 before anything binds (the port is
    held by the test, so a bind would fail differently, with exit 3)."""
    with _held_port() as p:
        config = _cell(tmp_path, **{k: int(str(v).format(p=p)) for k, v in sections.items()})
        done = _vision_server("serve", "--config", str(config), *(o.format(p=p) for o in options))
    assert done.returncode == ExitCode.USAGE, done.stderr
    assert done.stdout == ""
    given = ", ".join(o for o in options if o.startswith("--"))
    assert done.stderr.startswith(f"vision-server serve: invalid configuration with {given}: ")
    assert clash.format(p=p) in done.stderr, done.stderr


@pytest.mark.parametrize(
    ("options", "error"),
    [
        (("--console-port", "65536"), "argument --console-port: expected a port in 0..65535"),
        (("--line-port", "-1"), "argument --line-port: expected a port in 0..65535"),
        (("--modbus-port", "plc"), "argument --modbus-port: expected a port in 0..65535"),
        (("--port", "70000"), "argument --port: expected a port in 0..65535"),
        (("--console-port", "0", "--no-console"), "argument --no-console: not allowed with"),
    ],
)
def test_bad_port_options_are_usage_errors(
    tmp_path: Path, options: tuple[str, ...], error: str
) -> None:
    config = _cell(tmp_path, console=0, line=0, modbus=0)
    done = _vision_server("serve", "--config", str(config), *options)
    assert done.returncode == ExitCode.USAGE, done.stderr
    assert error in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def test_help_names_every_listening_option() -> None:
    done = _vision_server("serve", "--help")
    assert done.returncode == 0
    text = " ".join(done.stdout.split())
    for name in FRONTENDS:
        assert f"[--{name}-port N | --no-{name}]" in text, text
        assert f"(default: {name}.port; 0: any); the file must enable it" in text
    assert "no two front-ends may share a port (exit 2, both keys named)" in text
