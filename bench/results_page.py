"""8. The console's Results page over a result log of 100,000 results, and what stored overlays
cost the log.

A log is filled with 100,000 rows (four inspections, 5 % failures, eight peers, spread over the
last 24 hours: the rows a busy cell writes in a day) in one transaction, then served by the real
HTTP front-end (:class:`vision_server.frontends.http.HttpFrontend` over an
:class:`~vision_server.service.InspectionService`, in its own event loop in a thread, on
127.0.0.1, port 0). A keep-alive HTTP client times what the page asks when it opens and
filters: the first page (50 rows), a filtered page (inspection, verdict, since and peer), an
older page (``before_id``), and the per-inspection statistics over 24 hours (every row). The
reference is the bare SQLite query of the same first page, and of the statistics' columns, on
the same database in the same run.

Stored overlays: :meth:`ResultLog.record` of the QC camera's 1024x768 frame under
``store_images: all``, with and without the overlay, against encoding the frame as PNG once.
"""

from __future__ import annotations

import asyncio
import http.client
import json
import sqlite3
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from .common import RunConfig, Section, Stats, Table, fmt, ratio, time_calls
from .env import Env
from .plots import log_scale_if_positive, pyplot, save

NAME = "results_page"
TITLE = "8. Results page with 100,000 stored results"
GOAL_MS = 200.0
INSPECTIONS = ("magnet_check", "cap_locate", "station_qr", "station_pose")
DAY_S = 86400.0


def fill(path: Path, rows: int, *, now: float, seed: int = 7) -> None:
    """``rows`` results over the last 24 hours into a new log at ``path``, in one transaction."""
    from vision_server.results import ResultLog

    rng = np.random.default_rng(seed)
    times = np.sort(now - rng.uniform(0.0, DAY_S, rows))
    passed = rng.random(rows) >= 0.05
    durations = rng.gamma(2.0, 2.0, rows)
    with ResultLog(path, store_images="none") as log:
        conn = log._conn  # the bench's own bulk load: one transaction, not 100k commits
        conn.execute("BEGIN IMMEDIATE")
        conn.executemany(
            "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, "
            "config_hash, request_id, peer, error) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, NULL)",
            (
                (
                    float(times[i]),
                    INSPECTIONS[i % len(INSPECTIONS)],
                    "qc",
                    int(passed[i]),
                    json.dumps({"measure": "dark_fraction", "value": round(float(i % 97) / 97, 4)}),
                    float(durations[i]),
                    "5f1c9e0a7b3d",
                    i,
                    f"10.0.0.{7 + i % 8}:{41000 + i % 3}",
                )
                for i in range(rows)
            ),
        )
        conn.execute("COMMIT")


class Served:
    """The real HTTP front-end over a log, in its own event loop on a thread."""

    def __init__(self, env: Env, db: Path) -> None:
        from vision_server.config import ConsoleSettings
        from vision_server.frontends import HttpFrontend
        from vision_server.results import ResultLog
        from vision_server.service import InspectionService

        self.log = ResultLog(db, store_images="none")
        self.service = InspectionService(env.catalog.catalog, results=self.log)
        self.front = HttpFrontend(self.service, ConsoleSettings(enabled=True, port=0))
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        asyncio.run_coroutine_threadsafe(self.front.start(), self.loop).result(30)
        host, port = self.front.address
        self.conn = http.client.HTTPConnection(host, port, timeout=60)

    def get(self, path: str) -> Any:
        self.conn.request("GET", path)
        response = self.conn.getresponse()
        body = response.read()
        if response.status != 200:
            raise RuntimeError(f"GET {path}: {response.status} {body[:200]!r}")
        return json.loads(body)

    def close(self) -> None:
        self.conn.close()
        asyncio.run_coroutine_threadsafe(self.front.stop(), self.loop).result(30)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()
        self.service.close()
        self.log.close()


