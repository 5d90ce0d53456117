"""2. Throughput against concurrency: 1, 4, 16 and 64 clients (one connection each), each
either waiting for every answer before the next request ("one at a time") or keeping 4
requests in flight on its connection ("pipelined x4"), for a light inspection (``brightness``)
and a CPU-bound one (``cap_locate``, the circle locate of the vision pick), both on the tool
camera's 1024x768 image sent in the request.

Each cell runs for a fixed time after a warm-up; requests per second count the answers that
arrived in the measuring window; latency is from the first send to the answer, BUSY retries
included (bench/busy.py: by the client itself when it can, else by hand with back-off; retries
stop when the window closes). CPU use of the server process and of this (client) process over
the window is reported: they share the machine's cores.

The reference is the machine's limit, measured in the same run: the inspection object called
by as many workers as cores, for a window, no protocol (bench/inprocess.py): threads in this
process (OpenCV's default thread count and ``cv2.setNumThreads(1)``) and processes (as the
server's worker processes); the best of the three. Goals (issue 16):

- at saturation (4, 16 and 64 clients, one at a time and pipelined x4) cap_locate reaches
  >= 0.9x that limit;
- no collapse: from the saturation point (in order of requests in flight, the first cell within
  0.9x of the peak) to 64 clients x 4, throughput stays >= 0.9x its peak, and p99 grows no
  faster than the queue it waits in: by Little's law a request waits on average (requests in
  flight ÷ throughput); the ratio p99 ÷ that, per cell, may not exceed its value at the
  saturation point by more than 10 %.

The former goal (>= 1.7x the single client's throughput) is kept as information.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .busy import Retrier, make_client, retry_mode
from .common import Goal, RunConfig, Section, Skip, Stats, Table, fmt, ratio
from .env import Env
from .inprocess import Rate, cores, process_rate, rate, runner
from .plots import log_scale_if_positive, pyplot, save
from .servers import ServerProcess, default_loop, other_loop

NAME = "throughput"
TITLE = "2. Throughput against concurrency"
CLIENTS = (1, 4, 16, 64)
PIPELINE = 4
SATURATED_CLIENTS = (4, 16, 64)
LIMIT_GOAL = 0.9
"""Saturated server throughput ÷ the machine's limit."""
PEAK_GOAL = 0.9
"""Throughput past the saturation point ÷ the peak; also what "within the peak" means."""
QUEUE_GROWTH_TOLERANCE = 1.1
"""How much the p99 ÷ (in flight ÷ throughput) ratio may grow past the saturation point."""
FORMER_SCALING_GOAL = 1.7
DRAIN_S = 15.0
"""How long after its window a cell still follows the requests sent inside it."""
LIMIT_GOAL_INSPECTIONS = ("cap_locate",)
"""brightness is bound by moving its image, not by compute: its limit ratio is information."""


@dataclass
class Cell:
    inspection: str
    clients: int
    depth: int
    window_s: float
    latencies: list[float] = field(default_factory=list)
    completed: int = 0
    busy: int = 0
    """BUSY answers inside the window."""
    errors: int = 0
    unanswered: int = 0
    """Requests sent inside the window that were still answered BUSY when the drain ended."""
    server_cpu_s: float = float("nan")
    client_cpu_s: float = float("nan")

    @property
    def rps(self) -> float:
        return self.completed / self.window_s

    @property
    def in_flight(self) -> int:
        return self.clients * self.depth

    @property
    def mode(self) -> str:
        return "one at a time" if self.depth == 1 else f"pipelined x{self.depth}"

    @property
    def label(self) -> str:
        return f"{self.clients} client(s) {self.mode}"

    @property
    def queue_ms(self) -> float:
        """Little's law: the mean time a request spends in the system, (in flight ÷ rps)."""
        return 1000.0 * self.in_flight / self.rps if self.completed else float("nan")

    @property
    def p99_over_queue(self) -> float:
        return Stats.of(self.latencies).p99 / self.queue_ms


