"""Running the two command-line tools as a user does (subprocesses), and ``vision-server serve``
processes to run them against: shared by tests/test_cli_tools.py and tests/test_cli_output.py."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent.parent
LISTENING = re.compile(r"vision-server listening on (\S+):(\d+)\n")
TOOLS = {
    "vision-server": [sys.executable, "-m", "vision_server"],
    "robot-client": [sys.executable, "-m", "robot_client.commands.program"],
}
INSPECTIONS = (
    "cameras: {tool: {source: request}}\n"
    "inspections:\n"
    "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 100}\n"
)


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    return {**env, "PYTHONPATH": str(REPO_ROOT), **extra}


def tool(name: str, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    """Run ``vision-server`` or ``robot-client`` with ``args`` and only the given CELLVISION_*
    environment variables."""
    return subprocess.run(
        [*TOOLS[name], *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=_env(**env),
        check=False,
    )


@dataclass(frozen=True)
class Server:
    address: str
    config: Path
    token_file: Path | None = None
    cert: Path | None = None


def _serve(config: Path) -> Iterator[Server]:
    proc = subprocess.Popen(
        [*TOOLS["vision-server"], "serve", "--config", str(config)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        match = LISTENING.fullmatch(line)
        assert match, f"the server did not start: {line!r} {proc.communicate(timeout=30)}"
        yield Server(f"127.0.0.1:{match[2]}", config)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=30)
