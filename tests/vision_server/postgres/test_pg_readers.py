"""The readers of a PostgreSQL result log, unaware of which database they read: the console's
Results API (a real server with its console, results recorded over the robot protocol) and
``vision-server results --db postgresql://...`` / ``--config``."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
from console_server import Browserless
from postgres import Cluster

from robot_client.client import VisionClient
from vision_server.app import App
from vision_server.service import CellRuntime

CONFIG = """\
server: {{port: 0}}
console: {{enabled: true, port: 0}}
results: {{url: "{url}", spool: spool.sqlite3}}
cameras: {{tool: {{source: request}}}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 100}}
"""


def test_the_console_lists_and_shows_results_from_postgresql(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text(CONFIG.format(url=pg_url))
    runtime = CellRuntime(config)
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()

    def on_loop(coro: object) -> object:
        return asyncio.run_coroutine_threadsafe(coro, loop).result(60.0)  # type: ignore[arg-type]

    async def make() -> App:
        return App(
            runtime.catalog,
            runtime.config.server,
            results=runtime.results,
            console=runtime.config.console,
            config_path=config,
        )

    app = on_loop(make())
    assert isinstance(app, App)
    try:
        on_loop(app.start())

        async def inspect() -> list[bool | None]:
            async with VisionClient("127.0.0.1", app.port) as client:
                return [
                    (await client.inspect("bright", np.full((8, 8), level, np.uint8))).stored
                    for level in (50, 150, 200)
                ]

        assert asyncio.run(inspect()) == [True, True, True]
        assert app.http is not None
        browser = Browserless(app.http.url)
        page = browser.get("/api/results?limit=2").json()
        assert [r["passed"] for r in page["results"]] == [True, True]
        rest = browser.get(f"/api/results?before_id={page['next_before_id']}").json()
        assert [r["passed"] for r in rest["results"]] == [False]
        failed = browser.get("/api/results?verdict=fail").json()["results"]
        assert len(failed) == 1
        one = browser.get(f"/api/results/{failed[0]['id']}").json()
        assert one["data"]["value"] == 50.0
        stats = browser.get("/api/stats?inspection=bright").json()["inspections"][0]
        assert (stats["count"], stats["pass"], stats["fail"]) == (3, 2, 1)
        # A console try is stored as a try, with its options, and counted in no statistic
        # (docs/console.md, "Tries in the result log"), as in the SQLite log.
        ok, png = cv2.imencode(".png", np.full((8, 8), 90, np.uint8))
        assert ok
        tried = browser.try_("bright", {"source": "upload", "options": {"min": 80}}, png.tobytes())
        assert tried.json()["verdict"] == "pass", tried.body
        newest = browser.get("/api/results?limit=1").json()["results"][0]
        assert newest["try"] is True
        shown = browser.get(f"/api/results/{newest['id']}").json()
        assert shown["data"]["try"] == {"options": {"min": 80}}
        stats = browser.get("/api/stats?inspection=bright").json()["inspections"][0]
        assert (stats["count"], stats["pass"], stats["fail"]) == (3, 2, 1)
        assert browser.get(f"/api/results/{failed[0]['id']}/image.png").status == 404
        # The database down: the page says so, the server stays up and keeps recording.
        pg_cluster.stop_immediate()
        try:
            down = browser.get("/api/results")
            assert down.status == 503
            assert down.json()["error"]["code"] == "RESULT_LOG_UNAVAILABLE"
            assert asyncio.run(inspect()) == [True, True, True]
        finally:
            pg_cluster.start()
    finally:
        on_loop(app.stop())
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()
        runtime.close()


def test_vision_server_results_reads_a_postgresql_log(pg_url: str, tmp_path: Path) -> None:
    from vision_server.results import PgResultLog, ResultEntry

    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3") as log:
        for i in range(3):
            entry = ResultEntry(1.7e9 + i, "gap", "cam", i != 1, {"mm": i}, 2.0, "h", i)
            assert log.record(entry)
    (tmp_path / "cell.yaml").write_text(CONFIG.format(url=pg_url))
    env = {**os.environ, "COLUMNS": "200"}
    for where in (["--db", pg_url], ["--config", str(tmp_path / "cell.yaml")]):
        done = subprocess.run(
            [sys.executable, "-m", "vision_server", "results", "--json", *where],
            capture_output=True,
            text=True,
            env=env,
            timeout=60,
            check=True,
        )
        rows = [json.loads(line) for line in done.stdout.splitlines()]
        assert [(r["request_id"], r["verdict"]) for r in rows] == [
            (2, "pass"),
            (1, "fail"),
            (0, "pass"),
        ]
    failed = subprocess.run(
        [sys.executable, "-m", "vision_server", "results", "--db", pg_url + "_missing"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert failed.returncode == 2
    assert "_missing" in failed.stderr