async def _run_cell(
    server: ServerProcess,
    cell: Cell,
    image: Any,
    warmup_s: float,
    drain_s: float,
    max_requests: int,
) -> None:
    """Runs ``cell``. A request sent inside the window is followed to its answer, retrying
    BUSY up to ``drain_s`` after the window closes, so that the slowest requests count in
    the latency rather than drop out of it; no new request is sent after the window."""
    clients = [
        make_client(server.port, busy_timeout_s=warmup_s + cell.window_s + drain_s)
        for _ in range(cell.clients)
    ]
    await asyncio.gather(*(c.connect() for c in clients))
    start = time.perf_counter()
    window_start = start + warmup_s
    window_end = window_start + cell.window_s
    drain_end = window_end + drain_s
    sent = 0
    snapshots: dict[str, tuple[float, float, int]] = {}
    retrier = Retrier(cell.clients * 10 + cell.depth)

    async def worker(client: Any) -> None:
        nonlocal sent
        while time.perf_counter() < window_end and sent < max_requests:
            sent += 1
            t0 = time.perf_counter()
            followed = t0 >= window_start
            try:
                answer = await retrier.inspect(
                    client, cell.inspection, image, until=drain_end if followed else window_end
                )
            except Exception:  # noqa: BLE001 - counted, reported
                cell.errors += 1
                continue
            if answer is None:
                cell.unanswered += int(followed)
                return  # still BUSY when the retries had to stop
            t1 = time.perf_counter()
            if window_start <= t1 <= window_end:
                cell.completed += 1
            if followed:
                cell.latencies.append((t1 - t0) * 1000.0)

    def snapshot() -> tuple[float, float, int]:
        return (server.cpu_seconds(), time.process_time(), retrier.busy(clients))

    async def clock() -> None:
        await asyncio.sleep(max(0.0, window_start - time.perf_counter()))
        snapshots["start"] = snapshot()
        await asyncio.sleep(max(0.0, window_end - time.perf_counter()))
        snapshots["end"] = snapshot()

    try:
        await asyncio.gather(clock(), *(worker(c) for c in clients for _ in range(cell.depth)))
    finally:
        await asyncio.gather(*(c.close() for c in clients), return_exceptions=True)
    if "start" in snapshots and "end" in snapshots:
        cell.server_cpu_s = snapshots["end"][0] - snapshots["start"][0]
        cell.client_cpu_s = snapshots["end"][1] - snapshots["start"][1]
        cell.busy = snapshots["end"][2] - snapshots["start"][2]


def by_load(cells: Sequence[Cell]) -> list[Cell]:
    """``cells`` in order of requests in flight (then pipelining depth): the order in which
    load grows, from 1 client one at a time to 64 clients x 4."""
    return sorted(cells, key=lambda c: (c.in_flight, c.depth))


def saturation_point(cells: Sequence[Cell]) -> Cell:
    """The first cell (by load) within PEAK_GOAL of the peak throughput."""
    ordered = by_load(cells)
    peak = max(c.rps for c in ordered)
    return next(c for c in ordered if c.rps >= PEAK_GOAL * peak)


