"""The inspection service on its own, without sockets: admission (BUSY), deadlines counted
from the request's arrival, image checks, errors without request ids, observers, reload off
the event loop. No sleeps: a gate inspection blocks a worker until the test releases it."""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import numpy as np
import pytest
from loopback import Gate, run, wait_until

from protocol import (
    BadImage,
    Busy,
    ConfigInvalid,
    DeadlineExceeded,
    ImageTooLarge,
    InvalidArgument,
    UnknownInspection,
)
from vision_server import Catalog
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ConfigError, ServiceSettings
from vision_server.service import (
    ImageNeeds,
    Images,
    InspectionRecord,
    InspectionService,
    InspectRequest,
    deadline_after,
)
from vision_server.service.builtin import MeanIntensityPresence

GRAY = np.full((48, 64), 200, np.uint8)


def make_catalog(*extra: Any) -> Catalog:
    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0), *extra],
    )


def make_service(*extra: Any, **settings: Any) -> InspectionService:
    settings.setdefault("workers", 1)
    settings.setdefault("queue_depth", 0)
    return InspectionService(make_catalog(*extra), ServiceSettings(**settings))


@pytest.fixture
def gate() -> Gate:
    return Gate()


# ----------------------------------------------------------------------------- admission


def test_a_full_service_answers_busy_and_takes_requests_again_once_a_slot_is_free() -> None:
    async def body() -> None:
        service = make_service()
        held = service.admit()  # what a front-end does at a frame's header
        with pytest.raises(Busy, match="all 1 inspection slots of the main lane are taken"):
            service.admit()
        with pytest.raises(Busy):
            await service.inspect(InspectRequest("brightness", Images(GRAY)))
        held.release()
        reply = await service.inspect(InspectRequest("brightness", Images(GRAY)))
        assert reply.passed
        assert service.pool.admitted == 0
        service.close()

    run(body())


def test_an_admitted_request_runs_on_its_reserved_slot(gate: Gate) -> None:
    async def body() -> None:
        service = make_service(gate)
        admission = service.admit()
        running = asyncio.create_task(
            service.inspect(InspectRequest("gate", Images(GRAY)), admission=admission)
        )
        await wait_until(lambda: gate.entered == 1, "the gate inspection runs")
        with pytest.raises(Busy):  # its slot is the only one, and it is taken
            service.admit()
        gate.release.set()
        assert (await running).data == {"gate": True}
        admission.release()
        assert service.pool.admitted == 0
        service.close()

    run(body())


def test_body_bytes_beyond_the_budget_are_busy_and_given_back() -> None:
    service = make_service(max_buffered_bytes=1000)
    first = service.admit(work=False, body_bytes=800)
    with pytest.raises(Busy, match="memory for request bodies") as refused:
        service.admit(work=False, body_bytes=400)
    assert refused.value.details["size"] == 400
    assert refused.value.details["retry_after_ms"] >= 1  # BUSY says when to try again
    assert service.budget.used == 800
    first.release()
    first.release()  # idempotent
    assert service.budget.used == 0
    service.close()


# ----------------------------------------------------------------------------- deadlines


def test_the_deadline_counts_from_arrival_not_from_submission(gate: Gate) -> None:
    """A request that arrived 10 s ago with a 1 s budget is late before it reaches the pool:
    DEADLINE_EXCEEDED, and the inspection never starts (counted from submission, it would run
    for a second first)."""

    async def body() -> None:
        service = make_service(gate)
        arrived = time.monotonic() - 10.0
        request = InspectRequest(
            "gate", Images(GRAY), arrived=arrived, deadline=deadline_after(arrived, 1000.0)
        )
        with pytest.raises(DeadlineExceeded, match="deadline of 1000 ms") as late:
            await service.inspect(request)
        assert late.value.request_id == 0
        assert gate.entered == 0
        assert service.pool.admitted == 0
        service.close()

    run(body())


def test_a_passed_deadline_answers_while_the_work_goes_on(gate: Gate) -> None:
    """The deadline passes while the inspection blocks: the caller is answered, the slot stays
    taken until the work returns (then it is given back)."""

    async def body() -> None:
        service = make_service(gate)
        # Already late by the time the gate is entered: the answer cannot wait for the gate.
        request = InspectRequest("gate", Images(GRAY), deadline=time.monotonic() + 0.05)
        with pytest.raises(DeadlineExceeded):
            await service.inspect(request)
        if gate.entered:  # it had started: its worker keeps the slot until the work returns
            assert service.pool.admitted == 1
        gate.release.set()
        await wait_until(lambda: service.pool.admitted == 0, "the slot is given back")
        service.close()

    run(body())


