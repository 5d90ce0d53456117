"""``make demo STAY=1`` (``python -m robot_client.demo --stay``): after the task the vision
server and its web console stay up for a person to look at, until Ctrl-C.

The demo runs as a person starts it (a subprocess, its own process group as a terminal's
foreground job); the test reads the console's address from its output, finds the demo's
results and live frames through the console's HTTP API, then presses Ctrl-C (SIGINT to the
process group) and checks a clean exit with the server gone. Every wait is for a line or a
condition, with a timeout; nothing is timed."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import subprocess
import sys
import threading
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from robot_client.demo import task as demo

REPO = Path(__file__).resolve().parent.parent
STARTUP_S = 180.0  # the whole task runs before the wait: generous on a shared machine
EXIT_S = 60.0


class Lines:
    """A subprocess's output, line by line, read by a thread (a test never blocks on it)."""

    def __init__(self, process: subprocess.Popen[str]) -> None:
        self.seen: list[str] = []
        self._queue: queue.Queue[str | None] = queue.Queue()
        assert process.stdout is not None
        stream = process.stdout

        def read() -> None:
            for line in stream:
                self._queue.put(line)
            self._queue.put(None)

        threading.Thread(target=read, daemon=True).start()

    def wait_for(self, pattern: str, timeout_s: float) -> re.Match[str]:
        """The first line (from here on) matching ``pattern``; fails at end of output or after
        ``timeout_s`` with everything read so far."""
        regex = re.compile(pattern)
        for line in self.seen:
            if found := regex.search(line):
                return found
        while True:
            try:
                line = self._queue.get(timeout=timeout_s)
            except queue.Empty:
                pytest.fail(f"no line {pattern!r} within {timeout_s:g} s:\n{''.join(self.seen)}")
            if line is None:
                pytest.fail(f"the demo ended without {pattern!r}:\n{''.join(self.seen)}")
            self.seen.append(line)
            if found := regex.search(line):
                return found

    def rest(self, timeout_s: float) -> str:
        """Everything up to the end of the output."""
        while True:
            line = self._queue.get(timeout=timeout_s)
            if line is None:
                return "".join(self.seen)
            self.seen.append(line)


def get(url: str) -> tuple[int, str, bytes]:
    with urllib.request.urlopen(url, timeout=30.0) as response:
        return response.status, response.headers.get("Content-Type", ""), response.read()


def get_json(url: str) -> Any:
    status, kind, body = get(url)
    assert status == 200
    assert kind.startswith("application/json"), kind
    return json.loads(body)


@pytest.fixture
def staying_demo(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Lines]]:
    env = dict(os.environ, PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    process = subprocess.Popen(
        [sys.executable, "-m", "robot_client.demo", "--stay", "--no-live"]
        + ["--output", str(tmp_path / "out")],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        process_group=0,  # a terminal's foreground job: Ctrl-C goes to this group
    )
    try:
        yield process, Lines(process)
    finally:
        if process.poll() is None:  # the test failed before its Ctrl-C: stop what it started
            os.killpg(process.pid, signal.SIGINT)
            try:
                process.wait(timeout=EXIT_S)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


def test_the_demo_stays_up_with_its_results_in_the_console_until_ctrl_c(
    staying_demo: tuple[subprocess.Popen[str], Lines],
) -> None:
    process, lines = staying_demo
    url = lines.wait_for(r"web console: (http://\S+/)", STARTUP_S).group(1)
    lines.wait_for(r"Ctrl-C to stop", STARTUP_S)
    assert url in "".join(lines.seen[-3:])  # the address is repeated beside "Ctrl-C to stop"
    assert process.poll() is None  # the task is over, the demo waits

    rows = get_json(url + "api/results?limit=200")["results"]
    verdicts: dict[str, list[bool]] = {}
    for row in reversed(rows):  # oldest first
        verdicts.setdefault(row["inspection"], []).append(row["passed"])
    assert {"station_pose", "cap_locate", "magnet_check"} <= set(verdicts), verdicts
    # the injected failure first, the retry's pass last (the demo's overlay re-asks between)
    magnet = verdicts["magnet_check"]
    assert magnet[0] is False, magnet
    assert magnet[-1] is True, magnet
    assert sum(verdicts["cap_locate"]) >= 3  # views without a cap fail; three caps were found

    # The live view: the fixed camera renders the cell as the robot left it, and the tool
    # camera shows the last image the robot sent.
    for camera in ("qc", "tool"):
        status, kind, body = get(f"{url}api/cameras/{camera}/frame.jpg")
        assert (status, kind) == (200, "image/jpeg")
        assert body[:2] == b"\xff\xd8"  # a JPEG's start-of-image marker

    os.killpg(process.pid, signal.SIGINT)  # Ctrl-C
    output = lines.rest(EXIT_S)
    assert process.wait(timeout=EXIT_S) == 0, output
    assert "demo succeeded" in output
    assert "Traceback" not in output
    with pytest.raises(urllib.error.URLError):  # the server stopped with the demo
        get(url + "api/server")


def test_a_pace_that_is_not_a_duration_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        demo.main(["--pace", "-1"])
    assert exit_.value.code == 2
    assert "between 0 and 3600 seconds" in capsys.readouterr().err


def test_pace_pauses_after_every_step_and_hold_sees_the_server_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import time as real_time
    import types

    pauses: list[float] = []
    # The demo's own clock module only: the pauses are recorded, not slept.
    fake_time = types.SimpleNamespace(perf_counter=real_time.perf_counter, sleep=pauses.append)
    monkeypatch.setattr(demo, "time", fake_time)
    seen: dict[str, Any] = {}

    def hold(result: demo.DemoResult, server: demo.DemoServer) -> None:
        assert server.console_url is not None
        seen["steps"] = len(result.steps)
        seen["server"] = get_json(server.console_url + "api/server")

    result = demo.run_demo(tmp_path / "out", live=False, pace_s=0.25, hold=hold)
    assert result.ok, result.error
    assert pauses == [0.25] * len(result.steps)
    assert seen["steps"] == len(result.steps)  # hold runs once the task is done
    assert seen["server"]["name"] == "grundfos-cell"  # ... with the console still answering
