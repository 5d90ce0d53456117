"""2e. The line protocol against the binary protocol: trigger to answer on a server camera.

One ``vision-server serve`` process (its own, with this section's configuration) serves a
1024x768 server camera (a folder camera replaying the tool camera's rendered view of the
conveyor, stored as BMP so that reading it costs little) with two inspections: ``cap_locate``
(the example cell's circle locator, tens of ms) and ``brightness`` (a mean grey level, well
under a millisecond of compute, so that a front-end's own cost shows). A robot controller's
view of each protocol, one request at a time, on loopback:

- **binary**: ``VisionClient.inspect(name)`` with no image (the server's camera), from
  sending the INSPECT to the decoded RESULT;
- **line**: ``T <number>`` then one answer line read (``text`` format), from the write to the
  answer's line end.

The two are alternated request by request in one run, so that they share the machine's load.
Goal (issue 20): the line protocol's p50 <= 1.2x the binary protocol's, for the 1024x768
server-camera inspection (both inspections are reported; the goal is checked on each).
"""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path
from typing import Any

import cv2
import yaml

from .busy import make_client
from .cell import CONVEYOR_VIEW
from .common import SCENE, Goal, RunConfig, Section, Stats, Table, fmt, ratio
from .env import Env
from .plots import cdf, log_scale_if_positive, pyplot, save

NAME = "line"
TITLE = "2e. Line protocol vs binary protocol: server-camera trigger to answer"
GOAL = 1.2
INSPECTIONS = ("cap_locate", "brightness")


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def write_config(workdir: Path, line_port: int) -> Path:
    """A server whose camera ``shelf`` replays the tool camera's view of the conveyor."""
    from simulation import SimCell

    folder = workdir / "line-images"
    folder.mkdir(parents=True, exist_ok=True)
    cell = SimCell.from_yaml(SCENE, seed=3)
    cell.robot.move_linear(CONVEYOR_VIEW)
    image = cell.render("tool_camera").color
    if image.shape[:2] != (768, 1024):
        raise RuntimeError(f"the tool camera renders {image.shape[1]}x{image.shape[0]}")
    cv2.imwrite(str(folder / "view.bmp"), image)
    doc: dict[str, Any] = {
        "server": {"host": "127.0.0.1", "port": 0, "name": "bench-line"},
        "results": {"enabled": False},
        "cameras": {"shelf": {"source": "folder", "path": str(folder), "glob": "*.bmp"}},
        "inspections": [
            {
                "name": "cap_locate",
                "type": "locate",
                "camera": "shelf",
                "method": "circle",
                "circle": {"min_radius_px": 60, "max_radius_px": 100, "polarity": "bright"},
                "min_count": 1,
                "max_count": 10,
            },
            {
                "name": "brightness",
                "type": "presence",
                "camera": "shelf",
                "measure": "mean_intensity",
                "min": 0,
            },
        ],
        "line": {"enabled": True, "host": "127.0.0.1", "port": line_port},
    }
    path = workdir / "line-cell.yaml"
    path.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return path


async def _line_connection(port: int) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    async with asyncio.timeout(60.0):
        while True:  # the line port opens just after the main port's announcement
            try:
                return await asyncio.open_connection("127.0.0.1", port)
            except OSError:
                await asyncio.sleep(0.05)


async def _measure(
    port: int, line_port: int, number: int, name: str, repeat: int, warmup: int
) -> tuple[list[float], list[float]]:
    """(binary ms, line ms) of ``repeat`` alternated triggers, after ``warmup`` of each."""
    client = make_client(port, busy_timeout_s=60.0)
    await client.connect()
    reader, writer = await _line_connection(line_port)
    request = f"T {number}\n".encode("ascii")
    binary: list[float] = []
    line: list[float] = []
    try:
        for i in range(warmup + repeat):
            t0 = time.perf_counter_ns()
            result = await client.inspect(name)
            t1 = time.perf_counter_ns()
            writer.write(request)
            answer = await reader.readline()
            t2 = time.perf_counter_ns()
            if not answer.startswith(b"OK "):
                raise RuntimeError(f"T {number} answered {answer!r}")
            if result.inspection != name:
                raise RuntimeError(f"INSPECT {name} answered {result.inspection}")
            if i >= warmup:
                binary.append((t1 - t0) / 1e6)
                line.append((t2 - t1) / 1e6)
        writer.write(b"Q\n")
        await reader.readline()
    finally:
        writer.close()
        await client.close()
    return binary, line


def run(cfg: RunConfig, env: Env) -> Section:
    from robot_client.demo.cell import vision_server

    repeat = cfg.n(300, 5)
    warmup = cfg.n(20, 2)
    section = Section(NAME, TITLE, intro=(__doc__ or "").split("\n\n", 1)[1].strip())
    line_port = _free_port()
    config = write_config(cfg.workdir, line_port)
    table = Table(
        [
            "inspection",
            "binary p50 ms",
            "binary p99 ms",
            "line p50 ms",
            "line p99 ms",
            "line/binary p50",
            "line/binary p99",
        ],
        caption=f"{repeat} triggers each, alternated, one at a time; 1024x768 server camera",
    )
    samples: dict[str, tuple[list[float], list[float]]] = {}
    with vision_server(config, cfg.workdir / "server-line.log") as server:
        for number, name in enumerate(INSPECTIONS, start=1):
            binary, line = asyncio.run(
                _measure(server.port, line_port, number, name, repeat, warmup)
            )
            samples[name] = (binary, line)
            b, li = Stats.of(binary), Stats.of(line)
            table.add(
                name,
                fmt(b.p50),
                fmt(b.p99),
                fmt(li.p50),
                fmt(li.p99),
                ratio(li.p50, b.p50, 2),
                ratio(li.p99, b.p99, 2),
            )
            section.value(f"{name}_binary_p50_ms", b.p50)
            section.value(f"{name}_binary_p99_ms", b.p99)
            section.value(f"{name}_line_p50_ms", li.p50)
            section.value(f"{name}_line_p99_ms", li.p99)
            ratio_p50 = li.p50 / b.p50
            section.goals.append(
                Goal(
                    f"line-protocol trigger-to-answer p50 <= {GOAL}x the binary protocol's "
                    f"({name}, 1024x768 server camera)",
                    f"{ratio_p50:.2f}x ({li.p50:.2f} ms vs {b.p50:.2f} ms; p99 "
                    f"{li.p99:.2f} vs {b.p99:.2f} ms)",
                    ratio_p50 <= GOAL,
                )
            )
    section.tables.append(table)

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(1, len(samples), figsize=(5.0 * len(samples), 3.4))
        for ax, (name, (binary, line)) in zip(axes, samples.items(), strict=True):
            cdf(ax, binary, "binary protocol (VisionClient)")
            cdf(ax, line, "line protocol (T n, text)")
            log_scale_if_positive(ax, "x")
            ax.set_xlabel(f"{name}: trigger to answer [ms]")
            ax.set_ylabel("fraction of triggers")
            ax.legend(loc="lower right", fontsize=8)
        return [save(fig, directory / "line.png")]

    section.plot = plot
    section.notes.append(
        "Both protocols trigger the same inspection of the same server: capture from the "
        "folder camera (a BMP read), the analysis, the result log off. The line answer is a "
        "short text line; the binary one a RESULT frame with the inspection's full data."
    )
    return section