def test_deadline_after_is_absolute() -> None:
    assert deadline_after(100.0, None) is None
    assert deadline_after(100.0, 250.0) == pytest.approx(100.25)


# ----------------------------------------------------------------------------- images, errors


def test_errors_carry_no_request_id() -> None:
    async def body() -> None:
        service = make_service()
        with pytest.raises(UnknownInspection) as unknown:
            await service.inspect(InspectRequest("nope", Images(GRAY), request_id=7))
        assert unknown.value.request_id == 0
        with pytest.raises(BadImage, match="arrive in the request, and the request has none"):
            await service.inspect(InspectRequest("brightness"))
        service.close()

    run(body())


@pytest.mark.parametrize(
    ("images", "error", "words"),
    [
        (Images(GRAY.astype(np.uint16)), BadImage, "must be 8-bit"),
        (Images(GRAY, (np.zeros((48, 64), np.uint16),)), BadImage, "takes no depth image"),
        (Images(np.zeros((100, 100), np.uint8)), ImageTooLarge, "the limit is 5000"),
    ],
)
def test_images_are_checked_whoever_decoded_them(
    images: Images, error: type[Exception], words: str
) -> None:
    async def body() -> None:
        service = make_service(max_image_pixels=5000)
        with pytest.raises(error, match=words):
            await service.inspect(InspectRequest("brightness", images))
        service.close()

    run(body())


def test_a_loader_decodes_in_a_worker_with_what_the_inspection_needs() -> None:
    seen: list[tuple[ImageNeeds, str]] = []

    def loader(needs: ImageNeeds) -> Images:
        seen.append((needs, threading.current_thread().name))
        return Images(GRAY)

    async def body() -> None:
        service = make_service(max_image_pixels=9999)
        reply = await service.inspect(InspectRequest("brightness", loader, overlay=".png"))
        assert reply.overlay is not None
        assert reply.overlay.encoded is not None
        assert reply.overlay.encoded.startswith(b"\x89PNG")
        service.close()

    run(body())
    [(needs, thread)] = seen
    assert needs == ImageNeeds("brightness", False, 9999)
    assert thread.startswith("inspect")


# ----------------------------------------------------------------------------- observers


def test_observers_see_each_answered_inspection_until_they_unsubscribe() -> None:
    records: list[InspectionRecord] = []

    def failing(record: InspectionRecord) -> None:
        raise RuntimeError("a broken observer")

    async def body() -> None:
        service = make_service()
        service.subscribe(failing)  # logged, never fails the request
        unsubscribe = service.subscribe(records.append)
        request = InspectRequest("brightness", Images(GRAY), peer="console", request_id=3)
        reply = await service.inspect(request)
        unsubscribe()
        await service.inspect(InspectRequest("brightness", Images(GRAY)))
        assert records == [InspectionRecord(request, reply)]
        assert reply.total_ms >= reply.compute_ms
        service.close()

    run(body())


# ----------------------------------------------------------------------------- reload


def test_reload_runs_off_the_event_loop_and_a_refused_one_keeps_the_catalog() -> None:
    threads: list[str] = []
    fresh = make_catalog(Gate())
    outcomes: list[Catalog | Exception] = [fresh, ConfigError("cell.yaml:3 broken")]

    def reloader() -> Catalog:
        threads.append(threading.current_thread().name)
        outcome = outcomes.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    async def body() -> None:
        service = InspectionService(make_catalog(), reloader=reloader)
        assert await service.reload() is fresh
        assert service.catalog is fresh
        with pytest.raises(ConfigInvalid, match="cell.yaml:3 broken"):
            await service.reload()
        assert service.catalog is fresh
        assert threading.current_thread().name not in threads
        without = InspectionService(make_catalog())
        with pytest.raises(InvalidArgument, match="without a configuration file"):
            await without.reload()
        service.close()
        without.close()

    run(body())
    assert len(threads) == 2


def test_a_reload_is_announced_only_once_its_catalog_is_served() -> None:
    """`serve` says "configuration reloaded" from this hook: before, it said so from the
    reloader, before the new catalog was served, and a client asking at once saw the old one."""
    fresh = make_catalog(Gate())
    seen: list[bool] = []

    async def body() -> None:
        service = InspectionService(make_catalog(), reloader=lambda: fresh)
        service.on_reloaded = lambda catalog: seen.append(service.catalog is catalog is fresh)
        await service.reload()

    run(body())
    assert seen == [True]
