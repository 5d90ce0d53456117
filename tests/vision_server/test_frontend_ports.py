"""Every front-end has its own default port, listed once in docs/configuration.md, and a
configuration that puts two enabled front-ends on one host:port is refused before anything
binds (check-config and serve), with both keys named."""

from __future__ import annotations

import asyncio
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from vision_server.app import App
from vision_server.commands import main
from vision_server.config import (
    ConfigError,
    ConsoleSettings,
    LineSettings,
    Listener,
    ListenError,
    ModbusSettings,
    OpcUaSettings,
    PortClash,
    ServerSettings,
    check_distinct,
    enabled_listeners,
    exposure_warnings,
    load_config,
)
from vision_server.service import builtin_catalog

ROOT = Path(__file__).resolve().parents[2]
CELL = """\
cameras:
  tool: {source: request}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 10}
"""


def _defaults() -> dict[str, int]:
    return {
        listener.key: listener.port
        for listener in enabled_listeners(
            ServerSettings(),
            console=ConsoleSettings(enabled=True),
            line=LineSettings(enabled=True),
            modbus=ModbusSettings(enabled=True),
            opcua=OpcUaSettings(enabled=True),
        )
    }


def test_every_front_end_has_its_own_default_port_as_documented() -> None:
    """The README's "line: {enabled: true}" beside the example's console made the console fail
    to listen: both defaulted to 7880."""
    check_distinct(
        enabled_listeners(
            ServerSettings(),
            console=ConsoleSettings(enabled=True),
            line=LineSettings(enabled=True),
            modbus=ModbusSettings(enabled=True),
            opcua=OpcUaSettings(enabled=True),
        )
    )
    text = (ROOT / "docs" / "configuration.md").read_text(encoding="utf-8")
    ports = text.split("## Ports", 1)[1].split("\n## ", 1)[0]
    documented = {k: int(p) for k, p in re.findall(r"\| `([a-z]+\.port)` \| (\d+) \|", ports)}
    assert documented == _defaults()


CLASHES = [
    ("console: {enabled: true, port: 7880}\nline: {enabled: true, port: 7880}\n",
     "console", "line"),
    ("line: {enabled: true, host: 0.0.0.0, port: 7885}\nmodbus: {enabled: true, port: 7885}\n",
     "line", "modbus"),
    ("server: {port: 7890}\nconsole: {enabled: true, host: 0.0.0.0, port: 7890}\n",
     "server", "console"),
]  # fmt: skip


@pytest.mark.parametrize(("sections", "first", "second"), CLASHES)
def test_two_front_ends_on_one_port_are_a_config_error_naming_both(
    tmp_path: Path, sections: str, first: str, second: str
) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL + sections, encoding="utf-8")
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert f"{second} -> port: {second}.port" in message, message
    assert f"is also {first}.port" in message, message


