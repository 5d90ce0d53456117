"""What the demos share: the vision server they start (a ``vision-server serve`` subprocess)
and the pick's error against the simulated cell's ground truth."""

from __future__ import annotations

import contextlib
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from geometry import invert_transform, transform_points
from simulation import SimCell


def _console_enabled(config: Path) -> bool:
    doc = yaml.safe_load(config.read_text(encoding="utf-8"))
    return bool((doc.get("console") or {}).get("enabled"))


@dataclass(frozen=True)
class DemoServer:
    """The demo's vision server: its protocol ``port``, the web console's address
    (``console_url``, None when the configuration does not enable the console) and ``stop``,
    which stops it (SIGTERM) and returns its exit code."""

    port: int
    console_url: str | None
    stop: Callable[[], int]


@contextlib.contextmanager
def vision_server(config: Path, log: Path) -> Iterator[DemoServer]:
    """``vision-server serve --config CONFIG --port 0`` in a subprocess: yields the port it
    bound (from its first line) and the console's address (from the next). Its other output
    goes to ``log``. It runs in its own process group, so that a Ctrl-C in the terminal
    reaches the demo only, which then stops the server itself (cleanly, once)."""
    command = [sys.executable, "-m", "vision_server", "serve", "--config", str(config)]
    with log.open("w", encoding="utf-8") as sink:
        process = subprocess.Popen(
            [*command, "--port", "0"],
            stdout=subprocess.PIPE,
            stderr=sink,
            text=True,
            process_group=0,
        )
        assert process.stdout is not None
        line = process.stdout.readline()
        sink.write(line)
        sink.flush()
        match = re.search(r"listening on \S+:(\d+)", line)
        console_url = None
        if match and _console_enabled(config):
            # serve prints the console's address on the line right after.
            line = process.stdout.readline()
            sink.write(line)
            address = re.search(r"web console on (\S+)", line)
            if address:
                console_url = address.group(1)
                print(f"web console: {console_url}", flush=True)

        def drain() -> None:  # keep the pipe empty (reload messages and the like)
            assert process.stdout is not None
            for rest in process.stdout:
                sink.write(rest)

        threading.Thread(target=drain, daemon=True).start()

        def stop() -> int:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
            try:
                return process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()
                return process.wait()

        try:
            if not match:
                stop()
                raise RuntimeError(f"the vision server did not start (see {log}): {line!r}")
            yield DemoServer(int(match.group(1)), console_url, stop)
        finally:
            stop()


def grasp_error_m(cell: SimCell) -> float:
    """How far the held part's true grasp point is from the TCP (the pick's error)."""
    held = cell.gripper.held
    assert held is not None
    tool_from_world = invert_transform(cell.world.world_from_tool())
    return float(np.linalg.norm(transform_points(tool_from_world, cell.gripper.grasp_point(held))))
