"""The manual clock the camera tests drive: it stands still, counts waiters, and wakes them."""

from __future__ import annotations

import threading
import time

import pytest

from vision_server.cameras import SYSTEM_CLOCK, ManualClock


def test_time_moves_only_when_advanced() -> None:
    clock = ManualClock(10.0, epoch_s=1000.0)
    assert (clock.monotonic(), clock.time()) == (10.0, 1000.0)
    clock.advance(0.25)
    assert (clock.monotonic(), clock.time()) == (10.25, 1000.25)
    with pytest.raises(ValueError, match="only moves forward"):
        clock.advance(-1.0)


def test_a_waiter_wakes_when_the_clock_reaches_its_deadline() -> None:
    clock = ManualClock(0.0)
    cond = threading.Condition()
    woke_at: list[float] = []

    def waiter() -> None:
        with cond:
            while clock.monotonic() < 1.0:
                clock.wait_until(cond, 1.0)
            woke_at.append(clock.monotonic())

    thread = threading.Thread(target=waiter)
    thread.start()
    deadline = time.monotonic() + 30.0
    while clock.waiters != 1:
        assert time.monotonic() < deadline, "the waiter never waited"
        time.sleep(0.001)
    clock.advance(0.5)
    assert woke_at == []
    clock.advance(0.5)
    thread.join(30.0)
    assert woke_at == [1.0]
    assert clock.waiters == 0


def test_a_passed_deadline_returns_at_once() -> None:
    clock = ManualClock(5.0)
    cond = threading.Condition()
    with cond:
        clock.wait_until(cond, 5.0)  # would block until an advance otherwise
    assert clock.waiters == 0


def test_the_system_clock_is_the_real_time() -> None:
    before = time.time()
    assert SYSTEM_CLOCK.time() >= before
    cond = threading.Condition()
    with cond:
        SYSTEM_CLOCK.wait_until(cond, SYSTEM_CLOCK.monotonic() - 1.0)  # passed: returns
