"""The result log's faults reach the client and the health check (issue 13, holes 6 and 8).

A ``vision-server serve`` process whose files may not grow past 256 KiB (``RLIMIT_FSIZE``, with
SIGXFSZ ignored, so that ``write()`` fails with EFBIG as on a full disk) answers a burst of
pipelined INSPECTs: every RESULT says whether its row was written (``stored``), every one that
does not say ``stored: false`` is in the log, the server's counters match, and both PING and
``vision-server ping`` (the container's HEALTHCHECK) report it unhealthy.

A result log that cannot be created at start is one line on stderr and exit 2, not a traceback;
``check-config`` reports it too.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import resource
import signal
import sqlite3
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from loopback import client_for, run, server_in_thread, wait_until

from protocol import Inspect, InspectionFailed, Ping, Pong, Result, payload_from_array
from robot_client.client import ReconnectPolicy, VisionClient
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.results import ResultLog
from vision_server.server import VisionServer
from vision_server.service.builtin import MeanIntensityPresence

REPO_ROOT = Path(__file__).resolve().parents[2]
CONFIG = """\
server: {{port: 0, max_in_flight: 32, queue_depth: 64}}
results: {{path: {path}, store_images: {images}}}
cameras: {{tool: {{source: request}}}}
inspections:
  - {{name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}}
"""
BURST = 300
FILE_SIZE_LIMIT = 256 * 1024
"""Bytes any file of the server may reach: the WAL passes it after a dozen commits."""


def _write_config(directory: Path, path: str = "results.sqlite3", images: str = "none") -> Path:
    config = directory / "cell.yaml"
    config.write_text(CONFIG.format(path=path, images=images))
    return config


def _small_files() -> None:
    """In the child before exec: files stop growing at FILE_SIZE_LIMIT, write() gets EFBIG."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (FILE_SIZE_LIMIT, FILE_SIZE_LIMIT))


