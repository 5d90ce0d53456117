"""``robot-client`` against a live server (in a background thread) and against nothing."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from loopback import server_in_thread

from robot_client.address import ENV_VAR
from robot_client.commands.program import main

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def address() -> Iterator[str]:
    with server_in_thread() as server:
        yield f"127.0.0.1:{server.port}"


@pytest.fixture(autouse=True)
def _no_env_address(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)


def _flat(text: str) -> str:
    """Rich wraps long lines at the console width: compare words, not lines."""
    return " ".join(text.split())


def test_ping_json(address: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--server", address, "ping", "--json", "-n", "3"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["server"] == {"name": "cellvision", "version": "0.1.0"}
    assert report["protocol"] == [1, 1]
    assert len(report["rtt_ms"]) == 3
    assert all(rtt >= 0.0 for rtt in report["rtt_ms"])


def test_ping_text(address: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--server", address, "ping"]) == 0
    out = _flat(capsys.readouterr().out)
    assert out.startswith(f"PONG from cellvision 0.1.0 at {address} (protocol 1.1):")
    assert out.endswith(" ms")


def test_inspections_json(address: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--server", address, "inspections", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report == {
        "inspections": [
            {
                "name": "brightness",
                "type": "presence",
                "camera": "tool",
                "camera_source": "request",
                "depth": False,
            }
        ]
    }


def test_inspections_table(address: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--server", address, "inspections"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if "brightness" in line)
    assert row.replace("│", " ").split() == ["brightness", "presence", "tool", "request", "no"]


def test_server_address_from_the_environment(
    address: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(ENV_VAR, address)
    assert main(["ping", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["protocol"] == [1, 1]


def test_no_server_is_a_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
        port = holder.getsockname()[1]
        code = main(["--server", f"127.0.0.1:{port}", "--timeout", "2", "ping"])
    captured = capsys.readouterr()
    assert code == 3  # a connection error
    assert captured.out == ""
    err = _flat(captured.err)
    assert err.startswith(f"error: cannot connect to 127.0.0.1:{port}")
    assert "Traceback" not in err


def test_bad_address_is_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--server", "cell:port", "ping"]) == 2
    assert "bad port 'port'" in _flat(capsys.readouterr().err)


def test_auth_token(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    good, bad = tmp_path / "good", tmp_path / "bad"
    good.write_text("s3cret\n")
    bad.write_text("nope\n")
    with server_in_thread(auth_token="s3cret") as server:
        address = f"127.0.0.1:{server.port}"
        assert main(["--server", address, "--token-file", str(good), "ping", "--json"]) == 0
        capsys.readouterr()
        assert main(["--server", address, "--token-file", str(bad), "ping"]) == 4
        assert _flat(capsys.readouterr().err).startswith("NOT_AUTHENTICATED:")
        assert main(["--server", address, "ping"]) == 4
        assert _flat(capsys.readouterr().err).startswith("NOT_AUTHENTICATED:")


def test_as_a_process(address: str) -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "robot_client.commands.program",
            "--server",
            address,
            "inspections",
            "--json",
        ],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert [i["name"] for i in json.loads(done.stdout)["inspections"]] == ["brightness"]


def test_inspect_an_image_file(
    address: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import cv2
    import numpy as np

    image = tmp_path / "bright.png"
    cv2.imwrite(str(image), np.full((48, 64), 200, np.uint8))
    code = main(["--server", address, "inspect", "brightness", "--image", str(image), "--json"])
    report = json.loads(capsys.readouterr().out)
    assert report["inspection"] == "brightness"
    assert report["verdict"] in ("pass", "fail")
    assert code == (0 if report["verdict"] == "pass" else 1)
    assert (
        main(["--server", address, "inspect", "brightness", "--image", str(tmp_path / "x.png")])
        == 2
    )
    err = _flat(capsys.readouterr().err)
    assert "cannot read" in err
    assert "x.png" in err


def test_a_token_on_the_command_line_is_deprecated(
    address: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--auth-token`` shows the token in ps: it still works, and says it is deprecated."""
    assert main(["--server", address, "--auth-token", "x", "ping"]) == 0
    err = _flat(capsys.readouterr().err)
    assert "--auth-token is deprecated" in err
    assert "--token-file" in err
