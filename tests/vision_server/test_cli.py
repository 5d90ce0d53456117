"""``vision-server serve`` as a process: it listens, answers, and stops cleanly on a signal."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from protocol import NotAuthenticated
from protocol.cli import UsageError
from robot_client.client import ReconnectPolicy, VisionClient
from vision_server.commands.program import build_parser
from vision_server.server import ServerSettings

REPO_ROOT = Path(__file__).resolve().parents[2]
LISTENING = re.compile(r"vision-server listening on (\S+):(\d+)\n")


def _env(**extra: str) -> dict[str, str]:
    """The environment without the caller's CELLVISION_* settings, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    return {**env, "PYTHONPATH": str(REPO_ROOT), **extra}


def _serve(*args: str, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--port", "0", *args],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env() if env is None else env,
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


def _token_file(tmp_path: Path, text: str) -> str:
    path = tmp_path / "token"
    path.write_text(text, encoding="utf-8")
    return str(path)


@pytest.mark.parametrize(
    "source",
    ["--token-file", "CELLVISION_TOKEN", "CELLVISION_TOKEN_FILE", "--auth-token (deprecated)"],
)
def test_serve_with_an_auth_token(
    source: str, tmp_path: Path, serve_process: list[subprocess.Popen[str]]
) -> None:
    """The token comes from a file or the environment (a file's newline is not part of it);
    a literal on the command line still works, with a warning."""
    args: tuple[str, ...] = ()
    env = _env()
    if source == "--token-file":
        args = ("--token-file", _token_file(tmp_path, "t0k\n"))
    elif source == "CELLVISION_TOKEN":
        env = _env(CELLVISION_TOKEN="t0k")
    elif source == "CELLVISION_TOKEN_FILE":
        env = _env(CELLVISION_TOKEN_FILE=_token_file(tmp_path, "  t0k\n\n"))
    else:
        args = ("--auth-token", "t0k")
    proc = _serve(*args, env=env)
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
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    assert ("--auth-token is deprecated" in err) == source.startswith("--auth-token")
    assert "t0k" not in err


def _start_or_exit(proc: subprocess.Popen[str]) -> tuple[int | None, str]:
    """(exit code, stderr) of a ``serve`` that must refuse to start; if it listens instead,
    (None, its first line): the test fails without waiting for a timeout."""
    assert proc.stdout is not None
    line = proc.stdout.readline()  # "" once the process has exited
    if line:
        return None, line
    _, err = proc.communicate(timeout=30)
    return proc.returncode, err


@pytest.mark.parametrize(
    "how",
    [
        "--auth-token ''",
        "--token-file (empty)",
        "CELLVISION_TOKEN=''",
        "CELLVISION_TOKEN_FILE (whitespace)",
        "auth_token: '  ' in the configuration",
    ],
)
def test_an_empty_token_never_starts_a_server(
    how: str, tmp_path: Path, serve_process: list[subprocess.Popen[str]]
) -> None:
    """Issue 13, hole 5: ``serve --auth-token "$UNSET"`` used to serve every client."""
    args: tuple[str, ...] = ()
    env = _env()
    if how.startswith("--auth-token"):
        args = ("--auth-token", "")
    elif how.startswith("--token-file"):
        args = ("--token-file", _token_file(tmp_path, ""))
    elif how.startswith("CELLVISION_TOKEN="):
        env = _env(CELLVISION_TOKEN="")
    elif how.startswith("CELLVISION_TOKEN_FILE"):
        env = _env(CELLVISION_TOKEN_FILE=_token_file(tmp_path, " \n\t\n"))
    else:
        config = tmp_path / "cell.yaml"
        config.write_text(
            "server: {auth_token: '  '}\nresults: {enabled: false}\n"
            "cameras: {tool: {source: request}}\n"
            "inspections:\n"
            "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}\n"
        )
        args = ("--config", str(config))
    proc = _serve(*args, env=env)
    serve_process.append(proc)
    code, err = _start_or_exit(proc)
    assert code == 2, f"the server started: {err!r}"
    lines = [line for line in err.strip().splitlines() if "deprecated" not in line]
    assert len(lines) == 1, err
    assert "empty" in lines[0] or "blank" in lines[0]


def test_settings_never_hold_an_empty_token() -> None:
    with pytest.raises(ValueError, match="auth_token is empty"):
        ServerSettings(auth_token="")
    with pytest.raises(ValueError, match="auth_token is empty"):
        ServerSettings(auth_token=" \n")


@pytest.mark.parametrize("host", ["0.0.0.0", "127.0.0.1"])
def test_serve_warns_when_it_listens_beyond_loopback_unprotected(
    host: str, serve_process: list[subprocess.Popen[str]]
) -> None:
    """Issue 13, hole 8: the container's default (all interfaces, no token, no TLS) says so."""
    proc = _serve("--host", host)
    serve_process.append(proc)
    assert proc.stdout is not None
    assert proc.stdout.readline().startswith(f"vision-server listening on {host}:")
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0
    warnings = [line for line in err.splitlines() if "WARNING" in line]
    if host == "127.0.0.1":
        assert warnings == []
    else:
        assert len(warnings) == 2, err
        assert "WITHOUT A TOKEN" in warnings[0]
        assert "reload" in warnings[0]  # RELOAD is allowed without a configuration too
        assert "WITHOUT TLS" in warnings[1]


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
    assert done.returncode == 3  # the connection-error code
    assert done.stdout == ""
    assert done.stderr.startswith(
        f"vision-server: the binary protocol (server.port) cannot listen on 127.0.0.1:{port}: "
    )
    assert "Traceback" not in done.stderr


def test_parser_defaults() -> None:
    """Options left out come from the configuration file (or ServerSettings' defaults:
    127.0.0.1:7878), so the parser itself leaves them unset."""
    args = build_parser().parse_args(["serve"])
    assert (args.host, args.port, args.token_file, args.config) == (None, None, None, None)
    with pytest.raises(UsageError, match="required: command"):
        build_parser().parse_args([])


def test_ctrl_c_in_a_command_is_one_line_and_exit_130(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Ctrl-C in a long command (here the golden cases, interrupted in their first case): no
    traceback, the shell's exit code for SIGINT."""
    import vision_server.commands.program as cli

    def interrupted(*args: object, **kwargs: object) -> int:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "_test_inspections", interrupted)
    assert cli.main(["test-inspections", str(tmp_path)]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "vision-server: interrupted"


def test_check_config_names_what_is_wrong_with_the_file_itself(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An empty file, a file of comments only and an image given by mistake are invalid, each
    with its cause in words (not a Python exception's text)."""
    from vision_server.commands import main

    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    comments = tmp_path / "comments.yaml"
    comments.write_text("# the cell\n# nothing yet\n")
    image = tmp_path / "cell.png"
    image.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    for path in (empty, comments):
        assert main(["check-config", str(path)]) == 2
        assert "the file is empty" in " ".join(capsys.readouterr().err.split())
    assert main(["check-config", str(image)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "not a YAML text file" in err
    assert "codec" not in err
    missing = tmp_path / "missing.yaml"
    assert main(["serve", "--config", str(missing)]) == 2
    err = " ".join(capsys.readouterr().err.split())
    assert "cannot read the file: no such file" in err
    assert "Errno" not in err


def test_check_config_warns_of_a_file_without_inspections(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from vision_server.commands import main

    config = tmp_path / "cell.yaml"
    config.write_text("cameras: {tool: {source: request}}\ninspections: []\n")
    assert main(["check-config", str(config)]) == 0
    assert "warning: no inspections" in capsys.readouterr().err


def test_results_of_an_inspection_the_configuration_lacks_warns(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A typo in --inspection showed '0 of 0' as if the inspection had simply not run."""
    from vision_server.commands import main

    config = tmp_path / "cell.yaml"
    config.write_text(
        "results: {path: results.sqlite3}\n"
        "cameras: {tool: {source: request}}\n"
        "inspections:\n"
        "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}\n"
    )
    from vision_server.results import ResultLog

    ResultLog(tmp_path / "results.sqlite3").close()  # an empty log, as serve creates it
    assert main(["results", "--config", str(config), "--inspection", "brigth"]) == 0
    err = " ".join(capsys.readouterr().err.split())
    assert "warning: 'brigth' is not an inspection of" in err
    assert "(its inspections: bright)" in err
    assert main(["results", "--config", str(config), "--inspection", "bright"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_ping_with_a_configuration_on_port_0_asks_for_the_address(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """server.port 0 says nothing of where the server listens: ping and reload used the default
    port 7878, which may be another server's; now they ask for --server."""
    from vision_server.commands import main

    monkeypatch.delenv("CELLVISION_SERVER", raising=False)
    config = tmp_path / "cell.yaml"
    config.write_text("server: {port: 0}\ncameras: {tool: {source: request}}\ninspections: []\n")
    for command in ("ping", "reload"):
        assert main([command, "--config", str(config)]) == 2
        err = " ".join(capsys.readouterr().err.split())
        assert "has server.port 0 (any free port)" in err
        assert "give --server HOST:PORT" in err


def test_results_into_a_pipe_keep_names_and_times_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Into a file or pipe Rich assumed 80 columns and cut 'inspecti…' and '2026-11-…'."""
    import time

    from vision_server.commands import main
    from vision_server.results import ResultEntry, ResultLog

    name = "bracket_plate_width_check_station_3"
    log = ResultLog(tmp_path / "results.sqlite3")
    data = {"width_mm": 125.2, "hole_mm": 2.83, "count": 3}
    log.record(ResultEntry(time.time(), name, "overhead_camera", True, data, 12.3, "abc"))
    log.close()
    assert main(["results", "--db", str(tmp_path / "results.sqlite3")]) == 0
    out = capsys.readouterr().out
    assert name in out
    assert "overhead_camera" in out
    assert "…" not in out
