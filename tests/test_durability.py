"""Durability of the result log (issue #8, item 5): SIGKILL the server in the middle of a burst
of 1,000 pipelined inspections; every result whose RESULT the client received is in the log.

The server records a result before it sends the answer (WAL, synchronous=NORMAL: a committed
transaction is in the operating system's page cache, which outlives the process). A RESULT is
matched to its row by the connection's peer address (``peer``) and the request id.
"""

from __future__ import annotations

import asyncio
import json
import re
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np

from protocol import Inspect, Result, payload_from_array
from robot_client.client import ReconnectPolicy, VisionClient
from robot_client.errors import ConnectionLost

REPO_ROOT = Path(__file__).resolve().parents[1]
CONFIG = """\
server: {port: 0, max_in_flight: 32, queue_depth: 64}
results: {path: results.sqlite3, store_images: none}
cameras: {tool: {source: request}}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}
"""
BURST = 1000
KILL_AFTER = 300


def test_every_acknowledged_result_survives_a_sigkill_mid_burst(tmp_path: Path) -> None:
    (tmp_path / "cell.yaml").write_text(CONFIG)
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", "cell.yaml"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        assert proc.stdout is not None
        port = int(re.findall(r":(\d+)", proc.stdout.readline())[-1])
        acknowledged: dict[int, float] = {}
        lost: list[int] = []

        async def burst() -> str:
            client = VisionClient(
                "127.0.0.1", port, request_timeout_s=60.0, reconnect=ReconnectPolicy(attempts=0)
            )
            await client.connect()
            assert client.stream is not None
            host, local_port = client.stream.get_extra_info("sockname")[:2]

            async def one(i: int) -> None:
                level = i % 256
                image = (payload_from_array(np.full((48, 64), level, np.uint8)),)
                try:
                    answer = await client.request(lambda rid: Inspect(rid, "bright", image))
                except ConnectionLost:
                    lost.append(i)
                    return
                assert isinstance(answer, Result)
                assert answer.data["value"] == float(level)
                acknowledged[answer.request_id] = answer.data["value"]
                if len(acknowledged) == KILL_AFTER:
                    proc.kill()  # SIGKILL: no shutdown, no checkpoint, no flush

            await asyncio.gather(*(one(i) for i in range(BURST)))
            await client.close()
            return f"{host}:{local_port}"

        peer = asyncio.run(asyncio.wait_for(burst(), 120.0))
        assert proc.wait(30) == -9
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=30)

    assert len(acknowledged) >= KILL_AFTER
    assert lost  # the kill came mid-burst: some requests were in flight or not yet sent
    assert len(acknowledged) + len(lost) == BURST
    # Opened after the kill (the WAL is replayed on open), read only.
    db = sqlite3.connect(f"file:{tmp_path / 'results.sqlite3'}?mode=ro", uri=True)
    try:
        rows = dict(
            db.execute(
                "SELECT request_id, data FROM results WHERE peer = ? AND inspection = 'bright'",
                (peer,),
            ).fetchall()
        )
    finally:
        db.close()
    missing = sorted(set(acknowledged) - set(rows))
    assert missing == [], f"{len(missing)} acknowledged results are not in the log"
    for request_id, value in acknowledged.items():
        assert json.loads(rows[request_id])["value"] == value
    print(
        f"durability: {len(acknowledged)} acknowledged before/around the SIGKILL, all in the log; "
        f"{len(rows)} rows for this connection ({len(rows) - len(acknowledged)} recorded but "
        f"never acknowledged); {len(lost)} requests lost in flight or unsent"
    )
