"""Cheap inspections run on the event loop itself (``inline_ms``), and what must not be on the
loop still is not: the result log's row, an overlay's encoding, decoding a compressed image, a
run that once took long. Which thread did what is recorded by the inspection and by wrappers
around the log and the encoder; nothing here depends on timing except the one slow run, which
is slow on purpose (20 ms against a 0.5 ms bound). An inspection is brought onto the loop by
running it until a run lands there (tests/helpers/inline_runs.py), not by counting runs."""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from inline_runs import until_on_the_loop
from loopback import run

from protocol import BadImage, ImageEncoding, ImagePayload, ImageRole, payload_from_array
from vision_server import Catalog
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ServiceSettings
from vision_server.frontends.images import payload_loader
from vision_server.inspections import InspectionInput, InspectionOutcome
from vision_server.results import ResultEntry, ResultLog
from vision_server.service import Images, InspectionService, InspectRequest
from vision_server.service import core as service_core

GRAY = np.full((48, 64), 200, np.uint8)


@dataclass(eq=False)
class Where:
    """An inspection that notes the thread of each run; ``slow_once_ms``: its next run sleeps
    that long first; ``fail``: its runs raise BAD_IMAGE."""

    name: str = "where"
    camera: str = "tool"
    type: str = "test_where"
    uses_depth: bool = False
    frames: int = 1
    threads: list[str] = field(default_factory=list)
    slow_once_ms: float = 0.0
    spin: bool = False
    fail: bool = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        self.threads.append(threading.current_thread().name)
        if self.slow_once_ms:
            if self.spin:  # busy: CPU time
                end = time.perf_counter() + self.slow_once_ms / 1000.0
                while time.perf_counter() < end:
                    pass
            else:  # waiting (a lock, I/O): wall time only
                time.sleep(self.slow_once_ms / 1000.0)
            self.slow_once_ms = 0.0
        if self.fail:
            raise BadImage("this part is not in the image")
        drawn = np.dstack([image.color] * 3) if overlay else None
        return InspectionOutcome(True, {"mean": float(image.color.mean())}, drawn)


class RecordingLog(ResultLog):
    """The SQLite result log, noting the thread each row was written from."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.threads: list[str] = []

    def record(self, entry: ResultEntry) -> int | None:
        self.threads.append(threading.current_thread().name)
        return super().record(entry)


def service_with(where: Where, **settings: Any) -> InspectionService:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [where])
    log = settings.pop("results", None)
    return InspectionService(
        catalog, ServiceSettings(workers=1, queue_depth=4, **settings), results=log
    )


async def onto_the_loop(service: InspectionService, where: Where, **request: Any) -> None:
    await until_on_the_loop(lambda: inspect_times(service, 1, **request), where.threads)


async def inspect_times(service: InspectionService, n: int, **request: Any) -> list[Any]:
    images = request.pop("images", None)
    replies = []
    for _ in range(n):
        loaded = images() if callable(images) else Images(GRAY)
        replies.append(await service.inspect(InspectRequest("where", loaded, **request)))
    return replies


def test_a_cheap_run_on_raw_images_is_on_the_event_loop_once_measured() -> None:
    """The first run has no measured cost and goes to a worker; the next ones run on the
    loop's own thread."""
    where = Where()

    async def body() -> None:
        service = service_with(where)
        await onto_the_loop(service, where)
        replies = await inspect_times(service, 3)
        assert all(r.passed for r in replies)
        assert service.pool.admitted == 0
        service.close()

    loop_thread = threading.current_thread().name
    run(body())
    assert where.threads[0].startswith("inspect")
    assert where.threads[-3:] == [loop_thread] * 3


def test_the_result_log_row_is_written_in_a_worker_when_the_run_was_on_the_loop(
    tmp_path: Path,
) -> None:
    where = Where()
    log = RecordingLog(tmp_path / "results.db")

    async def body() -> None:
        service = service_with(where, results=log)
        await onto_the_loop(service, where)
        replies = await inspect_times(service, 2)
        assert [r.stored for r in replies] == [True, True]
        assert all(r.result_id for r in replies)
        service.close()

    loop_thread = threading.current_thread().name
    try:
        run(body())
    finally:
        log.close()
    assert where.threads[-2:] == [loop_thread] * 2
    assert all(t.startswith("inspect") for t in log.threads)
    assert len(log.threads) == len(where.threads)  # one row per run