def test_the_same_port_on_two_distinct_hosts_is_allowed(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(
        CELL + "line: {enabled: true, host: 127.0.0.2, port: 7885}\n"
        "modbus: {enabled: true, host: 127.0.0.1, port: 7885}\n",
        encoding="utf-8",
    )
    load_config(path)


def test_serve_refuses_a_port_option_onto_another_front_end(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--port`` moves the binary protocol after the file was checked: serve checks again
    before it binds anything (exit 2, both keys named)."""
    path = tmp_path / "cell.yaml"
    path.write_text(CELL + "line: {enabled: true, port: 7886}\n", encoding="utf-8")
    code = main(["serve", "--config", str(path), "--port", "7886"])
    assert code == 2
    err = capsys.readouterr().err
    assert "line.port 127.0.0.1:7886 is also server.port" in err, err


def test_a_clash_names_the_later_key() -> None:
    clash = PortClash(
        *enabled_listeners(ServerSettings(port=5), line=LineSettings(enabled=True, port=5))
    )
    assert str(clash).startswith("line.port 127.0.0.1:5 is also server.port (127.0.0.1:5)")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _app(main_port: int, frontend: str, port: int) -> App:
    enabled: dict[str, Any] = {
        "line": {"line": LineSettings(enabled=True, port=port)},
        "modbus": {"modbus": ModbusSettings(enabled=True, port=port)},
        "console": {"console": ConsoleSettings(enabled=True, port=port)},
    }[frontend]
    return App(builtin_catalog(), ServerSettings(port=main_port, workers=1), **enabled)


@pytest.mark.parametrize(
    ("frontend", "named"),
    [
        ("line", "the line protocol (line.port)"),
        ("modbus", "Modbus TCP (modbus.port)"),
        ("console", "the web console (console.port)"),
    ],
)
def test_a_busy_front_end_port_stops_the_server_naming_its_own_address(
    frontend: str, named: str
) -> None:
    """Line 7885 taken was reported as "cannot listen on 127.0.0.1:7909 (the free main port):
    ... ('127.0.0.1', 7885)"; a taken console port was skipped with a log line. Now every
    enabled front-end follows one rule: the server stops, the error names the front-end and
    its own address once, and nothing is left listening."""
    main_port = _free_port()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        app = _app(main_port, frontend, port)

        async def body() -> None:
            with pytest.raises(ListenError) as info:
                await app.start()
            message = str(info.value)
            assert message.startswith(f"{named} cannot listen on 127.0.0.1:{port}: "), message
            assert message.count(str(port)) == 1, message
            assert str(main_port) not in message, message
            with pytest.raises(ConnectionRefusedError):  # the main port was closed again
                await asyncio.open_connection("127.0.0.1", main_port)

        try:
            asyncio.run(body())
        finally:
            app.service.close()


def test_serve_exits_3_when_the_line_port_is_taken(tmp_path: Path) -> None:
    """The command line's side of the rule: exit 3 and one line on stderr."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = tmp_path / "cell.yaml"
        path.write_text(CELL + f"line: {{enabled: true, port: {port}}}\n", encoding="utf-8")
        done = subprocess.run(
            [sys.executable, "-m", "vision_server", "serve", "--config", str(path), "--port", "0"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
        )
    assert done.returncode == 3, done.stderr
    assert done.stdout == ""
    assert done.stderr == (
        f"vision-server: the line protocol (line.port) cannot listen on 127.0.0.1:{port}: "
        "Address already in use\n"
    )


def test_serve_warns_for_every_front_end_open_beyond_loopback(tmp_path: Path) -> None:
    """The line and Modbus ports listened on 0.0.0.0 without a token, without a word; the
    guide promises a warning for what listens beyond loopback unprotected."""
    path = tmp_path / "cell.yaml"
    path.write_text(
        CELL + "line: {enabled: true, host: 0.0.0.0, port: 0}\n"
        "modbus: {enabled: true, host: 0.0.0.0, port: 0}\n",
        encoding="utf-8",
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", str(path), "--port", "0"],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        # The warnings are written before this line (serve warns once it listens).
        assert proc.stdout.readline().startswith("vision-server listening on 127.0.0.1:")
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    warnings = [line.split(" WARNING ", 1)[1] for line in err.splitlines() if " WARNING " in line]
    assert len(warnings) == 2, err  # the binary protocol is on loopback: nothing about it
    line, modbus = warnings
    assert line.startswith("the line protocol listening on 0.0.0.0:"), line
    assert "WITHOUT A TOKEN" in line
    assert "set server.auth_token_file" in line
    assert modbus.startswith("Modbus TCP listening on 0.0.0.0:"), modbus
    assert "WITHOUT AUTHENTICATION (Modbus TCP has none in the standard)" in modbus
    assert "modbus.host" in modbus


def test_no_warning_for_front_ends_on_loopback_or_behind_a_token() -> None:
    listeners = [
        Listener("line.port", "the line protocol", "0.0.0.0", 7879),
        Listener("console.port", "the web console", "127.0.0.1", 7880),
    ]
    assert exposure_warnings(ServerSettings(auth_token="t"), listeners) == []
