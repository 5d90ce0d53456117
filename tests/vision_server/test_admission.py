"""Admission by lane and by cost, without sockets or sleeps: the worker pool's lanes, its FIFO
of waiters (what TCP backpressure waits in), the cost bound, and the service running a cheap
inspection in the fast lane while the main lane is held by a gate."""

from __future__ import annotations

import asyncio
import os
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from loopback import Gate, run, wait_until

from protocol import Busy
from vision_server import Catalog
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ConfigError, ServiceSettings, load_config
from vision_server.service import Images, InspectionService, InspectRequest
from vision_server.service.admission import CostModel, Slot, Waiter, WorkPool
from vision_server.service.builtin import MeanIntensityPresence

GRAY = np.full((48, 64), 200, np.uint8)


def pool_with(**costs: float) -> WorkPool:
    model = CostModel()
    for key, ms in costs.items():
        model.observe(key, ms)
    return WorkPool(1, 0, fast_workers=1, fast_lane_ms=5.0, costs=model)


def test_a_cheap_request_gets_the_fast_lane_while_the_main_lane_is_full() -> None:
    pool = pool_with(cheap=1.0, heavy=30.0)
    heavy = pool.try_reserve("heavy")
    assert heavy is not None
    assert heavy.lane is pool.main
    assert pool.try_reserve("heavy") is None  # one worker, no queue
    assert pool.try_reserve("unmeasured") is None  # unknown cost: the main lane
    cheap = pool.try_reserve("cheap")
    assert cheap is not None
    assert cheap.lane is pool.fast
    pool.release(heavy)
    pool.release(cheap)
    assert pool.admitted == 0


def test_a_lane_admits_by_cost_not_only_by_count() -> None:
    model = CostModel()
    model.observe("heavy", 60.0)
    model.observe("light", 10.0)
    pool = WorkPool(1, 10, fast_workers=0, max_queue_ms=100.0, costs=model)
    first = pool.try_reserve("heavy")
    assert first is not None
    assert pool.try_reserve("heavy") is None  # 120 ms of work > 100 ms: refused, 10 places free
    # BUSY's reason names the bound that refused it, not the slots (10 of 11 are free).
    why = pool.full_because("heavy")
    assert "holds 60 ms of measured work in 1 request(s)" in why
    assert "bound of 100 ms (max_queue_ms x 1 threads)" in why
    light = pool.try_reserve("light")  # 70 ms fits
    assert light is not None
    assert pool.main.admitted_cost_ms == pytest.approx(70.0)
    pool.release(first)
    pool.release(light)
    assert pool.main.admitted_cost_ms == 0.0


def test_a_request_heavier_than_the_bound_still_runs_on_an_empty_lane() -> None:
    model = CostModel()
    model.observe("huge", 10_000.0)
    pool = WorkPool(1, 4, fast_workers=0, max_queue_ms=100.0, costs=model)
    slot = pool.try_reserve("huge")
    assert slot is not None
    pool.release(slot)


def test_waiters_get_freed_slots_first_come_first_served() -> None:
    async def body() -> None:
        pool = pool_with(heavy=30.0)
        held = pool.try_reserve("heavy")
        assert held is not None
        first = pool.reserve_or_wait("heavy")
        second = pool.reserve_or_wait("heavy")
        assert isinstance(first, Waiter)
        assert isinstance(second, Waiter)
        assert pool.waiting == 2
        pool.release(held)
        # Nobody jumps the queue: the freed slot is the first waiter's already.
        assert pool.try_reserve("heavy") is None
        got = await first.wait(10.0)
        assert isinstance(got, Slot)
        assert pool.waiting == 1
        pool.release(got)
        assert isinstance(await second.wait(10.0), Slot)
        assert pool.waiting == 0

    run(body())


def test_a_waiter_that_gives_up_leaves_the_queue_and_its_slot_is_not_lost() -> None:
    async def body() -> None:
        pool = pool_with(heavy=30.0)
        held = pool.try_reserve("heavy")
        assert held is not None
        waiter = pool.reserve_or_wait("heavy")
        assert isinstance(waiter, Waiter)
        assert await waiter.wait(0.0) is None
        assert pool.waiting == 0
        pool.release(held)
        assert pool.admitted == 0
        again = pool.try_reserve("heavy")
        assert again is not None
        pool.release(again)

    run(body())


def test_the_cost_model_learns_from_the_jobs_it_runs() -> None:
    async def body() -> None:
        pool = WorkPool(1, 0, fast_workers=0)
        slot = pool.try_reserve("job")
        assert slot is not None
        assert await pool.submit(slot, lambda: 42) == 42
        assert pool.costs.estimate("job") is not None
        assert pool.admitted == 0

    run(body())


