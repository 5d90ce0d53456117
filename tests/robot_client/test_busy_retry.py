"""The client honours BUSY: ``busy_timeout_s`` sends a refused INSPECT again after the server's
``retry_after_ms`` hint (or a jittered back-off) until the timeout, then raises the last BUSY.

A real server with one slot (workers=1, queue_depth=0) whose slot a gated inspection holds:
every other INSPECT is BUSY (admission_wait_s 0: no waiting unread) until the test opens the
gate. Verdicts are counts of retries and the answers, never durations. The server's own hint
(``retry_after_ms`` in BUSY's details, SPEC §6.1) is replaced by the test's to control it.
"""

from __future__ import annotations

import asyncio
import random
from collections.abc import Iterator

import numpy as np
import pytest
from loopback import Gate, client_for, run, server_in_thread, wait_until

from protocol import Busy
from robot_client import SyncVisionClient, VisionClient
from robot_client.client import BUSY_BACKOFF_INITIAL_S, busy_wait_s
from vision_server import Catalog
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.server import VisionServer
from vision_server.service.builtin import MeanIntensityPresence

IMAGE = np.full((48, 64), 200, np.uint8)


@pytest.fixture
def gate() -> Iterator[Gate]:
    g = Gate()
    yield g
    g.release.set()


@pytest.fixture
def one_slot(gate: Gate) -> Iterator[VisionServer]:
    catalog = Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [gate, MeanIntensityPresence("brightness", "tool", 64.0, 255.0)],
    )
    with server_in_thread(
        catalog, workers=1, queue_depth=0, fast_workers=0, admission_wait_s=0.0
    ) as server:
        yield server


def hint_busy(server: VisionServer, retry_after_ms: int | None) -> None:
    """Make the server's BUSY carry ``retry_after_ms`` (None: no hint at all)."""
    service = server.service
    busy = service._busy

    def busy_with_hint(key: str | None, *, waited: bool = False) -> Busy:
        exc = busy(key, waited=waited)
        if retry_after_ms is None:
            exc.details.pop("retry_after_ms", None)
        else:
            exc.details["retry_after_ms"] = retry_after_ms
        return exc

    service._busy = busy_with_hint  # type: ignore[method-assign]


async def _hold_the_slot(server: VisionServer, gate: Gate) -> tuple[VisionClient, asyncio.Task]:
    holder = client_for(server, request_timeout_s=30.0)
    await holder.connect()
    task = asyncio.ensure_future(holder.inspect("gate", IMAGE))
    await wait_until(lambda: gate.entered == 1, "the gate holds the only slot")
    return holder, task


def test_without_busy_timeout_busy_is_raised_at_once(one_slot: VisionServer, gate: Gate) -> None:
    async def body() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        async with client_for(one_slot) as client:
            with pytest.raises(Busy):
                await client.inspect("brightness", IMAGE)
            assert client.busy_retries == 0
        gate.release.set()
        await held
        await holder.close()

    run(body())


def test_busy_with_a_hint_is_sent_again_until_the_slot_frees(
    one_slot: VisionServer, gate: Gate
) -> None:
    hint_busy(one_slot, retry_after_ms=20)

    async def body() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        async with client_for(one_slot, busy_timeout_s=60.0) as client:
            asking = asyncio.ensure_future(client.inspect("brightness", IMAGE))
            await wait_until(lambda: client.busy_retries >= 2, "two retries", 30.0)
            assert not asking.done()
            gate.release.set()
            result = await asking
            assert result.passed
            assert client.busy_retries >= 2
        await held
        await holder.close()

    run(body(), timeout_s=60.0)


def test_a_hint_beyond_busy_timeout_raises_without_retrying(
    one_slot: VisionServer, gate: Gate
) -> None:
    """The hint decides the wait: a slot expected in 60 s is not waited for within 5 s (the
    back-off alone would have retried many times)."""
    hint_busy(one_slot, retry_after_ms=60_000)

    async def body() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        async with client_for(one_slot, busy_timeout_s=5.0) as client:
            with pytest.raises(Busy) as refused:
                await client.inspect("brightness", IMAGE)
            assert refused.value.details["retry_after_ms"] == 60_000
            assert client.busy_retries == 0
        gate.release.set()
        await held
        await holder.close()

    run(body())


def test_busy_without_a_hint_backs_off_and_succeeds(one_slot: VisionServer, gate: Gate) -> None:
    hint_busy(one_slot, None)

    async def body() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        async with client_for(one_slot, busy_timeout_s=60.0) as client:
            asking = asyncio.ensure_future(client.inspect("brightness", IMAGE))
            await wait_until(lambda: client.busy_retries >= 3, "three retries", 30.0)
            gate.release.set()
            assert (await asking).passed
        await held
        await holder.close()

    run(body(), timeout_s=60.0)


def test_busy_timeout_exhausted_raises_the_last_busy(one_slot: VisionServer, gate: Gate) -> None:
    async def body() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        async with client_for(one_slot, busy_timeout_s=2.0) as client:
            with pytest.raises(Busy) as refused:
                await client.inspect("brightness", IMAGE)
            assert not refused.value.fatal
            assert client.busy_retries >= 1
        gate.release.set()
        await held
        await holder.close()

    run(body(), timeout_s=60.0)


def test_the_sync_client_retries_busy_too(one_slot: VisionServer, gate: Gate) -> None:
    async def hold() -> None:
        holder, held = await _hold_the_slot(one_slot, gate)
        with SyncVisionClient(
            "127.0.0.1", one_slot.port, busy_timeout_s=2.0, request_timeout_s=10.0
        ) as client:
            with pytest.raises(Busy):
                await asyncio.to_thread(client.inspect, "brightness", IMAGE)
            assert client.busy_retries >= 1
        gate.release.set()
        await held
        await holder.close()

    run(hold(), timeout_s=60.0)


@pytest.mark.parametrize("seed", range(5))
def test_the_wait_follows_the_hint_or_the_back_off_within_the_jitter(seed: int) -> None:
    rng = random.Random(seed)
    hinted = Busy("busy", details={"retry_after_ms": 250})
    assert 0.2 <= busy_wait_s(hinted, BUSY_BACKOFF_INITIAL_S, rng) <= 0.3
    bare = Busy("busy")
    assert 0.004 <= busy_wait_s(bare, 0.005, rng) <= 0.006
    assert 0.16 <= busy_wait_s(bare, 0.2, rng) <= 0.24
    for junk in ("soon", -5, True, float("nan"), None):
        odd = Busy("busy", details={"retry_after_ms": junk})
        assert 0.004 <= busy_wait_s(odd, 0.005, rng) <= 0.006
