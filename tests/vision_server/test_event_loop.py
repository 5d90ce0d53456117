"""``server: event_loop`` (issue 33): ``serve`` runs on asyncio's loop or on uvloop's, and the
same requests are answered the same on both. Which loop the process really runs is noted in
the process itself (a round trip would look the same on either): the child wraps the loop
factory ``serve`` uses and writes down the class of the loop it made. A loop that is not known
is a configuration error naming the key."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from loopback import run

from robot_client import VisionClient
from vision_server.config import ConfigError, load_config
from vision_server.process import EVENT_LOOPS, uvloop_available

ROOT = Path(__file__).resolve().parents[2]
CELL = """\
server: {{port: 0, event_loop: {loop}}}
results: {{enabled: false}}
cameras:
  tool: {{source: request}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 10}}
"""

CHILD = """
import sys
from vision_server.commands import program

real = program.loop_factory

def noting(name):
    make = real(name)

    def made():
        loop = make()
        with open(sys.argv[2], "w") as out:
            out.write(type(loop).__module__)
        return loop

    return made

program.loop_factory = noting
sys.exit(program.main(["serve", "--config", sys.argv[1]]))
"""


def _cell(tmp_path: Path, loop: str) -> Path:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.format(loop=loop), encoding="utf-8")
    return path


@pytest.mark.parametrize("loop", EVENT_LOOPS)
def test_serve_runs_on_the_configured_loop_and_answers_the_same(tmp_path: Path, loop: str) -> None:
    if loop == "uvloop" and not uvloop_available():
        pytest.skip("uvloop is not installed (the extra cellvision[uvloop]; make test has it)")
    noted = tmp_path / "loop.txt"
    env = {k: v for k, v in os.environ.items() if not k.startswith("CELLVISION_")}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *sys.path])
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(_cell(tmp_path, loop)), str(noted)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert proc.stdout is not None
    try:
        line = proc.stdout.readline()
        assert line.startswith("vision-server listening on 127.0.0.1:"), line
        port = int(line.rsplit(":", 1)[1])
        image = np.full((48, 64), 200, np.uint8)

        async def ask() -> list[bool]:
            async with VisionClient("127.0.0.1", port, request_timeout_s=10.0) as client:
                await client.ping()
                # Enough requests that the later ones run on the loop itself (inline_ms).
                return [(await client.inspect("bright", image)).passed for _ in range(5)]

        assert run(ask()) == [True] * 5
    finally:
        proc.send_signal(signal.SIGTERM)
        _, errors = proc.communicate(timeout=60)
    assert proc.returncode == 0, errors
    assert noted.read_text().split(".")[0] == loop


def test_an_unknown_loop_is_a_configuration_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="event_loop"):
        load_config(_cell(tmp_path, "tokio"))


def test_the_default_loop_is_asyncio(tmp_path: Path) -> None:
    path = tmp_path / "cell.yaml"
    path.write_text(CELL.format(loop="asyncio").replace(", event_loop: asyncio", ""))
    assert load_config(path).server.event_loop == "asyncio"
