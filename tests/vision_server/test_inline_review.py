"""An independent review of issue 33's fast path, kept as regression tests.

- A run on the event loop that fails with an unexpected exception (a bug in an inspection,
  ``cv2.error`` on a degenerate input) after burning CPU counts as slow, as one that fails
  with a CellvisionError does: otherwise a client that can trigger it holds the loop on every
  such request.
- A request without a deadline that is cancelled (the TCP front-end cancels its request tasks
  on a broken connection and after the shutdown grace) while the thread work of its run is
  queued or running: the slot is held until that work ends, and the row of a run that
  happened is written. (The first version gave an inline run's slot back while its row was
  still being written, and dropped a row still queued; in the pool path a job cancelled while
  queued never gave its slot back, before issue 33 too.)
- The cost of a run on the loop is learnt from the run only: one compressed request (a PNG
  decoded in a worker, a server camera read there) does not make the same inspection on raw
  pixels look slow.

Nothing here measures time except the slow failure and the slow decoding (30 and 5 ms of CPU
against a 0.5 ms bound).
"""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from inline_runs import FailsSlowly, until_on_the_loop
from loopback import run, wait_until

from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ServiceSettings
from vision_server.results import ResultEntry, ResultLog
from vision_server.service import Images, InspectionService, InspectRequest

SMALL = np.full((48, 64), 120, np.uint8)


def slow_bug() -> FailsSlowly:
    """Fails with an exception that is no CellvisionError (a bug, or OpenCV's own error)."""
    return FailsSlowly("buggy", lambda: ValueError("an index out of range deep in the inspection"))


def test_a_run_on_the_loop_that_fails_slowly_with_a_bug_counts_as_slow() -> None:
    bug = slow_bug()
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [bug])

    async def body() -> None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            for _ in range(3):
                await service.inspect(InspectRequest("buggy", Images(SMALL)))
            bug.fail_after_ms = 30.0
            for _ in range(5):
                with pytest.raises(ValueError, match="index out of range"):
                    await service.inspect(InspectRequest("buggy", Images(SMALL)))
        finally:
            service.close()

    loop_thread = threading.current_thread().name
    run(body())
    failing = bug.threads[3:]
    assert failing.count(loop_thread) <= 1, failing


class Cheap:
    name = "cheap"
    camera = "tool"
    type = "test_cheap"
    uses_depth = False
    frames = 1

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        return InspectionOutcome(True, {"mean": float(image.color.mean())})


class GatedLog(ResultLog):
    """The SQLite result log, whose rows wait for ``gate`` once it is armed."""

    def __init__(self, path: Path) -> None:
        super().__init__(path)
        self.armed = False
        self.gate = threading.Event()
        self.entered = 0
        self.written: list[int | None] = []

    def record(self, entry: ResultEntry) -> int | None:
        if self.armed:
            self.entered += 1
            self.gate.wait(20.0)
        row = super().record(entry)
        self.written.append(entry.request_id)
        return row


def cheap_service(log: ResultLog, inline_ms: float) -> InspectionService:
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [Cheap()])
    # One fast-lane thread: a second row waits behind the first.
    settings = ServiceSettings(workers=1, fast_workers=1, queue_depth=4, inline_ms=inline_ms)
    return InspectionService(catalog, settings, results=log)