def _vision_server(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "vision_server", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_a_result_that_was_not_logged_says_so_and_the_server_turns_unhealthy(
    tmp_path: Path,
) -> None:
    _write_config(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", "cell.yaml"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_small_files,
    )
    try:
        assert proc.stdout is not None
        port = int(re.findall(r":(\d+)", proc.stdout.readline())[-1])

        async def burst() -> tuple[str, list[Result], Pong]:
            client = VisionClient(
                "127.0.0.1", port, request_timeout_s=60.0, reconnect=ReconnectPolicy(attempts=0)
            )
            await client.connect()
            assert client.stream is not None
            host, local_port = client.stream.get_extra_info("sockname")[:2]
            image = (payload_from_array(np.full((48, 64), 120, np.uint8)),)

            async def one() -> Result:
                answer = await client.request(lambda rid: Inspect(rid, "bright", image))
                assert isinstance(answer, Result)
                return answer

            answers = await asyncio.gather(*(one() for _ in range(BURST)))
            pong = await client.request(lambda rid: Ping(rid, "health"))
            assert isinstance(pong, Pong)
            await client.close()
            return f"{host}:{local_port}", list(answers), pong

        peer, answers, pong = asyncio.run(asyncio.wait_for(burst(), 120.0))
        ping = _vision_server("ping", "--server", f"127.0.0.1:{port}", cwd=tmp_path)
    finally:
        if proc.poll() is None:
            proc.terminate()
        _, stderr = proc.communicate(timeout=60)

    assert all(a.passed and a.data["value"] == 120.0 for a in answers)
    # The server has a result log: every RESULT says whether it was written.
    assert {a.stored for a in answers} <= {True, False}
    stored = {a.request_id for a in answers if a.stored}
    not_stored = {a.request_id for a in answers if a.stored is False}
    assert stored, "the first results must fit under the size limit"
    assert not_stored, "the size limit must have been reached"

    db = sqlite3.connect(f"file:{tmp_path / 'results.sqlite3'}?mode=ro", uri=True)
    try:
        logged = {
            rid
            for (rid,) in db.execute(
                "SELECT request_id FROM results WHERE peer = ? AND inspection = 'bright'", (peer,)
            )
        }
    finally:
        db.close()
    # The promise: a result acknowledged without stored: false is in the log.
    missing = sorted(stored - logged)
    assert missing == [], f"{len(missing)} results acknowledged as stored are not in the log"
    assert logged == stored

    health = pong.health
    assert health is not None
    assert health["ok"] is False
    assert not pong.healthy
    counters = health["result_log"]
    assert counters["failed"] == len(not_stored)
    assert counters["written"] == len(stored)
    assert counters["failing"] is True
    assert counters["last_error"]

    assert ping.returncode == 1, ping
    assert "UNHEALTHY" in ping.stderr
    assert f"{len(not_stored)} failed" in ping.stderr
    assert "Traceback" not in stderr
    print(
        f"disk full: {len(stored)} results stored, {len(not_stored)} answered stored: false; "
        f"ping: {ping.stderr.strip()}"
    )


def test_a_healthy_server_pings_healthy_with_its_counters(tmp_path: Path) -> None:
    _write_config(tmp_path)
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", "cell.yaml"],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        port = int(re.findall(r":(\d+)", proc.stdout.readline())[-1])

        async def three() -> list[Result]:
            async with VisionClient("127.0.0.1", port, request_timeout_s=30.0) as client:
                image = np.full((48, 64), 7, np.uint8)
                return list(await asyncio.gather(*(client.inspect("bright", image) for _ in "abc")))

        answers = asyncio.run(asyncio.wait_for(three(), 60.0))
        ping = _vision_server("ping", "--server", f"127.0.0.1:{port}", cwd=tmp_path)
    finally:
        if proc.poll() is None:
            proc.terminate()
        proc.communicate(timeout=60)
    assert [a.stored for a in answers] == [True] * 3
    assert ping.returncode == 0, ping
    assert "healthy: result log: 3 written, 0 failed" in ping.stdout


# ----------------------------------------------------------------------------- in process


@dataclass(frozen=True)
class AlwaysFails:
    """An inspection that cannot run: its request is answered ERROR and logged as an error row."""

    name: str = "broken"
    camera: str = "tool"
    type: str = "presence"
    uses_depth: bool = False
    frames: int = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        raise InspectionFailed("no part in view")


def test_a_lost_error_row_counts_too_and_no_log_means_no_stored_field(tmp_path: Path) -> None:
    catalog = Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("brightness", "tool", 0.0, 255.0), AlwaysFails()],
    )
    image = np.full((8, 8), 200, np.uint8)

    async def exchange(server: VisionServer) -> tuple[Result, Pong]:
        async with client_for(server) as client:
            with pytest.raises(InspectionFailed):
                await client.inspect("broken", image)
            result = await client.inspect("brightness", image)
            pong = await client.request(lambda rid: Ping(rid))
            assert isinstance(pong, Pong)
            return result, pong

    log = ResultLog(tmp_path / "results.sqlite3")
    with server_in_thread(catalog, results=log) as server:
        result, pong = run(exchange(server))
    assert result.stored is True
    assert pong.health is not None
    assert pong.health["ok"] is True
    assert pong.health["result_log"]["written"] == 2  # the error row and the result
    assert [r.error for r in log.query(newest_first=False)] == [
        "INSPECTION_FAILED: no part in view",
        None,
    ]

    log.close()  # every write fails from now on, error rows included
    with server_in_thread(catalog, results=log) as server:
        result, pong = run(exchange(server))
    assert result.stored is False
    assert pong.health is not None
    assert pong.health["ok"] is False
    assert pong.health["result_log"]["failed"] == 2

    with server_in_thread(catalog) as server:  # no result log: nothing to promise
        result, pong = run(exchange(server))
    assert result.stored is None
    assert pong.health is not None
    assert pong.health["ok"] is True
    assert "result_log" not in pong.health
    assert pong.health["admission"]["connections"] == 1