def machine_limit(env: Env, name: str, image: Any, window_s: float) -> list[Rate]:
    """The throughput of ``name`` without a protocol, with as many workers as cores: threads
    in this process with OpenCV's default thread count (as the server runs) and with
    ``cv2.setNumThreads(1)``; and processes with one OpenCV thread each (as the server's
    worker processes), the better of which is the limit."""
    call = runner(env, name, image)
    rates = [rate(call, threads=cores(), window_s=window_s, cv_threads=cv) for cv in (None, 1)]
    rates.append(process_rate(env, name, image, processes=cores(), window_s=window_s))
    return rates


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
    limits: dict[str, list[Rate]] = {}
    for name, _, _ in inspections:
        if name in env.catalog.catalog.inspections:
            limits[name] = machine_limit(env, name, image, cfg.f(3.0, 0.1))
    clients = CLIENTS if not cfg.quick else (1, 2)
    drain_s = cfg.f(DRAIN_S, 1.0)
    depths = (1, PIPELINE) if not cfg.quick else (1, 2)
    cells: list[Cell] = []
    for name, window_s, warmup_s in inspections:
        for depth in depths:
            for n in clients:
                cell = Cell(name, n, depth, window_s)
                asyncio.run(_run_cell(server, cell, image, warmup_s, drain_s, max_requests=100_000))
                cells.append(cell)
    if not cells:
        raise Skip("nothing to measure")

    workers = server.info.get("workers")
    section.intro = (
        f"The server runs with its default settings: {workers} worker threads, "
        f"queue_depth {server.info.get('queue_depth')}, max_in_flight "
        f"{server.info.get('max_in_flight')} per connection. All clients are asyncio "
        f"`VisionClient`s in one process on the same machine; BUSY is retried {retry_mode()}. "
        f"Windows: {', '.join(f'{n} {w:g} s after {u:g} s warm-up' for n, w, u in inspections)}."
        " A cheap inspection (brightness) runs on the event loop itself (`inline_ms`); the"
        " server also has a fast lane (one thread of its own for inspections measured at"
        " 5 ms or less), sets OpenCV's own pool to cores ÷ workers threads, and runs "
        f"{', '.join(server.info.get('process_inspections') or ['nothing'])} in worker "
        "processes (`process_inspections`, chosen by section 2b's rule). The machine's"
        " limit: the inspection called without a protocol by "
        f"{cores()} threads in one process, and by {cores()} processes (one worker per core"
        f" either way) for {cfg.f(3.0, 0.1):g} s; the best of them."
    )
    limit_table = Table(
        ["inspection", "workers", "OpenCV threads per worker", "requests/s", "CPU"],
        caption="The machine's limit (no protocol, same image, same run):",
    )
    limit_rps: dict[str, float] = {}
    for name, rates in limits.items():
        for r in rates:
            limit_table.add(
                name, f"{r.threads} {r.model}", r.cv_threads, fmt(r.rps, 1), f"{r.cpu_pct:.0f} %"
            )
        limit_rps[name] = max(r.rps for r in rates)
        section.value(f"{name}_limit_rps", limit_rps[name])
    section.tables.append(limit_table)

    table = Table(
        [
            "inspection",
            "clients",
            "mode",
            "requests/s",
            "÷ 1 client",
            "÷ limit",
            "p50 ms",
            "p99 ms",
            "in flight ÷ rps, ms",
            "p99 ÷ that",
            "BUSY per answer",
            "server CPU",
            "client CPU",
        ]
    )
    summary = Table(
        [
            "inspection",
            "limit req/s",
            "peak",
            "saturation point",
            "worst saturated ÷ limit",
            f"best ÷ 1 client (former goal >= {FORMER_SCALING_GOAL}x)",
        ],
        caption="Summary per inspection (saturated: 4, 16 and 64 clients, both modes):",
    )
    for name, _, _ in inspections:
        mine = [c for c in cells if c.inspection == name]
        reference = next(c for c in mine if c.clients == 1 and c.depth == 1)
        limit = limit_rps.get(name, float("nan"))
        for cell in mine:
            s = Stats.of(cell.latencies)
            table.add(
                name,
                cell.clients,
                cell.mode,
                fmt(cell.rps, 1),
                ratio(cell.rps, reference.rps),
                ratio(cell.rps, limit),
                fmt(s.p50, 2),
                fmt(s.p99, 2),
                fmt(cell.queue_ms, 1),
                fmt(cell.p99_over_queue, 2),
                fmt(cell.busy / cell.completed if cell.completed else float("nan"), 2),
                f"{100 * cell.server_cpu_s / cell.window_s:.0f} %",
                f"{100 * cell.client_cpu_s / cell.window_s:.0f} %",
            )
            key = f"{name}_c{cell.clients}_d{cell.depth}"
            section.value(f"{key}_rps", cell.rps)
            section.value(f"{key}_p99_ms", s.p99)
            section.value(f"{key}_busy_per_answer", cell.busy / max(cell.completed, 1))
            section.value(f"{key}_p99_over_queue", cell.p99_over_queue)
            if cell.errors:
                section.notes.append(f"{key}: {cell.errors} requests failed (not BUSY).")
            if cell.unanswered:
                section.notes.append(
                    f"{key}: {cell.unanswered} requests sent in the window were still answered "
                    f"BUSY {drain_s:g} s after it closed; their latency is missing (p99 is "
                    "then a lower bound)."
                )
        best = max(mine, key=lambda c: c.rps)
        scaling = best.rps / reference.rps if reference.rps else float("nan")
        section.value(f"{name}_single_rps", reference.rps)
        section.value(f"{name}_best_rps", best.rps)
        section.value(f"{name}_scaling", scaling)
        saturated = (
            [c for c in mine if c.clients in SATURATED_CLIENTS]
            or [c for c in mine if c.clients > 1]  # --quick has no 4, 16, 64
            or mine
        )
        worst = min(saturated, key=lambda c: c.rps)
        knee = saturation_point(mine)
        summary.add(
            name,
            fmt(limit, 1),
            f"{fmt(best.rps, 1)} req/s ({best.label})",
            knee.label,
            f"{ratio(worst.rps, limit)} ({worst.label})",
            ratio(best.rps, reference.rps),
        )
        section.value(f"{name}_worst_saturated_over_limit", worst.rps / limit)
        if name in LIMIT_GOAL_INSPECTIONS:
            section.goals.append(
                Goal(
                    f"{name} at saturation (4, 16, 64 clients, both modes) >= {LIMIT_GOAL}x "
                    f"the machine's limit (the best of {cores()} threads and {cores()} "
                    "processes, no protocol)",
                    f"worst {fmt(worst.rps, 1)} req/s ({worst.label}) ÷ limit "
                    f"{fmt(limit, 1)} req/s = {ratio(worst.rps, limit)}; best "
                    f"{ratio(best.rps, limit)}",
                    worst.rps >= LIMIT_GOAL * limit,
                )
            )
        section.goals += collapse_goals(name, mine)
    section.tables += [summary, table]
    for name, _, _ in inspections:
        peak = max(
            (100 * c.server_cpu_s / c.window_s for c in cells if c.inspection == name),
            default=float("nan"),
        )
        section.value(f"{name}_peak_server_cpu_pct", peak)
        section.notes.append(
            f"{name}: the server process used at most {peak:.0f} % CPU in any cell "
            f"(the machine has {cores()} cores = {100 * cores()} %)."
        )
    section.notes += [
        "brightness computes in about 0.1 ms: its throughput is bound by moving a 786 KB image "
        "per request, so its ÷ limit column is information, not a goal.",
        "Little's law: with N requests in flight at X requests/s, a request spends N ÷ X in "
        "the system on average. p99 ÷ (N ÷ X) near 1 means every request waits its turn; far "
        "above 1, some requests wait much longer than others (retries after BUSY, unfair "
        "service).",
        f"Latency counts every request sent inside the window, followed to its answer (BUSY "
        f"retries included) for up to {drain_s:g} s after the window; no new request is sent "
        "after the window, so the last ones meet a server that is emptying (p99 slightly "
        "low, not censored). Requests per second and BUSY per answer count the window only.",
        "CPU is the process's user + system time over the window divided by the window "
        "(100 % = one core). With the cores shared by server and clients, what the clients use "
        "is not available to the server.",
    ]
    loops_table(section, cfg, env, server, image, inspections, drain_s)
    section.plot = _plotter(cells, [n for n, _, _ in inspections], clients, depths, limit_rps)
    return section


