"""2. Throughput against concurrency: 1, 4, 16 and 64 clients (one connection each), each
either waiting for every answer before the next request ("one at a time") or keeping 4
requests in flight on its connection ("pipelined x4"), for a light inspection (``brightness``)
and a CPU-bound one (``cap_locate``, the circle locate of the vision pick), both on the tool
camera's 1024x768 image sent in the request.

Each cell runs for a fixed time after a warm-up; requests per second count the answers that
arrived in the measuring window; latency is from the first send to the answer, BUSY retries
included (a BUSY answer is retried with exponential back-off, as SPEC §6.1 asks: 5 ms
doubling up to 200 ms, with jitter; retries stop when the window closes). The
reference is the single client one at a time. CPU use of the server process and of this
(client) process over the window is reported: they share the machine's cores.

Goal: the CPU-bound inspection reaches >= 1.7x the single-client throughput on 2 cores.
"""

from __future__ import annotations

import asyncio
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol import Busy
from robot_client import VisionClient

from .common import Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .env import Env
from .plots import log_scale_if_positive, pyplot, save
from .servers import HOST, ServerProcess

NAME = "throughput"
TITLE = "2. Throughput against concurrency"
CLIENTS = (1, 4, 16, 64)
PIPELINE = 4
BUSY_BACKOFF_S = 0.005
BUSY_BACKOFF_MAX_S = 0.2
SCALING_GOAL = 1.7


@dataclass
class Cell:
    inspection: str
    clients: int
    depth: int
    window_s: float
    latencies: list[float] = field(default_factory=list)
    completed: int = 0
    busy: int = 0
    errors: int = 0
    server_cpu_s: float = float("nan")
    client_cpu_s: float = float("nan")

    @property
    def rps(self) -> float:
        return self.completed / self.window_s

    @property
    def mode(self) -> str:
        return "one at a time" if self.depth == 1 else f"pipelined x{self.depth}"