def test_an_error_row_of_a_run_on_the_loop_is_written_in_a_worker(tmp_path: Path) -> None:
    where = Where()
    log = RecordingLog(tmp_path / "results.db")

    async def body() -> None:
        service = service_with(where, results=log)
        await onto_the_loop(service, where)
        where.fail = True
        with pytest.raises(BadImage, match="not in the image"):
            await inspect_times(service, 1)
        assert service.pool.admitted == 0
        service.close()

    loop_thread = threading.current_thread().name
    try:
        run(body())
        rows = log.query(limit=10)
    finally:
        log.close()
    assert where.threads[-1] == loop_thread
    assert all(t.startswith("inspect") for t in log.threads)
    assert any(row.error and "not in the image" in row.error for row in rows)


def test_an_overlay_is_encoded_in_a_worker_when_the_run_was_on_the_loop(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    where = Where()
    encoded_in: list[str] = []
    encode = service_core._overlay

    def noting(image: Any, wanted: str) -> Any:
        encoded_in.append(threading.current_thread().name)
        return encode(image, wanted)

    monkeypatch.setattr(service_core, "_overlay", noting)

    async def body() -> None:
        service = service_with(where)
        # Drawing is part of the run: runs that draw are measured on their own.
        await onto_the_loop(service, where, overlay=".png")
        [reply] = await inspect_times(service, 1, overlay=".png")
        assert reply.overlay is not None
        assert reply.overlay.encoded is not None
        assert reply.overlay.encoded.startswith(b"\x89PNG")
        service.close()

    loop_thread = threading.current_thread().name
    run(body())
    assert where.threads[-2:] == [loop_thread] * 2
    assert len(encoded_in) == len(where.threads)
    assert all(t.startswith("inspect") for t in encoded_in)


def test_compressed_images_are_decoded_in_a_worker() -> None:
    """A PNG in the request is decoding work: never on the loop, however cheap the run."""
    where = Where()
    png = ImagePayload(
        ImageEncoding.PNG, 64, 48, service_core.encode_image(GRAY, ".png"), ImageRole.COLOR
    )

    async def body() -> None:
        service = service_with(where)
        await onto_the_loop(service, where)
        await inspect_times(service, 2, images=lambda: payload_loader([png]))
        await inspect_times(service, 1, images=lambda: payload_loader([payload_from_array(GRAY)]))
        service.close()

    loop_thread = threading.current_thread().name
    run(body())
    assert all(t.startswith("inspect") for t in where.threads[-3:-1])
    assert where.threads[-1] == loop_thread  # raw pixels through the same loader: cheap


@pytest.mark.parametrize("spin", [False, True], ids=["waiting", "busy"])
def test_one_slow_run_keeps_an_inspection_off_the_loop(spin: bool) -> None:
    """What may run on the loop is judged by the slowest recent run, not the mean: after a
    20 ms run, busy or waiting, the inspection goes back to a worker for the runs that
    follow."""
    where = Where(spin=spin)

    async def body() -> None:
        service = service_with(where)
        await onto_the_loop(service, where)
        where.slow_once_ms = 20.0
        await inspect_times(service, 1)  # on the loop: its cost was not known
        await inspect_times(service, 5)
        service.close()

    loop_thread = threading.current_thread().name
    run(body())
    assert where.threads[-6] == loop_thread
    assert all(t.startswith("inspect") for t in where.threads[-5:])


def test_inline_ms_zero_keeps_every_run_in_a_worker() -> None:
    where = Where()

    async def body() -> None:
        service = service_with(where, inline_ms=0.0)
        await inspect_times(service, 4)
        service.close()

    run(body())
    assert all(t.startswith("inspect") for t in where.threads)