def run(cfg: RunConfig, env: Env) -> Section:
    section = Section(NAME, TITLE)
    rows = cfg.n(100_000, 2_000)
    repeat = cfg.n(30, 3)
    db = cfg.workdir / "results-page.sqlite3"
    now = time.time()
    t0 = time.perf_counter()
    fill(db, rows, now=now)
    fill_s = time.perf_counter() - t0

    served = Served(env, db)
    try:
        first = served.get("/api/results?limit=50")
        older_id = first["next_before_id"]
        filtered_path = (
            f"/api/results?limit=50&inspection=magnet_check&verdict=fail"
            f"&since={now - DAY_S / 2:.0f}&peer=10.0.0.7"
        )
        filtered = served.get(filtered_path)
        cases = [
            ("first page (50 rows)", "/api/results?limit=50", len(first["results"])),
            ("filtered page", filtered_path, len(filtered["results"])),
            ("older page (before_id)", f"/api/results?limit=50&before_id={older_id}", 50),
            ("stats, 4 inspections, 24 h", f"/api/stats?window_s={DAY_S:.0f}", rows),
            ("stats, 1 inspection, 24 h", "/api/stats?inspection=magnet_check&window_s=86400", 1),
        ]

        def getter(path: str) -> Callable[[], object]:
            return lambda: served.get(path)

        timed = {
            what: Stats.of(time_calls(getter(path), repeat=repeat, warmup=1))
            for what, path, _ in cases
        }
        stats = served.get(f"/api/stats?window_s={DAY_S:.0f}")
        counted = {s["name"]: s["count"] for s in stats["inspections"]}
        calls = {
            path: Stats.of(time_calls(getter(path), repeat=repeat, warmup=1))
            for path in sorted({p for _, paths in PAGES for p in paths})
        }
    finally:
        served.close()

    bare = sqlite3.connect(db)
    bare_page = Stats.of(
        time_calls(
            lambda: bare.execute(
                "SELECT * FROM results ORDER BY time DESC, id DESC LIMIT 51"
            ).fetchall(),
            repeat=repeat,
            warmup=1,
        )
    )
    bare_stats = Stats.of(
        time_calls(
            lambda: bare.execute(
                "SELECT time, passed, duration_ms FROM results WHERE time >= ?", (now - DAY_S,)
            ).fetchall(),
            repeat=repeat,
            warmup=1,
        )
    )
    bare.close()

    table = Table(["request", "rows", "p50 ms", "p99 ms", "p50 ÷ bare SQLite"])
    for what, _, count in cases:
        s = timed[what]
        reference = bare_stats if what.startswith("stats") else bare_page
        if what.startswith("stats, 4"):
            count = sum(counted.values())
        elif what.startswith("stats, 1"):
            count = counted["magnet_check"]
        table.add(what, count, fmt(s.p50, 2), fmt(s.p99, 2), ratio(s.p50, reference.p50))
        section.value(f"{what.split(' ')[0]}_{what.split(' ')[1]}_p50_ms", s.p50)
    table.add("bare SQLite: first page", 51, fmt(bare_page.p50, 2), fmt(bare_page.p99, 2), "1×")
    table.add(
        "bare SQLite: stats columns", rows, fmt(bare_stats.p50, 2), fmt(bare_stats.p99, 2), "1×"
    )
    section.tables.append(table)
    pages = Table(
        ["page", "requests when it opens", "sum of their p50 ms", "slowest p99 ms"],
        caption=(
            f"Every page of the console over the same {rows:,} results: the API requests its "
            "script makes when it opens (and the status pill's /api/server), one after another "
            "(the browser runs some at once: the sum is the worse case)."
        ),
    )
    worst_page = 0.0
    for page, paths in PAGES:
        opened_page = sum(calls[p].p50 for p in paths)
        worst_page = max(worst_page, opened_page)
        pages.add(
            page,
            ", ".join(paths),
            fmt(opened_page, 3),
            fmt(max(calls[p].p99 for p in paths), 3),
        )
        section.value(f"page_{page.lower()}_open_p50_ms", opened_page)
    section.tables.append(pages)
    section.goals.append(_pages_goal(rows, worst_page))
    opened = timed["first page (50 rows)"].p50 + timed["stats, 4 inspections, 24 h"].p50
    section.value("page_open_p50_ms", opened)
    section.value("rows", rows)
    slowest = max(s.p99 for s in timed.values())
    section.goals.append(_goal(rows, opened, slowest))
    section.intro = (
        f"{rows:,} rows (filled in {fill_s:.1f} s), served by the real HTTP front-end on "
        "127.0.0.1; a keep-alive client, one request at a time. Opening the page = first page + "
        f"stats: {fmt(opened, 3)} ms at p50. Filtered page: inspection magnet_check, verdict fail, "
        "since 12 h ago, peer prefix 10.0.0.7."
    )
    section.tables.append(_overlay_cost(cfg, env, section))

    def plot(directory: Path) -> list[Path]:
        plt = pyplot()
        if plt is None:
            return []
        fig, ax = plt.subplots(figsize=(8, 3.6))
        names = [what for what, _, _ in cases]
        xs = np.arange(len(names))
        ax.bar(xs - 0.2, [timed[n].p50 for n in names], 0.4, label="p50")
        ax.bar(xs + 0.2, [timed[n].p99 for n in names], 0.4, label="p99")
        ax.axhline(GOAL_MS, color="red", linestyle="--", linewidth=1, label="goal")
        ax.set_xticks(xs, names, rotation=12, fontsize=8)
        ax.set_ylabel(f"ms, {rows:,} rows")
        log_scale_if_positive(ax)
        ax.grid(True, axis="y", alpha=0.3)
        ax.legend(fontsize=8)
        return [save(fig, directory / "results_page.png")]

    section.plot = plot
    return section


PAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Cameras", ("/api/server", "/api/cameras", "/api/online")),
    (
        "Inspections",
        (
            "/api/server",
            "/api/inspections",
            "/api/schema",
            "/api/inspections/magnet_check/reads?last=20",
        ),
    ),
    ("Results", ("/api/server", "/api/results?limit=50", f"/api/stats?window_s={DAY_S:.0f}")),
    ("Results by operator", ("/api/server", "/api/results?limit=50&operator=anna")),
    ("Server", ("/api/server",)),
    ("Operator", ("/api/server", "/api/operator/calls")),
)
"""What each page of the console asks when it opens (static/js/*.js), besides its files."""


def _pages_goal(rows: int, worst_ms: float) -> Any:
    from .common import Goal

    return Goal(
        f"every console page opens in < {GOAL_MS:.0f} ms p50 with {rows:,} stored results",
        f"slowest page: {fmt(worst_ms, 3)} ms (the sum of its requests' p50)",
        worst_ms < GOAL_MS,
    )


def _goal(rows: int, opened_ms: float, slowest_p99_ms: float) -> Any:
    from .common import Goal

    return Goal(
        f"Results page with {rows:,} stored results answers in < {GOAL_MS:.0f} ms",
        f"page open (first page + stats) {fmt(opened_ms, 3)} ms at p50; slowest request p99 "
        f"{fmt(slowest_p99_ms, 3)} ms",
        opened_ms < GOAL_MS and slowest_p99_ms < GOAL_MS,
    )


def _overlay_cost(cfg: RunConfig, env: Env, section: Section) -> Table:
    """What a stored overlay adds to :meth:`ResultLog.record` (in the worker, per stored row)."""
    import cv2

    from vision_server.inspections.base import draw_verdict, overlay_base
    from vision_server.results import ResultEntry, ResultLog

    frame = env.samples.qc
    overlay = draw_verdict(overlay_base(frame, (486, 236, 50, 60)), False, "dark_fraction 0.0")
    repeat = cfg.n(20, 2)
    table = Table(
        ["record() with store_images: all (1024x768 QC frame)", "p50 ms", "p50 ÷ one PNG encode"],
        caption="Stored overlays: the cost in the worker, per row whose images are stored.",
    )
    png = Stats.of(time_calls(lambda: cv2.imencode(".png", frame), repeat=repeat, warmup=1))
    draw = Stats.of(
        time_calls(lambda: overlay_base(frame, (486, 236, 50, 60)), repeat=repeat, warmup=1)
    )
    with ResultLog(cfg.workdir / "overlay-cost.sqlite3", store_images="all") as log:

        def record(with_overlay: bool) -> None:
            log.record(
                ResultEntry(
                    time=time.time(),
                    inspection="magnet_check",
                    camera="qc",
                    passed=False,
                    data={},
                    duration_ms=0.0,
                    config_hash="",
                    image=frame,
                    overlay=overlay if with_overlay else None,
                )
            )

        plain = Stats.of(time_calls(lambda: record(False), repeat=repeat, warmup=1))
        both = Stats.of(time_calls(lambda: record(True), repeat=repeat, warmup=1))
    table.add("PNG encode of the frame (reference)", fmt(png.p50, 2), "1×")
    table.add("drawing the overlay (ROI + verdict)", fmt(draw.p50, 3), ratio(draw.p50, png.p50))
    table.add("input only", fmt(plain.p50, 2), ratio(plain.p50, png.p50))
    table.add("input + overlay", fmt(both.p50, 2), ratio(both.p50, png.p50))
    section.value("record_input_p50_ms", plain.p50)
    section.value("record_input_overlay_p50_ms", both.p50)
    section.value("png_encode_p50_ms", png.p50)
    return table
