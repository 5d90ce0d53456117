"""Durability of the PostgreSQL result log through a real ``vision-server serve``: stop the
database at once (``pg_ctl stop -m immediate``, as a crash) in the middle of a burst of pipelined
inspections, start it again later in the burst, and count: every result acknowledged with
``stored: true`` is in the database once the spool has drained, exactly once. And the spool
outlives a SIGKILL of the server while the database is down, and the next server forwards it.

A RESULT is matched to its row by the connection's peer address (``peer``) and the request id.
"""

from __future__ import annotations

import asyncio
import re
import sqlite3
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
from loopback import run, wait_until
from postgres import Cluster

from protocol import Inspect, Result, payload_from_array
from robot_client.client import ReconnectPolicy, VisionClient

psycopg = pytest.importorskip(
    "psycopg", reason="psycopg is not installed: pip install -e '.[test]' (extra postgres)"
)

CONFIG = """\
server: {{port: 0, max_in_flight: 32, queue_depth: 64}}
results: {{url: "{url}", spool: spool.sqlite3}}
cameras: {{tool: {{source: request}}}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}}
"""
BURST = 1000
STOP_AFTER = 250  # acknowledged results when the database is stopped
START_AFTER = 600  # ... and started again


@contextmanager
def serve(folder: Path) -> Iterator[tuple[subprocess.Popen[str], int]]:
    """``vision-server serve`` in ``folder`` (its stderr, the server's log, in server.log)."""
    with open(folder / "server.log", "a") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "vision_server", "serve", "--config", "cell.yaml"],
            cwd=folder,
            stdout=subprocess.PIPE,
            stderr=log,
            text=True,
        )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line, f"the server did not start: {(folder / 'server.log').read_text()[-2000:]}"
        yield proc, int(re.findall(r":(\d+)", line)[-1])
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)


def spooled(folder: Path) -> int:
    path = folder / "spool.sqlite3"
    if not path.exists():
        return 0
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return int(db.execute("SELECT count(*) FROM spool").fetchone()[0])
    finally:
        db.close()


def image(level: int) -> tuple[object, ...]:
    return (payload_from_array(np.full((48, 64), level, np.uint8)),)


def test_every_acknowledged_result_is_in_the_database_after_a_crash_mid_burst(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    (tmp_path / "cell.yaml").write_text(CONFIG.format(url=pg_url))
    acknowledged: dict[int, float] = {}
    not_stored: list[int] = []
    try:
        with serve(tmp_path) as (proc, port):

            async def burst() -> str:
                client = VisionClient(
                    "127.0.0.1",
                    port,
                    request_timeout_s=120.0,
                    reconnect=ReconnectPolicy(attempts=0),
                )
                await client.connect()
                assert client.stream is not None
                host, local_port = client.stream.get_extra_info("sockname")[:2]

                async def one(i: int) -> None:
                    level = i % 256
                    answer = await client.request(lambda rid: Inspect(rid, "bright", image(level)))
                    assert isinstance(answer, Result)
                    if answer.stored is not True:
                        not_stored.append(answer.request_id)
                        return
                    acknowledged[answer.request_id] = answer.data["value"]
                    # Blocking on purpose: the server goes on answering while pg_ctl works.
                    if len(acknowledged) == STOP_AFTER:
                        pg_cluster.stop_immediate()
                    elif len(acknowledged) == START_AFTER:
                        pg_cluster.start()

                await asyncio.gather(*(one(i) for i in range(BURST)))
                await client.close()
                return f"{host}:{local_port}"

            peer = asyncio.run(asyncio.wait_for(burst(), 300.0))
            run(wait_until(lambda: spooled(tmp_path) == 0, "the spool drains", 120.0), 130.0)
            assert proc.poll() is None  # the outage never stopped the server
    finally:
        pg_cluster.start_if_stopped()

    log = (tmp_path / "server.log").read_text()
    assert "spooling" in log  # the database did fail mid-burst ...
    assert "is back after" in log  # ... and the forwarder saw it return
    assert not_stored == []
    assert len(acknowledged) == BURST
    with psycopg.connect(pg_url) as conn:
        rows = conn.execute(
            "SELECT request_id, data FROM results WHERE peer = %s AND inspection = 'bright'",
            (peer,),
        ).fetchall()
        uids = conn.execute("SELECT count(*), count(DISTINCT uid) FROM results").fetchone()
    by_request: dict[int, list[str]] = {}
    for request_id, data in rows:
        by_request.setdefault(request_id, []).append(data)
    missing = sorted(set(acknowledged) - set(by_request))
    duplicated = sorted(r for r, found in by_request.items() if len(found) > 1)
    assert missing == [], f"{len(missing)} acknowledged results are not in the database"
    assert duplicated == [], f"{len(duplicated)} results are in the database twice"
    assert uids[0] == uids[1] == BURST
    for request_id, value in acknowledged.items():
        assert f'"value":{value}' in by_request[request_id][0]
    print(
        f"postgres durability: {len(acknowledged)} acknowledged, database stopped after "
        f"{STOP_AFTER} and started after {START_AFTER}; {len(rows)} rows, 0 lost, 0 duplicated"
    )


def test_the_spool_outlives_a_killed_server_while_the_database_is_down(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    (tmp_path / "cell.yaml").write_text(CONFIG.format(url=pg_url))
    count = 50

    async def inspect_all(port: int) -> list[bool | None]:
        async with VisionClient("127.0.0.1", port) as client:
            return [
                (await client.inspect("bright", np.full((48, 64), i, np.uint8))).stored
                for i in range(count)
            ]

    # The database is created (and migrated) by a first server, then goes down.
    with serve(tmp_path):
        pass
    pg_cluster.stop_immediate()
    try:
        with serve(tmp_path) as (proc, port):
            assert run(inspect_all(port), 60.0) == [True] * count
            proc.kill()  # SIGKILL: nothing is flushed on the way out
            assert proc.wait(30) == -9
        assert spooled(tmp_path) == count
    finally:
        pg_cluster.start()
    with serve(tmp_path):
        run(wait_until(lambda: spooled(tmp_path) == 0, "the spool drains", 60.0), 70.0)
    with psycopg.connect(pg_url) as conn:
        total, distinct = conn.execute(
            "SELECT count(*), count(DISTINCT uid) FROM results"
        ).fetchone()
    assert total == distinct == count