def test_busy_says_when_to_try_again() -> None:
    pool_settings = ServiceSettings(workers=1, queue_depth=0, fast_workers=0)
    service = InspectionService(
        Catalog.build(
            [RequestCamera("tool", RequestCameraSettings())],
            [MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
        ),
        pool_settings,
    )
    service.pool.costs.observe("brightness", 40.0)
    held = service.admit(key="brightness")
    with pytest.raises(Busy) as refused:
        service.admit(key="brightness")
    assert refused.value.details["retry_after_ms"] >= 40  # the job ahead of it
    held.release()
    service.close()


def test_a_cheap_inspection_runs_while_a_long_one_holds_every_main_worker() -> None:
    """Mixed load: the gate holds the only main worker; brightness, measured cheap once, runs
    in the fast lane meanwhile instead of waiting behind it."""
    gate = Gate()
    catalog = Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [MeanIntensityPresence("brightness", "tool", 64.0, 255.0), gate],
    )
    settings = ServiceSettings(workers=1, queue_depth=4, fast_workers=1, fast_lane_ms=1000.0)
    service = InspectionService(catalog, settings)

    async def body() -> None:
        await service.inspect(InspectRequest("brightness", Images(GRAY)))  # measured: cheap
        held = asyncio.ensure_future(service.inspect(InspectRequest("gate", Images(GRAY))))
        await wait_until(lambda: gate.entered == 1, "the gate holds the main worker")
        reply = await service.inspect(InspectRequest("brightness", Images(GRAY)))
        assert reply.passed
        assert not held.done()
        gate.release.set()
        assert (await held).passed

    try:
        run(body())
    finally:
        gate.release.set()
        service.close()


def test_an_overlay_is_admitted_by_the_bytes_of_its_reply() -> None:
    """An overlay's reply is as large as a colour copy of the input: it is reserved in the
    byte budget before the inspection runs, BUSY when it does not fit; without an overlay the
    same request runs."""
    image = np.full((600, 800), 200, np.uint8)  # overlay about 1.44 MB
    service = InspectionService(
        Catalog.build(
            [RequestCamera("tool", RequestCameraSettings())],
            [MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
        ),
        ServiceSettings(workers=1, queue_depth=0, max_buffered_bytes=1024 * 1024),
    )

    async def body() -> None:
        with pytest.raises(Busy, match="memory for replies") as refused:
            await service.inspect(InspectRequest("brightness", Images(image), overlay=".png"))
        assert refused.value.details["size"] > 800 * 600 * 3
        assert (await service.inspect(InspectRequest("brightness", Images(image)))).passed
        assert service.budget.used == 0

    try:
        run(body())
    finally:
        service.close()


def test_a_cheap_request_takes_a_free_main_slot_when_the_fast_lane_is_full() -> None:
    pool = pool_with(cheap=1.0, heavy=30.0)
    fast = pool.try_reserve("cheap")
    assert fast is not None
    assert fast.lane is pool.fast
    spill = pool.try_reserve("cheap")  # the fast lane (1 thread, no queue) is full
    assert spill is not None
    assert spill.lane is pool.main
    assert pool.try_reserve("heavy") is None  # and a heavy one never takes the fast lane's
    pool.release(fast)
    assert pool.try_reserve("heavy") is None
    pool.release(spill)
    assert pool.admitted == 0


def test_retry_after_is_never_below_the_floor_while_work_is_ahead() -> None:
    pool = WorkPool(1, 0, fast_workers=0)  # nothing measured yet: costs count as 0 ms
    held = pool.try_reserve("unmeasured")
    assert held is not None
    assert pool.expected_wait_ms("unmeasured") >= 5.0
    pool.release(held)
    assert pool.expected_wait_ms("unmeasured") == 0.0


def _thread_niceness() -> int:
    return os.getpriority(os.PRIO_PROCESS, threading.get_native_id())


@pytest.mark.skipif(sys.platform != "linux", reason="per-thread niceness is Linux's")
def test_the_main_lane_runs_below_the_fast_lane_and_the_event_loop() -> None:
    # A woken event loop or fast-lane thread must preempt a locate, not wait for its turn.
    own = _thread_niceness()
    pool = WorkPool(2, 0, fast_workers=1, main_lane_nice=5)
    try:
        assert pool.fast is not None
        main = {pool.main.executor.submit(_thread_niceness).result() for _ in range(4)}
        fast = pool.fast.executor.submit(_thread_niceness).result()
    finally:
        pool.shutdown()
    assert main == {min(own + 5, 19)}
    assert fast == own
    assert _thread_niceness() == own


def test_a_niceness_out_of_range_is_a_config_error(tmp_path: Path) -> None:
    config = tmp_path / "cell.yaml"
    config.write_text("server: {port: 0, main_lane_nice: 20}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="niceness in 0..19") as refused:
        load_config(config)
    assert "main_lane_nice" in str(refused.value)
    config.write_text("server: {port: 0, main_lane_policy: fifo}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="main_lane_policy"):
        load_config(config)
    config.write_text("server: {port: 0}\n", encoding="utf-8")
    assert load_config(config).server.main_lane_nice == 10
    assert load_config(config).server.main_lane_policy == "nice"
