"""Inspections named in ``process_inspections`` run in worker processes, their images passed
through shared memory: the outcome is the same as in a thread, from another process; each
process keeps one block, removed when the lane stops; errors come back typed, and a process that
dies is replaced. Counts and values only, no timing."""

from __future__ import annotations

import os
import sys
import threading
from multiprocessing.shared_memory import SharedMemory
from pathlib import Path

import numpy as np
import pytest
from child_inspections import (
    CountsItsPickles,
    Misbehaving,
    UnpicklableInWorkers,
    WhereAmI,
    pickled_times,
)
from loopback import run

from protocol.errors import InspectionFailed, InternalError, ShuttingDown
from vision_server import Catalog, InspectionInput
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ConfigError, ServiceSettings, load_config
from vision_server.service import Images, InspectionService, InspectRequest, process_lane
from vision_server.service.process_lane import ProcessLane

COLOR = (np.arange(48 * 64, dtype=np.uint32).reshape(48, 64) % 251).astype(np.uint8)
DEPTH = np.full((48, 64), 700, np.uint16)


def test_an_inspection_named_for_processes_runs_in_another_process_with_its_images() -> None:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [WhereAmI()])
    settings = ServiceSettings(workers=1, queue_depth=0, process_inspections=("where",))
    service = InspectionService(catalog, settings)

    async def body() -> None:
        assert service.processes is not None
        reply = await service.inspect(
            InspectRequest("where", Images(COLOR, (DEPTH,)), overlay="array")
        )
        assert reply.data["pid"] != os.getpid()
        assert reply.data["mean"] == pytest.approx(float(COLOR.mean()))
        assert reply.data["depth"] == [[[48, 64], 700 * 48 * 64]]
        assert reply.overlay is not None
        assert np.array_equal(reply.overlay.image, 255 - COLOR)

    try:
        run(body(), timeout_s=120.0)
    finally:
        service.close()


def test_without_the_setting_it_runs_in_the_server_process() -> None:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [WhereAmI()])
    service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=0))

    async def body() -> None:
        assert service.processes is None
        reply = await service.inspect(InspectRequest("where", Images(COLOR)))
        assert reply.data["pid"] == os.getpid()

    try:
        run(body())
    finally:
        service.close()


def _created_blocks(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    names: list[str] = []
    real = SharedMemory.__init__

    def recording(self: SharedMemory, *args: object, **kwargs: object) -> None:
        real(self, *args, **kwargs)  # type: ignore[arg-type]
        if kwargs.get("create"):
            names.append(self.name)

    monkeypatch.setattr(SharedMemory, "__init__", recording)
    return names


def _gone(name: str) -> bool:
    try:
        SharedMemory(name=name).close()
    except FileNotFoundError:
        return True
    return False


def test_a_worker_keeps_one_block_for_its_requests_and_shutdown_removes_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # A block per request cost ~200 page faults and a resource-tracker round trip each time.
    names = _created_blocks(monkeypatch)
    lane = ProcessLane(1)
    try:
        for shift in range(3):
            image = (COLOR + shift).astype(np.uint8)
            outcome = lane.run(WhereAmI(), InspectionInput(image), overlay=False)
            assert outcome.data["mean"] == pytest.approx(float(image.mean()))
        assert len(names) == 1
        assert not _gone(names[0])
        bigger = np.zeros((1200, 1000), np.uint8)  # more than the first block's 1 MiB
        outcome = lane.run(WhereAmI(), InspectionInput(bigger), overlay=False)
        assert outcome.data["mean"] == 0.0
        assert len(names) == 2
        assert _gone(names[0])  # replaced by the larger one
    finally:
        lane.shutdown()
    assert all(_gone(name) for name in names)


def test_an_image_above_the_kept_size_gets_a_block_removed_after_its_run(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(process_lane, "KEPT_BLOCK_BYTES", COLOR.nbytes // 2)
    names = _created_blocks(monkeypatch)
    lane = ProcessLane(1)
    try:
        outcome = lane.run(WhereAmI(), InspectionInput(COLOR), overlay=False)
        assert outcome.data["mean"] == pytest.approx(float(COLOR.mean()))
        assert len(names) == 1
        assert _gone(names[0])
    finally:
        lane.shutdown()


def test_an_inspection_is_pickled_once_however_often_it_runs() -> None:
    lane = ProcessLane(1)
    inspection = CountsItsPickles()
    before = pickled_times()
    try:
        for _ in range(4):
            lane.run(inspection, InspectionInput(COLOR), overlay=False)
    finally:
        lane.shutdown()
    assert pickled_times() - before == 1


def test_the_inspections_own_errors_come_back_typed_and_the_worker_stays() -> None:
    lane = ProcessLane(1)
    try:
        lane.start()
        pids = lane.pids
        with pytest.raises(InspectionFailed, match="shows no part"):
            lane.run(Misbehaving("refuse"), InspectionInput(COLOR), overlay=False)
        with pytest.raises(FileNotFoundError, match="template.png"):
            lane.run(Misbehaving("oserror"), InspectionInput(COLOR), overlay=False)
        outcome = lane.run(Misbehaving("fine"), InspectionInput(COLOR), overlay=False)
        assert [outcome.data["pid"]] == pids == lane.pids
    finally:
        lane.shutdown()


def test_a_worker_that_dies_fails_its_request_and_is_replaced() -> None:
    lane = ProcessLane(1)
    try:
        lane.start()
        (first,) = lane.pids
        with pytest.raises(InternalError, match="ended during the inspection") as failed:
            lane.run(Misbehaving("die"), InspectionInput(COLOR), overlay=False)
        assert "'misbehaving'" in str(failed.value)
        outcome = lane.run(Misbehaving("fine"), InspectionInput(COLOR), overlay=False)
        assert outcome.data["pid"] != first
        assert lane.pids == [outcome.data["pid"]]
    finally:
        lane.shutdown()


def test_a_name_that_is_no_inspection_is_a_config_error(tmp_path: Path) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text(
        "server: {port: 0, process_inspections: [nope]}\n"
        "cameras: {tool: {source: request}}\n"
        "inspections:\n"
        "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 1}\n",
        encoding="utf-8",
    )
    with pytest.raises(ConfigError, match="'nope' is not an inspection") as refused:
        load_config(config)
    assert "process_inspections" in str(refused.value)


@pytest.mark.skipif(sys.platform != "linux", reason="per-thread niceness is Linux's")
def test_worker_processes_run_at_the_main_lanes_lower_priority() -> None:
    # Priority by cost (bench 2c): the locates in the processes yield the cores to the event
    # loop and the fast lane. The process's niceness is its own plus main_lane_nice.
    own = os.getpriority(os.PRIO_PROCESS, 0)
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [WhereAmI()])
    settings = ServiceSettings(
        workers=1, queue_depth=0, process_inspections=("where",), main_lane_nice=7
    )
    service = InspectionService(catalog, settings)

    async def body() -> None:
        reply = await service.inspect(InspectRequest("where", Images(COLOR)))
        assert reply.data["pid"] != os.getpid()
        assert reply.data["nice"] == min(own + 7, 19)

    try:
        run(body(), timeout_s=120.0)
    finally:
        service.close()
    assert os.getpriority(os.PRIO_PROCESS, 0) == own  # the server's own thread is untouched


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="SCHED_IDLE is Linux's")
def test_the_idle_policy_puts_the_worker_processes_at_sched_idle() -> None:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [WhereAmI()])
    settings = ServiceSettings(
        workers=1, queue_depth=0, process_inspections=("where",), main_lane_policy="idle"
    )
    service = InspectionService(catalog, settings)

    async def body() -> None:
        reply = await service.inspect(InspectRequest("where", Images(COLOR)))
        assert reply.data["policy"] == os.SCHED_IDLE

    try:
        run(body(), timeout_s=120.0)
    finally:
        service.close()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the server itself is untouched


