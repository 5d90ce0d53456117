"""Faults while serving (issue #8, item 3): a client gone mid-frame, the server SIGKILLed in the
middle of a vision pick, a camera that fails and comes back, a full result log.

(A configuration reload with a broken file keeping the old configuration is tested in
tests/vision_server/test_runtime.py: over SIGHUP, RELOAD and the runtime.)
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import sqlite3
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from example_servers import example_cell_into, serve_command

from protocol import CameraUnavailable, Hello, Inspect, payload_from_array
from robot_client import SyncVisionClient
from robot_client.client import ReconnectPolicy, VisionClient
from robot_client.devices.sim import sim_devices
from robot_client.skills import FailureReason, SkillContext, default_registry, execute
from vision_server.results import ResultLog
from vision_server.results import sqlite as results_module
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import CellRuntime, builtin_catalog

REPO_ROOT = Path(__file__).resolve().parents[1]
GRAY = np.full((48, 64), 200, np.uint8)


@contextlib.contextmanager
def server_in_thread(server: VisionServer) -> Iterator[VisionServer]:
    """``server`` started on its own event loop in a background thread."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="test-server", daemon=True)
    thread.start()
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(10.0)
        yield server
    finally:
        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(server.stop(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()


def wait_until(predicate: Callable[[], bool], what: str, timeout_s: float = 15.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


# ----------------------------------------------------------------------------- mid-frame


@pytest.mark.parametrize("abort", [False, True], ids=["FIN", "RST"])
def test_clients_gone_in_the_middle_of_a_frame_leave_the_server_serving(
    abort: bool, caplog: pytest.LogCaptureFixture
) -> None:
    frame = Inspect(2, "brightness", (payload_from_array(GRAY),)).to_frame((1, 0)).serialize()
    cuts = [1, 12, 23, 24, 40, len(frame) // 2, len(frame) - 1]
    with server_in_thread(VisionServer(builtin_catalog(), ServerSettings(port=0))) as server:
        for cut in cuts:
            sock = socket.create_connection(("127.0.0.1", server.port), timeout=10.0)
            sock.sendall(Hello(1).to_frame((1, 0)).serialize())
            assert sock.recv(65536)  # WELCOME
            sock.sendall(frame[:cut])
            if abort:  # reset instead of an orderly close
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            sock.close()
        wait_until(lambda: not server.tcp.connections, "the server to drop the broken connections")
        with SyncVisionClient("127.0.0.1", server.port) as client:
            assert client.ping("still here") >= 0.0
            assert client.inspect("brightness", GRAY).data["value"] == 200.0
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


# ----------------------------------------------------------------------------- SIGKILL mid-task

STALLING_SERVER = """
import asyncio, threading
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server import Catalog
from vision_server.server import ServerSettings, VisionServer

class Stall:
    name, type, camera, uses_depth, frames = "cap_locate", "locate", "tool", False, 1

    def run(self, image, *, overlay):
        print("inspecting", flush=True)
        threading.Event().wait()  # until the test kills this process

async def main():
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [Stall()])
    server = VisionServer(catalog, ServerSettings(port=0))
    await server.start()
    print(server.port, flush=True)
    await server.serve_forever()

asyncio.run(main())
"""

SCENE = REPO_ROOT / "examples/scenes/grundfos_cell.yaml"
DOWN = [np.pi, 0.0, 0.0]


def _readline(proc: subprocess.Popen[str], timeout_s: float = 60.0) -> str:
    """The next stdout line of ``proc``, without blocking forever."""
    assert proc.stdout is not None
    box: list[str] = []
    reader = threading.Thread(target=lambda: box.append(proc.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    reader.start()
    reader.join(timeout_s)
    assert box, f"no output from the server within {timeout_s} s"
    return box[0]


def test_server_killed_during_a_vision_pick_no_grasp_on_stale_vision_then_reconnect(
    tmp_path: Path,
) -> None:
    from geometry import transform_from_xyz_rpy
    from simulation import SimCell

    cap_height, grasp_depth = 0.025, 0.0125
    record_values = {
        "p_cam_start": transform_from_xyz_rpy([0.05, -0.55, 0.275], DOWN),
        "p_cam_end": transform_from_xyz_rpy([0.55, -0.55, 0.275], DOWN),
        "h_detect": cap_height,
        "h_grasp": cap_height - grasp_depth,
    }
    stalling = subprocess.Popen(
        [sys.executable, "-c", STALLING_SERVER], cwd=REPO_ROOT, stdout=subprocess.PIPE, text=True
    )
    procs = [stalling]
    try:
        port = int(_readline(stalling))
        cell = SimCell.from_yaml(SCENE, seed=7)
        vision = SyncVisionClient(
            "127.0.0.1",
            port,
            request_timeout_s=60.0,
            reconnect=ReconnectPolicy(attempts=60, initial_s=0.05, max_s=0.5),
        )
        ctx = SkillContext.create(sim_devices(cell, vision=vision))
        closes: list[int] = []
        moves: list[float] = []
        real_close, real_move = ctx.gripper.close, ctx.robot.move_linear

        def counting_close(*args: Any, **kwargs: Any) -> Any:
            closes.append(1)
            return real_close(*args, **kwargs)

        def recording_move(pose: Any, *args: Any, **kwargs: Any) -> Any:
            moves.append(float(pose[2, 3]))
            return real_move(pose, *args, **kwargs)

        ctx.gripper.close = counting_close  # type: ignore[method-assign]
        ctx.robot.move_linear = recording_move  # type: ignore[method-assign]
        skill = default_registry().get("vision_pick")
        record = skill.teach("l1", record_values, ctx)
        ctx.robot.move_linear(record_values["p_cam_start"])
        moves.clear()

        outcome_box: list[Any] = []
        first = threading.Thread(target=lambda: outcome_box.append(execute(skill, record, ctx)))
        first.start()
        assert _readline(stalling) == "inspecting\n"  # the INSPECT is in flight
        stalling.kill()
        stalling.wait(30)
        first.join(60)
        (outcome,) = outcome_box
        # The request in flight failed with the lost connection: the skill stops safely.
        assert outcome.reason is FailureReason.VISION_UNAVAILABLE, outcome
        assert closes == []  # no grasp
        assert min(moves) > record_values["h_grasp"] + 0.1  # never went down to grasp
        assert cell.gripper.held is None

        # A new server on the same port; the client reconnects with backoff (it starts trying
        # before the server listens) and the skill, run again, looks again and picks once.
        # Its other front-ends (the example's console) on port 0: the defaults may be taken.
        restarted = subprocess.Popen(
            serve_command(example_cell_into(tmp_path), port=port),
            cwd=REPO_ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        procs.append(restarted)
        ctx.robot.move_linear(record_values["p_cam_start"])
        second = execute(skill, record, ctx)
        assert second.ok, second
        assert len(closes) == 1  # exactly one pick in all
        assert cell.gripper.held is not None
        assert vision._client.reconnects == 1
        vision.close()
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=30)


# ----------------------------------------------------------------------------- cameras

CAMERA_CONFIG = """\
server: {port: 0}
results: {enabled: false}
cameras:
  video: {source: opencv, device: clip.avi, loop_file: true, reconnect_interval_s: 0.1}
  replay: {source: folder, path: frames}
inspections:
  - {name: on_video, type: presence, camera: video, measure: mean_intensity, min: 0}
  - {name: on_folder, type: presence, camera: replay, measure: mean_intensity, min: 0}
"""


def _write_video(path: Path, frames: int = 6) -> None:
    """A short MJPG clip, written under another name and renamed (never seen half-written)."""
    tmp = path.with_name(f".tmp-{path.name}")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter.fourcc(*"MJPG"), 30.0, (64, 48))
    assert writer.isOpened(), "OpenCV cannot write MJPG/AVI here"
    for _ in range(frames):
        writer.write(np.full((48, 64, 3), 120, np.uint8))
    writer.release()
    tmp.replace(path)


def _outcome(client: SyncVisionClient, inspection: str) -> str:
    try:
        client.inspect(inspection, timeout_s=20.0)
    except CameraUnavailable:
        return "unavailable"
    return "result"


def test_a_failing_camera_is_camera_unavailable_then_reconnects_by_itself(
    tmp_path: Path,
) -> None:
    (tmp_path / "cell.yaml").write_text(CAMERA_CONFIG)
    frames = tmp_path / "frames"
    frames.mkdir()
    cv2.imwrite(str(frames / "f0.png"), GRAY)
    runtime = CellRuntime(tmp_path / "cell.yaml")
    server = VisionServer(runtime.catalog, ServerSettings(port=0))
    video = tmp_path / "clip.avi"
    try:
        with (
            server_in_thread(server),
            SyncVisionClient("127.0.0.1", server.port) as client,
        ):
            # The video file is not there yet: CAMERA_UNAVAILABLE, at once and typed.
            assert _outcome(client, "on_video") == "unavailable"
            _write_video(video)
            wait_until(lambda: _outcome(client, "on_video") == "result", "the camera to come up")
            # It disappears while playing (at its end the camera reopens it and fails) ...
            video.unlink()
            wait_until(lambda: _outcome(client, "on_video") == "unavailable", "the camera down")
            # ... and comes back: the camera reconnects without a restart or a reload.
            _write_video(video)
            wait_until(lambda: _outcome(client, "on_video") == "result", "a reconnect")
            assert runtime.catalog.cameras["video"].status()["reconnects"] >= 2

            # The folder camera: the directory goes away and comes back.
            assert _outcome(client, "on_folder") == "result"
            frames.rename(tmp_path / "gone")
            assert _outcome(client, "on_folder") == "unavailable"
            (tmp_path / "gone").rename(frames)
            assert _outcome(client, "on_folder") == "result"
            assert client.ping() >= 0.0
    finally:
        runtime.close()


# ----------------------------------------------------------------------------- disk full


def test_a_full_result_log_still_answers_and_logs_the_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    connections: list[sqlite3.Connection] = []
    real_connect = results_module._connect

    def connect(path: Path, *, readonly: bool, busy_timeout_s: float) -> sqlite3.Connection:
        conn = real_connect(path, readonly=readonly, busy_timeout_s=busy_timeout_s)
        connections.append(conn)
        return conn

    monkeypatch.setattr(results_module, "_connect", connect)
    caplog.set_level(logging.INFO, logger="vision_server.results")
    log = ResultLog(tmp_path / "results.sqlite3", store_images="all")
    (db,) = connections
    server = VisionServer(builtin_catalog(), ServerSettings(port=0), results=log)
    try:
        with server_in_thread(server):

            async def inspect_all(n: int, level: int) -> list[float]:
                async with VisionClient("127.0.0.1", server.port) as client:
                    image = np.full((48, 64), level, np.uint8)
                    answers = await asyncio.gather(
                        *(client.inspect("brightness", image) for _ in range(n))
                    )
                    return [a.data["value"] for a in answers]

            assert asyncio.run(inspect_all(3, 150)) == [150.0] * 3
            rows_before = log.count()
            # The disk is full: SQLite cannot grow the file (SQLITE_FULL, as on ENOSPC).
            pages = db.execute("PRAGMA page_count").fetchone()[0]
            db.execute(f"PRAGMA max_page_count = {pages}")
            for _ in range(50):  # until the free room in the last pages is used up too
                assert asyncio.run(inspect_all(10, 180)) == [180.0] * 10  # still answered
                if log.errors:
                    break
            assert log.errors > 0
            assert "full" in (log.status().last_error or "")
            errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
            assert errors
            assert any("full" in r.getMessage() for r in errors)
            # Room again: the log takes results again by itself.
            db.execute("PRAGMA max_page_count = 1073741823")
            assert asyncio.run(inspect_all(2, 90)) == [90.0] * 2
            assert log.count() >= rows_before + 2
    finally:
        log.close()