LOOP_CELLS = ((4, 1), (64, PIPELINE))
"""The cells measured on both event loops: the saturation point and the heaviest load."""


def loops_table(
    section: Section,
    cfg: RunConfig,
    env: Env,
    server: ServerProcess,
    image: Any,
    inspections: Sequence[tuple[str, float, float]],
    drain_s: float,
) -> None:
    """The same cells on the default event loop and the other one, alternated (one round,
    two for the cheap inspection), so that ``server: event_loop`` is chosen by measurement."""
    other = other_loop()
    try:
        alternative = env.server(f"cellvision_{other}")
    except Skip as exc:
        section.skipped.append(f"the {other} event loop: {exc}")
        return
    table = Table(
        [
            "inspection",
            "clients",
            "mode",
            *(f"{n} req/s" for n in (default_loop(), other)),
            f"{other} ÷ {default_loop()}",
            *(f"{n} p99 ms" for n in (default_loop(), other)),
        ],
        caption=f"Both event loops in the same run (`server: event_loop`, default "
        f"{default_loop()}), alternated cell by cell:",
    )
    cells = LOOP_CELLS if not cfg.quick else ((2, 1),)
    for name, window_s, warmup_s in inspections:
        for clients, depth in cells:
            measured: dict[str, list[Cell]] = {default_loop(): [], other: []}
            for _ in range(2 if name == "brightness" and not cfg.quick else 1):
                for loop, proc in ((default_loop(), server), (other, alternative)):
                    cell = Cell(name, clients, depth, window_s)
                    asyncio.run(
                        _run_cell(proc, cell, image, warmup_s, drain_s, max_requests=100_000)
                    )
                    measured[loop].append(cell)
            rps = {
                k: sum(c.completed for c in v) / sum(c.window_s for c in v)
                for k, v in measured.items()
            }
            p99 = {k: Stats.of(x for c in v for x in c.latencies).p99 for k, v in measured.items()}
            first = measured[default_loop()][0]
            table.add(
                name,
                clients,
                first.mode,
                fmt(rps[default_loop()], 1),
                fmt(rps[other], 1),
                ratio(rps[other], rps[default_loop()]),
                fmt(p99[default_loop()], 2),
                fmt(p99[other], 2),
            )
            section.value(
                f"{name}_c{clients}_d{depth}_{other}_over_default_rps",
                rps[other] / rps[default_loop()],
            )
    section.tables.append(table)