def test_each_process_runs_opencv_with_the_threads_left_to_it() -> None:
    # A spawned process starts at one OpenCV thread per core; ``workers`` of them would
    # oversubscribe the cores. The service gives each the server's per-worker count.
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [WhereAmI()])
    settings = ServiceSettings(
        workers=2, queue_depth=0, process_inspections=("where",), opencv_threads=1
    )
    service = InspectionService(catalog, settings)

    async def body() -> None:
        reply = await service.inspect(InspectRequest("where", Images(COLOR)))
        assert reply.data["opencv_threads"] == 1

    try:
        run(body(), timeout_s=120.0)
    finally:
        service.close()


class Interrupted(Exception):
    """What an interrupted thread sees between sending a request and reading its reply."""


def test_a_reply_left_unread_by_an_interrupted_thread_is_not_taken_for_the_next_one() -> None:
    lane = ProcessLane(1)
    try:
        lane.start()
        conn = lane._workers[0].conn
        real_recv = conn.recv
        interrupted = [False]

        def recv_interrupted_once() -> object:
            if not interrupted[0]:
                interrupted[0] = True
                raise Interrupted
            return real_recv()

        conn.recv = recv_interrupted_once  # type: ignore[method-assign]
        with pytest.raises(Interrupted):
            lane.run(WhereAmI(), InspectionInput(COLOR, (DEPTH,)), overlay=False)
        # The image lies in the shared block, which the next request overwrites: the layout
        # that travels with each message (a depth frame, then none) tells the replies apart.
        darker = (COLOR // 2).astype(np.uint8)
        outcome = lane.run(WhereAmI(), InspectionInput(darker), overlay=False)
        assert outcome.data["depth"] == []
        assert outcome.data["mean"] == pytest.approx(float(darker.mean()))
    finally:
        lane.shutdown()


def test_a_thread_waiting_for_a_worker_when_the_lane_stops_gets_shutting_down() -> None:
    lane = ProcessLane(1)
    lane.start()
    taken = lane._idle.get()  # the only worker is busy
    assert taken is not None
    outcome: list[BaseException] = []

    def wait_for_a_worker() -> None:
        try:
            lane.run(WhereAmI(), InspectionInput(COLOR), overlay=False)
        except BaseException as exc:  # noqa: BLE001 - the test reads what it was
            outcome.append(exc)

    waiter = threading.Thread(target=wait_for_a_worker)
    waiter.start()
    lane.shutdown()
    waiter.join(60.0)
    assert not waiter.is_alive()
    assert len(outcome) == 1
    assert isinstance(outcome[0], ShuttingDown)


def test_a_process_that_could_not_unpickle_an_inspection_is_sent_it_again() -> None:
    # The server counts an inspection as held once sent; a process whose unpickling failed
    # says it lacks it, and the next request sends the pickle again (the same error, not a
    # lookup error of the process's cache).
    lane = ProcessLane(1)
    inspection = UnpicklableInWorkers()
    try:
        for _ in range(2):
            with pytest.raises(ValueError, match="cannot be unpickled in a worker"):
                lane.run(inspection, InspectionInput(COLOR), overlay=False)
        outcome = lane.run(WhereAmI(), InspectionInput(COLOR), overlay=False)
        assert outcome.data["mean"] == pytest.approx(float(COLOR.mean()))
    finally:
        lane.shutdown()
