"""``robot-client teach`` refuses a record that names an inspection the vision server does not
have, when the server answers (and teaches offline when it cannot be reached)."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples" / "scenes" / "grundfos_cell.yaml"


def teach(tmp: Path, server: str, *params: str) -> subprocess.CompletedProcess[str]:
    """``robot-client --server SERVER teach quality_control magnet PARAMS`` as a process."""
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "robot_client.commands.program",
            "--server",
            server,
            "--timeout",
            "20",
            "teach",
            "quality_control",
            "magnet",
            *params,
            "--store",
            str(tmp / "taught.yaml"),
            "--scene",
            str(SCENE),
            "--state-file",
            str(tmp / "world.json"),
            "--json",
        ],  # fmt: skip
        cwd=tmp,
        env={**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "300"},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def taught(tmp: Path) -> list[str]:
    store = tmp / "taught.yaml"
    if not store.is_file():
        return []
    data = yaml.safe_load(store.read_text(encoding="utf-8")) or {}
    return [str(r["params"]["inspection"]) for r in data.get("records", [])]


def test_teach_refuses_an_inspection_the_server_does_not_have(
    tmp_path: Path,
    cell_config: Callable[..., Path],
    live_server: Callable[[Path], contextlib.AbstractContextManager[int]],
) -> None:
    config = cell_config(tmp_path, tmp_path / "world.json")
    with live_server(config) as port:
        refused = teach(tmp_path, f"127.0.0.1:{port}", "inspection=nosuch")
        assert refused.returncode == 2, refused.stdout + refused.stderr
        # With --json, errors are JSON on stdout too (docs/integrator-guide.md §6).
        message = json.loads(refused.stdout)["error"]["message"]
        assert (
            "skill 'quality_control': inspection='nosuch' is not an inspection of the vision "
            "server (it has: cap_locate, magnet_check, station_pose, station_qr)" in message
        )
        assert taught(tmp_path) == []  # nothing stored

        accepted = teach(tmp_path, f"127.0.0.1:{port}", "inspection=magnet_check")
        assert accepted.returncode == 0, accepted.stdout + accepted.stderr
        assert taught(tmp_path) == ["magnet_check"]


def test_teach_offline_is_allowed_when_the_server_cannot_be_reached(tmp_path: Path) -> None:
    with socket.socket() as closed:  # bound, not listening: connections are refused
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
        done = teach(tmp_path, f"127.0.0.1:{port}", "inspection=nosuch")
    assert done.returncode == 0, done.stdout + done.stderr
    assert taught(tmp_path) == ["nosuch"]