def test_a_cancelled_inline_request_holds_its_slot_until_its_row_is_written(
    tmp_path: Path,
) -> None:
    """The slot is the lane thread's while it writes the row: it is given back when the row
    is written, not when the request that waited for it was cancelled."""
    log = GatedLog(tmp_path / "results.db")

    async def body() -> tuple[int, int]:
        service = cheap_service(log, inline_ms=0.5)
        try:
            for _ in range(3):  # measured: the next runs are on the loop
                await service.inspect(InspectRequest("cheap", Images(SMALL)))
            log.armed = True
            task = asyncio.create_task(
                service.inspect(InspectRequest("cheap", Images(SMALL), request_id=7))
            )
            await wait_until(lambda: log.entered == 1, "the row is being written")
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
            held_while_writing = service.pool.admitted
            log.gate.set()
            await wait_until(lambda: len(log.written) == 4, "the row is written")
            await wait_until(lambda: service.pool.admitted == 0, "the slot is back")
            return held_while_writing, service.pool.admitted
        finally:
            log.gate.set()
            service.close()

    try:
        held_while_writing, after = run(body())
    finally:
        log.close()
    assert after == 0
    assert held_while_writing == 1, "the slot was given back while its thread still works"


@pytest.mark.parametrize("inline_ms", [0.0, 0.5], ids=["pool", "inline"])
def test_a_cancelled_request_whose_work_is_queued_leaks_nothing_and_loses_no_row(
    tmp_path: Path, inline_ms: float
) -> None:
    """Request 1's row hangs in the one fast-lane thread; request 2 (no deadline) waits behind
    it and is cancelled. Once the log moves again, every slot is back, and request 2's row is
    written when its run happened (inline: it ran on the loop before waiting for the row)."""
    log = GatedLog(tmp_path / "results.db")

    async def body() -> int:
        service = cheap_service(log, inline_ms=inline_ms)
        try:
            for _ in range(3):
                await service.inspect(InspectRequest("cheap", Images(SMALL)))
            log.armed = True
            first = asyncio.create_task(
                service.inspect(InspectRequest("cheap", Images(SMALL), request_id=1))
            )
            await wait_until(lambda: log.entered == 1, "request 1's row is being written")
            second = asyncio.create_task(
                service.inspect(InspectRequest("cheap", Images(SMALL), request_id=2))
            )
            await asyncio.sleep(0.05)  # request 2 has run (inline) and waits in the lane
            second.cancel()
            with pytest.raises(asyncio.CancelledError):
                await second
            log.gate.set()
            await first
            await asyncio.sleep(0.2)  # anything still queued in the lane runs now
            return service.pool.admitted
        finally:
            log.gate.set()
            service.close()

    try:
        admitted = run(body())
    finally:
        log.close()
    assert admitted == 0, "a cancelled request's slot was never given back"
    if inline_ms:
        assert 2 in log.written, "the row of a run that happened on the loop was dropped"


class Decoding:
    """A loader of one compressed image: ``spin_ms`` of CPU to decode (a PNG, a JPEG)."""

    cheap = False

    def __init__(self, image: np.ndarray, spin_ms: float) -> None:
        self._image = image
        self._spin_ms = spin_ms
        self.pixels = int(image.shape[0] * image.shape[1])

    def __call__(self, needs: object) -> Images:
        end = time.perf_counter() + self._spin_ms / 1000.0
        while time.perf_counter() < end:
            pass
        return Images(self._image)


def test_decoding_a_compressed_image_does_not_send_raw_requests_off_the_loop() -> None:
    """The decoding of a compressed image is done in a worker and never on the loop, yet the
    worker's RunClock starts before ``prepare`` (which decodes) and ``loop_costs`` knows the
    run only by the inspection: one PNG request makes the same inspection on raw pixels look
    as slow as the decoding, and sends it to the workers for the next ~50 runs (a client that
    mixes one PNG in 50 keeps it off the loop for good)."""
    bug = slow_bug()
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [bug])

    async def body() -> None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            await until_on_the_loop(
                lambda: service.inspect(InspectRequest("buggy", Images(SMALL))), bug.threads
            )
            await service.inspect(InspectRequest("buggy", Decoding(SMALL, 5.0)))
            for _ in range(3):
                await service.inspect(InspectRequest("buggy", Images(SMALL)))
        finally:
            service.close()

    loop_thread = threading.current_thread().name
    run(body())
    assert bug.threads[-3:] == [loop_thread] * 3, bug.threads