def test_ping_answers_while_a_write_waits_for_a_locked_database(tmp_path: Path) -> None:
    """The health report is read on the event loop: it must not wait for a write in progress
    (a locked database holds the writer for up to ``busy_timeout_s``, here longer than the
    test's whole deadline)."""
    db = tmp_path / "results.sqlite3"
    log = ResultLog(db, busy_timeout_s=30.0)
    inside = threading.Event()
    real_insert = log._insert

    def insert(*args: Any) -> Any:
        inside.set()
        return real_insert(*args)

    log._insert = insert  # type: ignore[method-assign]
    other = sqlite3.connect(db, isolation_level=None)
    other.execute("BEGIN EXCLUSIVE")  # another process holds the write lock

    async def exchange(server: VisionServer) -> tuple[Pong, Result]:
        async with client_for(server, request_timeout_s=20.0) as client:
            pending = asyncio.ensure_future(
                client.inspect("brightness", np.full((8, 8), 200, np.uint8))
            )
            await wait_until(inside.is_set, "the write is waiting for the lock")
            pong = await client.request(lambda rid: Ping(rid))
            assert isinstance(pong, Pong)
            assert not pending.done()
            other.execute("COMMIT")
            return pong, await pending

    try:
        with server_in_thread(results=log) as server:
            pong, result = run(exchange(server), timeout_s=15.0)
    finally:
        if other.in_transaction:
            other.execute("ROLLBACK")
        other.close()
        log.close()
    assert pong.health is not None
    assert pong.health["result_log"]["written"] == 0
    assert result.stored is True


# ----------------------------------------------------------------------------- at start


@contextlib.contextmanager
def _read_only_mount(directory: Path) -> Iterator[None]:
    """A read-only tmpfs on ``directory`` (as Docker's ``/config:ro``); skip where not allowed."""
    directory.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(directory)],
        capture_output=True,
        text=True,
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {mounted.stderr.strip()}")
    try:
        yield
    finally:
        subprocess.run(["umount", str(directory)], check=True)


@pytest.fixture(params=["under_a_file", "a_directory", "read_only", "no_permission"])
def bad_log(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, str]]:
    """A result-log path that cannot be created, and the OS error it must be reported with."""
    kind = request.param
    if kind == "under_a_file":
        (tmp_path / "plain").write_text("a file, not a directory")
        yield "plain/results.sqlite3", "Not a directory"
    elif kind == "a_directory":
        (tmp_path / "results.sqlite3").mkdir()
        yield "results.sqlite3", "Is a directory"
    elif kind == "read_only":
        with _read_only_mount(tmp_path / "ro"):
            yield "ro/results.sqlite3", "Read-only file system"
    else:
        if os.geteuid() == 0:
            pytest.skip("root may write anywhere: permissions cannot be tested as root")
        (tmp_path / "locked").mkdir(mode=0o555)
        yield "locked/sub/results.sqlite3", "Permission denied"


def test_serve_with_a_result_log_that_cannot_be_created_is_one_line_and_exit_2(
    tmp_path: Path, bad_log: tuple[str, str]
) -> None:
    path, reason = bad_log
    _write_config(tmp_path, path=path)
    done = _vision_server("serve", "--config", "cell.yaml", cwd=tmp_path)
    assert done.returncode == 2, done
    assert "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(
        "vision-server serve: invalid configuration: cell.yaml:2 results -> path"
    )
    assert reason in lines[0]
    assert str(tmp_path / path) in lines[0]
    assert done.stdout == ""


def test_check_config_reports_a_result_log_that_cannot_be_created(
    tmp_path: Path, bad_log: tuple[str, str]
) -> None:
    path, reason = bad_log
    _write_config(tmp_path, path=path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    done = _vision_server("check-config", "cell.yaml", cwd=tmp_path)
    assert done.returncode == 2, done
    assert "cell.yaml:2 results -> path" in done.stderr
    assert reason in done.stderr
    assert "Traceback" not in done.stderr
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # it created nothing
    as_json = _vision_server("check-config", "--json", "cell.yaml", cwd=tmp_path)
    assert as_json.returncode == 2
    assert '"path": "results -> path"' in as_json.stdout
    assert '"line": 2' in as_json.stdout


def test_check_config_accepts_a_result_log_that_can_be_created(tmp_path: Path) -> None:
    _write_config(tmp_path, path="logs/new/results.sqlite3", images="failures")
    done = _vision_server("check-config", "cell.yaml", cwd=tmp_path)
    assert done.returncode == 0, done
    assert not (tmp_path / "logs").exists()  # checked, not created
