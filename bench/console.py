"""2d. The web console's cost (issue 17): the protocol path's INSPECT throughput with the
console closed and while a person has it open, and the live view's latency and frame rate.

One server process (bench/console_server.py): the bench catalog with the console on, plus a
camera of known rate, ``live`` (a video file played in real time at 30 fps, the ``opencv``
source), the console's read cap at 10 frames per second (the example cell's ``max_view_fps``).
A viewer process (bench/console_viewer.py) asks what the page's JavaScript asks at the page's
rhythm, on the Cameras page (the live view: every camera's card, the list, the status pill)
or on the Server page. Its frames of ``live`` carry the camera's capture time
(``X-Frame-Timestamp``): latency is capture to arrival at the HTTP client (same machine,
same clock; a browser would add its JPEG decode), the frame rate counts distinct frames.

INSPECT load: a few protocol clients, each one request at a time, on the tool camera's
1024x768 image, for a light inspection (``brightness``) and a CPU-bound one (``cap_locate``).
Each (page, inspection) cell runs a window after a warm-up; the pages take turns in rounds
(console closed, Cameras, Server, rotating the order each round) so that drift of a shared
machine falls on all of them; throughput is summed over the rounds. Goal (issue 17): with the
console open, INSPECT throughput >= 0.9x without.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import queue
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from . import console_viewer
from .busy import Retrier, make_client, retry_mode
from .common import Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .console_server import CAMERA_FPS, LIVE_CAMERA, MAX_VIEW_FPS, write_config
from .env import Env
from .plots import cdf, log_scale_if_positive, pyplot, save
from .servers import ServerProcess

NAME = "console"
TITLE = "2d. The web console: its cost to INSPECT, and the live view"
INSPECTIONS = ("brightness", "cap_locate")
CLIENTS = 4
PAGES = ("closed", "cameras", "server")
OPEN_PAGES = ("cameras", "server")
PAGE_LABEL = {
    "closed": "console closed",
    "cameras": "Cameras page (live view)",
    "server": "Server page",
}
RATIO_GOAL = 0.9
"""INSPECT throughput with the console open ÷ with it closed."""
READY_TIMEOUT_S = 60.0
DRAIN_S = 10.0


@dataclass
class Window:
    """One (page, inspection) cell of one round: INSPECT answers inside ``window_s``."""

    page: str
    inspection: str
    window_s: float
    start: float = float("nan")
    """Unix seconds (the viewer's frames are matched to windows by time)."""
    end: float = float("nan")
    answers: int = 0
    latencies: list[float] = field(default_factory=list)
    busy: int = 0
    errors: int = 0
    server_cpu_s: float = float("nan")


async def _load(server: ServerProcess, cell: Window, image: Any, warmup_s: float) -> None:
    """``CLIENTS`` clients, one INSPECT at a time each, for ``warmup_s`` + the window."""
    busy_timeout_s = warmup_s + cell.window_s + DRAIN_S
    clients = [make_client(server.port, busy_timeout_s=busy_timeout_s) for _ in range(CLIENTS)]
    await asyncio.gather(*(c.connect() for c in clients))
    retrier = Retrier(seed=len(cell.inspection) * 31 + CLIENTS)
    window_start = time.perf_counter() + warmup_s
    window_end = window_start + cell.window_s
    marks: dict[str, tuple[float, float, int]] = {}

    async def client_loop(client: Any) -> None:
        while time.perf_counter() < window_end:
            t0 = time.perf_counter()
            try:
                answer = await retrier.inspect(
                    client, cell.inspection, image, until=window_end + DRAIN_S
                )
            except Exception:  # noqa: BLE001 - counted, reported
                cell.errors += 1
                continue
            t1 = time.perf_counter()
            if answer is None:
                return
            if window_start <= t1 <= window_end:
                cell.answers += 1
            if t0 >= window_start:
                cell.latencies.append((t1 - t0) * 1000.0)

    async def clock() -> None:
        await asyncio.sleep(max(0.0, window_start - time.perf_counter()))
        marks["start"] = (time.time(), server.cpu_seconds(), retrier.busy(clients))
        await asyncio.sleep(max(0.0, window_end - time.perf_counter()))
        marks["end"] = (time.time(), server.cpu_seconds(), retrier.busy(clients))

    try:
        await asyncio.gather(clock(), *(client_loop(c) for c in clients))
    finally:
        await asyncio.gather(*(c.close() for c in clients), return_exceptions=True)
    cell.start, cell.end = marks["start"][0], marks["end"][0]
    cell.server_cpu_s = marks["end"][1] - marks["start"][1]
    cell.busy = marks["end"][2] - marks["start"][2]


class Viewer:
    """The viewer process (bench/console_viewer.py): ``open(page)`` switches what it looks at
    and returns what it did on the page it left."""

    def __init__(self, base: str) -> None:
        context = multiprocessing.get_context("spawn")
        self.control: Any = context.Queue()
        self.out: Any = context.Queue()
        self.process = context.Process(
            target=console_viewer.main,
            args=(base, LIVE_CAMERA, self.control, self.out),
            name="bench-console-viewer",
        )
        self.process.start()

    def _next(self, kind: str) -> Any:
        try:
            got, value = self.out.get(timeout=READY_TIMEOUT_S)
        except queue.Empty:
            raise RuntimeError(
                f"the console viewer gave no {kind} within {READY_TIMEOUT_S:g} s (alive: "
                f"{self.process.is_alive()}, exit code {self.process.exitcode})"
            ) from None
        if got != kind:
            raise RuntimeError(f"the console viewer sent {got!r} where {kind!r} was due")
        return value

    def open(self, page: str) -> console_viewer.Segment:
        self.control.put(page)
        left: console_viewer.Segment = self._next("segment")
        self._next("ready")
        return left

    def close(self) -> None:
        if self.process.is_alive():
            self.control.put("stop")  # it answers with a last segment, not read here
            self.process.join(READY_TIMEOUT_S)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(10.0)


@dataclass(frozen=True)
class LiveFigures:
    """The live view over one stretch of time: latency capture -> arrival (ms), the frame
    rate reached (distinct frames per second), and how many frame.jpg answers there were."""

    latencies: list[float]
    fps: float
    answers: int


def live_figures(frames: list[tuple[float, float]], start: float, end: float) -> LiveFigures:
    """``frames`` (captured, received) that arrived between ``start`` and ``end`` (Unix s)."""
    inside = [(c, r) for c, r in frames if start <= r <= end and c == c]
    latencies = [(r - c) * 1000.0 for c, r in inside]
    distinct = len({c for c, _ in inside})
    fps = distinct / (end - start) if end > start else float("nan")
    return LiveFigures(latencies, fps, len(inside))


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    try:
        import aiohttp  # noqa: F401 - the console's own library, and the viewer's
    except ImportError:
        raise Skip("aiohttp is not installed: the server has no console") from None
    image = np.ascontiguousarray(env.samples.tool)
    config = write_config(cfg.workdir, env.samples.qc)
    server = ServerProcess(
        "console", cfg.workdir, "--config", str(config), module="bench.console_server"
    )
    try:
        return _measure(cfg, section, server, image)
    finally:
        server.stop()


def _measure(cfg: RunConfig, section: Section, server: ServerProcess, image: Any) -> Section:
    info = server.info
    missing = [n for n in INSPECTIONS if n not in info["inspections"]]
    if missing:
        raise Skip(f"inspection(s) {', '.join(missing)} not served")
    rounds = cfg.n(3, 1)
    windows_s = {"brightness": cfg.f(3.0, 0.3), "cap_locate": cfg.f(5.0, 0.4)}
    warmup_s = cfg.f(0.5, 0.1)
    idle_s = cfg.f(5.0, 0.5)
    viewer = Viewer(str(info["console_url"]))
    cells: list[Window] = []
    segments: list[console_viewer.Segment] = []
    try:
        viewer.open("cameras")  # the live view alone, no INSPECT load
        idle_start = time.time()
        time.sleep(idle_s)  # the measuring window of the idle live view, not a verdict
        idle_end = time.time()
        idle_segment = viewer.open("closed")
        for round_ in range(rounds):
            order = PAGES[round_ % len(PAGES) :] + PAGES[: round_ % len(PAGES)]
            for page in order:
                viewer.open(page)
                for name in INSPECTIONS:
                    cell = Window(page, name, windows_s[name])
                    asyncio.run(_load(server, cell, image, warmup_s))
                    cells.append(cell)
                segments.append(viewer.open("closed"))
    finally:
        viewer.close()

    section.intro = (
        f"One server process with the console on (`max_view_fps` {MAX_VIEW_FPS:g}) and "
        f"{info['workers']} workers; camera `{LIVE_CAMERA}` plays a 1024x768 video in real time "
        f"at {CAMERA_FPS:g} fps. INSPECT: {CLIENTS} protocol clients, one request at a time "
        f"each, on the tool camera's 1024x768 image; BUSY is retried {retry_mode()}. Windows: "
        + ", ".join(f"{n} {w:g} s" for n, w in windows_s.items())
        + f" after {warmup_s:g} s warm-up, in {rounds} round(s) of the pages "
        "(closed, Cameras, Server; the order rotates each round). The viewer is an aiohttp "
        "client in its own process asking what the page asks at the page's rhythm "
        "(bench/console_viewer.py); on the Cameras page that is every camera's card "
        f"({max((s.cards for s in segments), default=0)} frame.jpg pollers), the camera list "
        "and the status pill."
    )
    _throughput(section, cells)
    _viewer_load(section, segments)
    _live(section, cells, segments, idle_segment, idle_start, idle_end)
    return section


def _total_rps(cells: list[Window]) -> float:
    seconds = sum(c.window_s for c in cells)
    return sum(c.answers for c in cells) / seconds if seconds else float("nan")


def _cpu_ms_per_answer(cells: list[Window]) -> float:
    """The server process's CPU time per INSPECT answered (ms): what the console adds to
    each request, steadier than throughput on a machine others share."""
    answers = sum(c.answers for c in cells)
    return 1000.0 * sum(c.server_cpu_s for c in cells) / answers if answers else float("nan")


def _throughput(section: Section, cells: list[Window]) -> None:
    table = Table(
        [
            "inspection",
            "console",
            "requests/s",
            "÷ closed",
            "per round ÷ closed",
            "p50 ms",
            "p99 ms",
            "server CPU ms per answer",
            "÷ closed",
            "BUSY",
            "errors",
        ],
        caption="INSPECT throughput (summed over the rounds) with the console closed and open:",
    )
    for name in INSPECTIONS:
        mine = [c for c in cells if c.inspection == name]
        closed = [c for c in mine if c.page == "closed"]
        closed_rps = _total_rps(closed)
        closed_cpu_ms = _cpu_ms_per_answer(closed)
        for page in PAGES:
            here = [c for c in mine if c.page == page]
            rps = _total_rps(here)
            # A window with no answer at all (a machine others load) has no ratio: "n/a".
            pairs = zip(here, closed, strict=True)
            per_round = [a.answers / b.answers for a, b in pairs if b.answers]
            stats = Stats.of(x for c in here for x in c.latencies)
            cpu_ms = _cpu_ms_per_answer(here)
            spread = (
                "-"
                if page == "closed"
                else f"{min(per_round):.2f}–{max(per_round):.2f}"
                if per_round and all(b.answers for b in closed)
                else "n/a"
            )
            table.add(
                name,
                PAGE_LABEL[page],
                fmt(rps, 1),
                ratio(rps, closed_rps),
                spread,
                fmt(stats.p50, 2),
                fmt(stats.p99, 2),
                fmt(cpu_ms, 2),
                ratio(cpu_ms, closed_cpu_ms),
                sum(c.busy for c in here),
                sum(c.errors for c in here),
            )
            section.value(f"{name}_{page}_rps", rps)
            section.value(f"{name}_{page}_server_cpu_ms_per_answer", cpu_ms)
            if page == "closed":
                continue
            section.value(f"{name}_{page}_over_closed", rps / closed_rps)
            section.value(f"{name}_{page}_cpu_per_answer_over_closed", cpu_ms / closed_cpu_ms)
            section.goals.append(
                Goal(
                    f"{name}: INSPECT throughput with the console open on the "
                    f"{PAGE_LABEL[page]} >= {RATIO_GOAL}x with the console closed",
                    f"{fmt(rps, 1)} ÷ {fmt(closed_rps, 1)} req/s = {ratio(rps, closed_rps)} "
                    f"(per round {spread})",
                    rps >= RATIO_GOAL * closed_rps,
                )
            )
    section.tables.append(table)
    section.notes.append(
        "On a machine shared with other work the per-round ratios spread further than the "
        "console's effect (see the column); the sums over the rounds are the figures judged. "
        "The server's CPU time per answer is the steadier measure of what the console adds "
        "to each request."
    )
    section.notes.append(
        "The console's observer of results (the request cameras' last image) is subscribed in "
        "every row, closed included: the server is the same process; 'closed' means nobody "
        "has the page open."
    )


def _viewer_load(section: Section, segments: list[console_viewer.Segment]) -> None:
    table = Table(
        ["console", "HTTP requests/s", "KB/s", "viewer CPU", "errors"],
        caption="What the open page asked of the server (the viewer process, over its pages):",
    )
    for page in OPEN_PAGES:
        mine = [s for s in segments if s.page == page]
        seconds = sum(s.ended - s.started for s in mine)
        if not mine or seconds <= 0:
            continue
        requests = sum(s.requests for s in mine)
        table.add(
            PAGE_LABEL[page],
            fmt(requests / seconds, 1),
            fmt(sum(s.bytes for s in mine) / seconds / 1000.0, 0),
            f"{100.0 * sum(s.cpu_s for s in mine) / seconds:.0f} %",
            sum(s.errors for s in mine),
        )
        section.value(f"viewer_{page}_requests_per_s", requests / seconds)
        errors = [s.first_error for s in mine if s.first_error]
        if errors:
            section.notes.append(f"{PAGE_LABEL[page]}: the viewer saw errors, first: {errors[0]}")
    section.tables.append(table)
    section.notes.append(
        "The viewer runs on the same machine as the server and the clients and uses its CPU "
        "(column 'viewer CPU'); a tablet at the cell would not. Its share is part of the "
        "measured cost here: with a remote browser the ratios would be, if anything, higher."
    )


def _live(
    section: Section,
    cells: list[Window],
    segments: list[console_viewer.Segment],
    idle: console_viewer.Segment,
    idle_start: float,
    idle_end: float,
) -> None:
    frames = [f for s in segments if s.page == "cameras" for f in s.frames]
    camera_fps = [x for s in [idle, *segments] for x in s.camera_fps]
    measured_fps = float(np.median(camera_fps)) if camera_fps else float("nan")
    asked_fps = 1.0 / console_viewer.frame_interval_s(
        {"source": "opencv", "view_fps": MAX_VIEW_FPS}
    )
    table = Table(
        [
            "INSPECT load",
            "frames",
            "capture → arrival p50 ms",
            "p99 ms",
            "frames/s reached",
            "÷ the camera's rate",
            "÷ the view cap",
        ],
        caption=(
            f"The live view of `{LIVE_CAMERA}`: the camera plays {CAMERA_FPS:g} fps (the "
            f"server measured {fmt(measured_fps, 1)}), the console reads at most "
            f"{MAX_VIEW_FPS:g} per second, the page starts a read every "
            f"{1000.0 / asked_fps:.0f} ms (at once after a slower one):"
        ),
    )
    stretches: list[tuple[str, str, LiveFigures]] = [
        ("none", "idle", live_figures(idle.frames, idle_start, idle_end))
    ]
    for name in INSPECTIONS:
        mine = [c for c in cells if c.page == "cameras" and c.inspection == name]
        parts = [live_figures(frames, c.start, c.end) for c in mine]
        seconds = sum(c.end - c.start for c in mine)
        distinct = sum(p.fps * (c.end - c.start) for p, c in zip(parts, mine, strict=True))
        merged = LiveFigures(
            [x for p in parts for x in p.latencies],
            distinct / seconds if seconds > 0 else float("nan"),
            sum(p.answers for p in parts),
        )
        stretches.append((f"{CLIENTS} clients {name}", name, merged))
    for label, key, figures in stretches:
        s = Stats.of(figures.latencies)
        table.add(
            label,
            figures.answers,
            fmt(s.p50, 1),
            fmt(s.p99, 1),
            fmt(figures.fps, 1),
            ratio(figures.fps, CAMERA_FPS),
            ratio(figures.fps, MAX_VIEW_FPS),
        )
        section.value(f"live_{key}_p50_ms", s.p50)
        section.value(f"live_{key}_p99_ms", s.p99)
        section.value(f"live_{key}_fps", figures.fps)
    section.value("live_camera_fps", CAMERA_FPS)
    section.value("live_camera_measured_fps", measured_fps)
    section.tables.append(table)
    section.notes.append(
        "Frame rate reached: distinct frames (by capture time) that arrived per second. The "
        "page starts a read every interval, never two at once (js/poll.js), and the server "
        "reads a new frame when the previous read began at least 0.9 interval ago; the "
        "camera's rate is above the cap on purpose (the cap is what the console promises, "
        "not the camera)."
    )
    section.notes.append(
        "A live frame is read through the service (admission, the worker pool): under a "
        "CPU-bound INSPECT load it waits its turn like any request, which is the latency "
        "the rows under load show."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, (bars, lat) = plt.subplots(1, 2, figsize=(11, 4))
        x = np.arange(len(INSPECTIONS))
        for offset, page in enumerate(OPEN_PAGES):
            heights = [section.values.get(f"{n}_{page}_over_closed", np.nan) for n in INSPECTIONS]
            bars.bar(x + (offset - 0.5) * 0.35, heights, 0.35, label=PAGE_LABEL[page])
        bars.axhline(RATIO_GOAL, color="k", linestyle="--", linewidth=1, label="goal")
        bars.set_xticks(x, INSPECTIONS)
        bars.set_ylabel("INSPECT req/s ÷ console closed")
        bars.set_ylim(0.0, 1.2)
        bars.grid(True, axis="y", alpha=0.3)
        bars.legend(fontsize=8)
        for label, _, figures in stretches:
            if figures.latencies:
                cdf(lat, figures.latencies, f"INSPECT load: {label}")
        log_scale_if_positive(lat, "x")
        lat.set_xlabel(f"live view: capture → arrival [ms] ({LIVE_CAMERA}, {CAMERA_FPS:g} fps)")
        lat.set_ylabel("fraction of frames")
        lat.grid(True, alpha=0.3)
        lat.legend(fontsize=8)
        return [save(fig, directory / "console.png")]

    section.plot = plot
