"""An invalid configuration file is a configuration error, exit 2, from every ``vision-server``
command that reads one (issue 28): ``check-config`` exited 1, the fail verdict's code, while
``--help``, its own ``--json`` error kind ("usage") and ``serve``, ``run`` and ``modbus-map``
said 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from protocol.cli import ErrorKind, ExitCode
from vision_server.commands import main

ROOT = Path(__file__).resolve().parents[2]
INVALID = "server:\n  port: seven\ncameras: {tool: {source: request}}\ninspections: []\n"
WHY = "bad.yaml:2 server -> port: expected an integer, got 'seven'"


def _vision_server(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *sys.path])
    return subprocess.run(
        [sys.executable, "-m", "vision_server", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )


@pytest.fixture
def invalid(tmp_path: Path) -> Path:
    path = tmp_path / "bad.yaml"
    path.write_text(INVALID, encoding="utf-8")
    return path


def test_check_config_exits_2_on_an_invalid_file(invalid: Path) -> None:
    done = _vision_server("check-config", invalid.name, cwd=invalid.parent)
    assert done.returncode == ExitCode.USAGE == 2, done.stderr
    assert done.stdout == ""
    assert WHY in " ".join(done.stderr.split())


def test_check_config_json_exits_with_its_error_kinds_code(invalid: Path) -> None:
    done = _vision_server("check-config", "--json", invalid.name, cwd=invalid.parent)
    report = json.loads(done.stdout)
    assert report["valid"] is False
    assert report["error"]["kind"] == ErrorKind.USAGE.value
    assert done.returncode == ErrorKind.USAGE.exit_code == 2
    assert (report["error"]["line"], report["error"]["path"]) == (2, "server -> port")


def test_check_config_still_exits_0_on_a_valid_file(tmp_path: Path) -> None:
    path = tmp_path / "good.yaml"
    path.write_text(INVALID.replace("seven", "0"), encoding="utf-8")
    assert _vision_server("check-config", path.name, cwd=tmp_path).returncode == 0


def test_every_command_that_reads_a_configuration_agrees(
    invalid: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The same file, the same code: a script may test ``check-config`` for what ``serve``
    would say."""
    commands = {
        "check-config": ["check-config", str(invalid)],
        "serve": ["serve", "--config", str(invalid), "--port", "0"],
        "run": ["run", "--config", str(invalid), "x", "--image", "x.png"],
        "modbus-map": ["modbus-map", str(invalid)],
    }
    codes = {name: main(argv) for name, argv in commands.items()}
    assert codes == dict.fromkeys(commands, int(ExitCode.USAGE))
    err = " ".join(capsys.readouterr().err.split())
    assert err.count(WHY) == len(commands), err


def test_help_states_the_code(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "2 usage or configuration error (an invalid file for check-config too)" in text