def collapse_goals(name: str, cells: Sequence[Cell]) -> list[Goal]:
    """No collapse past the saturation point: throughput >= PEAK_GOAL x the peak, and p99 ÷
    (in flight ÷ throughput) no more than QUEUE_GROWTH_TOLERANCE x its value at that point."""
    ordered = by_load(cells)
    peak = max(c.rps for c in ordered)
    knee = saturation_point(ordered)
    past = ordered[ordered.index(knee) :]
    low = min(past, key=lambda c: c.rps)
    base = knee.p99_over_queue
    worst = max(past, key=lambda c: c.p99_over_queue if c.completed else float("inf"))
    grows = worst.p99_over_queue / base if base == base and base > 0 else float("nan")
    return [
        Goal(
            f"{name}: no collapse, from the saturation point to 64 clients x 4 throughput "
            f">= {PEAK_GOAL}x its peak",
            f"from {knee.label}: lowest {fmt(low.rps, 1)} req/s ({low.label}) ÷ peak "
            f"{fmt(peak, 1)} = {ratio(low.rps, peak)}",
            low.rps >= PEAK_GOAL * peak,
        ),
        Goal(
            f"{name}: p99 grows no faster than the queue (p99 ÷ (in flight ÷ throughput) "
            f"<= {QUEUE_GROWTH_TOLERANCE}x its value at the saturation point)",
            f"{fmt(base, 2)} at {knee.label}; highest {fmt(worst.p99_over_queue, 2)} "
            f"({worst.label}) = {fmt(grows, 2)}×",
            grows <= QUEUE_GROWTH_TOLERANCE,
        ),
    ]


def _plotter(
    cells: list[Cell],
    names: list[str],
    clients: Sequence[int],
    depths: Sequence[int],
    limit_rps: dict[str, float],
) -> Any:
    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, axes = plt.subplots(2, len(names), figsize=(5.5 * len(names), 7), squeeze=False)
        for col, name in enumerate(names):
            for index, depth in enumerate(depths):
                row_cells = [c for c in cells if c.inspection == name and c.depth == depth]
                xs = [c.clients for c in row_cells]
                label = row_cells[0].mode if row_cells else ""
                color = f"C{index}"
                axes[0][col].plot(xs, [c.rps for c in row_cells], "o-", color=color, label=label)
                p99 = [Stats.of(c.latencies).p99 for c in row_cells]
                axes[1][col].plot(xs, p99, "o-", color=color, label=f"p99, {label}")
                queue = [c.queue_ms for c in row_cells]
                axes[1][col].plot(xs, queue, ":", color=color, label=f"in flight ÷ rps, {label}")
            if name in limit_rps and name in LIMIT_GOAL_INSPECTIONS:
                axes[0][col].axhline(
                    limit_rps[name], color="k", ls="--", lw=1, label="machine's limit"
                )
            for row, ylabel in enumerate(("requests / s", "latency [ms]")):
                ax = axes[row][col]
                ax.set_xscale("log", base=2)
                ax.set_xticks(list(clients), [str(c) for c in clients])
                ax.set_xlabel("clients")
                ax.set_ylabel(ylabel)
                ax.set_title(name)
                ax.grid(True, alpha=0.3)
                ax.legend(fontsize=7)
            log_scale_if_positive(axes[1][col])
        return [save(fig, directory / "throughput.png")]

    return plot