async def _run_cell(
    server: ServerProcess, cell: Cell, image: Any, warmup_s: float, max_requests: int
) -> None:
    clients = [VisionClient(HOST, server.port, request_timeout_s=60.0) for _ in range(cell.clients)]
    await asyncio.gather(*(c.connect() for c in clients))
    start = time.perf_counter()
    window_start = start + warmup_s
    window_end = window_start + cell.window_s
    sent = 0
    snapshots: dict[str, tuple[float, float]] = {}
    rng = random.Random(cell.clients * 10 + cell.depth)

    async def worker(client: VisionClient) -> None:
        nonlocal sent
        while time.perf_counter() < window_end and sent < max_requests:
            sent += 1
            t0 = time.perf_counter()
            backoff = BUSY_BACKOFF_S
            while True:
                try:
                    await client.inspect(cell.inspection, image)
                    break
                except Busy:
                    cell.busy += 1
                    if time.perf_counter() >= window_end:
                        return  # the window is over: no more retries
                    await asyncio.sleep(backoff * rng.uniform(0.5, 1.0))
                    backoff = min(2.0 * backoff, BUSY_BACKOFF_MAX_S)
                except Exception:  # noqa: BLE001 - counted, reported
                    cell.errors += 1
                    break
            t1 = time.perf_counter()
            if window_start <= t1 <= window_end:
                cell.completed += 1
                if t0 >= window_start:
                    cell.latencies.append((t1 - t0) * 1000.0)

    async def clock() -> None:
        await asyncio.sleep(max(0.0, window_start - time.perf_counter()))
        snapshots["start"] = (server.cpu_seconds(), time.process_time())
        await asyncio.sleep(max(0.0, window_end - time.perf_counter()))
        snapshots["end"] = (server.cpu_seconds(), time.process_time())

    try:
        await asyncio.gather(clock(), *(worker(c) for c in clients for _ in range(cell.depth)))
    finally:
        await asyncio.gather(*(c.close() for c in clients), return_exceptions=True)
    if "start" in snapshots and "end" in snapshots:
        cell.server_cpu_s = snapshots["end"][0] - snapshots["start"][0]
        cell.client_cpu_s = snapshots["end"][1] - snapshots["start"][1]


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    server = env.server("cellvision")
    image = np.ascontiguousarray(env.samples.tool)
    inspections = [("brightness", cfg.f(2.0, 0.15), cfg.f(0.5, 0.05))]
    if "cap_locate" in server.info["inspections"]:
        inspections.append(("cap_locate", cfg.f(5.0, 0.3), cfg.f(1.0, 0.1)))
    else:
        section.skipped.append(f"cap_locate (CPU-bound): not served ({server.info['problem']})")
    if server.info.get("problem"):
        section.notes.append(f"Catalog: {server.info['problem']}.")
    clients = CLIENTS if not cfg.quick else (1, 2)
    depths = (1, PIPELINE) if not cfg.quick else (1, 2)
    cells: list[Cell] = []
    for name, window_s, warmup_s in inspections:
        for depth in depths:
            for n in clients:
                cell = Cell(name, n, depth, window_s)
                asyncio.run(_run_cell(server, cell, image, warmup_s, max_requests=100_000))
                cells.append(cell)
    if not cells:
        raise Skip("nothing to measure")

    workers = server.info.get("workers")
    section.intro = (
        f"The server runs with its default settings: {workers} worker threads, "
        f"queue_depth {server.info.get('queue_depth')} (beyond workers + queue_depth a request "
        f"is answered BUSY), max_in_flight {server.info.get('max_in_flight')} per connection. "
        f"All clients are asyncio `VisionClient`s in one process on the same machine. "
        f"Windows: {', '.join(f'{n} {w:g} s after {u:g} s warm-up' for n, w, u in inspections)}."
        " OpenCV's own thread pool is left at its default "
        f"({_cv_threads()} threads), as the server leaves it."
    )
    table = Table(
        [
            "inspection",
            "clients",
            "mode",
            "requests/s",
            "÷ 1 client",
            "p50 ms",
            "p99 ms",
            "BUSY per answer",
            "server CPU",
            "client CPU",
        ]
    )
    for name, _, _ in inspections:
        reference = next(
            c for c in cells if c.inspection == name and c.clients == 1 and c.depth == 1
        )
        for cell in (c for c in cells if c.inspection == name):
            s = Stats.of(cell.latencies)
            table.add(
                name,
                cell.clients,
                cell.mode,
                fmt(cell.rps, 1),
                ratio(cell.rps, reference.rps),
                fmt(s.p50, 2),
                fmt(s.p99, 2),
                fmt(cell.busy / cell.completed if cell.completed else float("nan"), 2),
                f"{100 * cell.server_cpu_s / cell.window_s:.0f} %",
                f"{100 * cell.client_cpu_s / cell.window_s:.0f} %",
            )
            key = f"{name}_c{cell.clients}_d{cell.depth}"
            section.value(f"{key}_rps", cell.rps)
            section.value(f"{key}_p99_ms", s.p99)
            if cell.errors:
                section.notes.append(f"{key}: {cell.errors} requests failed (not BUSY).")
        best = max((c for c in cells if c.inspection == name), key=lambda c: c.rps)
        scaling = best.rps / reference.rps if reference.rps else float("nan")
        section.value(f"{name}_single_rps", reference.rps)
        section.value(f"{name}_best_rps", best.rps)
        section.value(f"{name}_scaling", scaling)
        if name == "cap_locate":
            section.goals.append(
                Goal(
                    f"CPU-bound inspection (cap_locate) reaches >= {SCALING_GOAL}x the "
                    "single-client throughput",
                    f"{fmt(best.rps, 2)} req/s at {best.clients} client(s) {best.mode} vs "
                    f"{fmt(reference.rps, 2)} req/s for 1 client = {fmt(scaling, 2)}×",
                    scaling >= SCALING_GOAL,
                )
            )
    section.tables.append(table)
    for name, _, _ in inspections:
        peak = max(
            (100 * c.server_cpu_s / c.window_s for c in cells if c.inspection == name),
            default=float("nan"),
        )
        section.value(f"{name}_peak_server_cpu_pct", peak)
        section.notes.append(
            f"{name}: the server process used at most {peak:.0f} % CPU in any cell "
            f"(the machine has {_cores()} cores = {100 * _cores()} %)."
        )
    section.notes.append(
        "Latency counts the requests that started and got their answer inside the window; "
        "n/a means none did (every one took longer than the window, BUSY retries included)."
    )
    section.notes.append(
        "CPU is the process's user + system time over the window divided by the window "
        "(100 % = one core). With 2 cores shared by server and clients, what the clients use "
        "is not available to the server."
    )

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        names = [n for n, _, _ in inspections]
        fig, axes = plt.subplots(2, len(names), figsize=(5.5 * len(names), 7), squeeze=False)
        for col, name in enumerate(names):
            for depth in depths:
                row_cells = [c for c in cells if c.inspection == name and c.depth == depth]
                xs = [c.clients for c in row_cells]
                label = row_cells[0].mode if row_cells else ""
                axes[0][col].plot(xs, [c.rps for c in row_cells], "o-", label=label)
                p99 = [Stats.of(c.latencies).p99 for c in row_cells]
                axes[1][col].plot(xs, p99, "o-", label=label)
            for row, ylabel in enumerate(("requests / s", "p99 latency [ms]")):
                ax = axes[row][col]
                ax.set_xscale("log", base=2)
                ax.set_xticks(list(clients), [str(c) for c in clients])
                ax.set_xlabel("clients")
                ax.set_ylabel(ylabel)
                ax.set_title(name)
                ax.grid(True, alpha=0.3)
                ax.legend(fontsize=8)
            log_scale_if_positive(axes[1][col])
        return [save(fig, directory / "throughput.png")]

    section.plot = plot
    return section


def _cv_threads() -> int:
    import cv2

    return int(cv2.getNumThreads())


def _cores() -> int:
    import os

    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1
