"""Catalog leases: a retired catalog is released (its owner may free its resources) only after
its last lease, and a request that read a released catalog is sent on to its successor."""

from __future__ import annotations

import threading

import pytest

from vision_server.service import Catalog, CatalogReleased


def empty(config_hash: str) -> Catalog:
    return Catalog.build([], [], config_hash=config_hash)


def test_released_only_after_retired_and_the_last_lease_is_gone() -> None:
    catalog = empty("a")
    released: list[str] = []
    catalog.on_release(lambda: released.append("a"))
    first, second = catalog.acquire(), catalog.acquire()
    assert catalog.leases == 2
    first.release()
    catalog.retire()
    assert catalog.retired
    assert not catalog.released
    assert released == []
    with catalog.acquire():  # a holder may hand work on: still allowed while leased
        second.release()
        assert released == []
    assert catalog.released
    assert released == ["a"]
    assert catalog.leases == 0


def test_releasing_twice_counts_once_and_retire_is_idempotent() -> None:
    catalog = empty("a")
    calls: list[int] = []
    catalog.on_release(lambda: calls.append(1))
    lease = catalog.acquire()
    other = catalog.acquire()
    lease.release()
    lease.release()
    catalog.retire()
    catalog.retire()
    assert calls == []  # ``other`` still holds it
    other.release()
    assert calls == [1]


def test_a_released_catalog_refuses_leases_and_runs_late_callbacks_at_once() -> None:
    catalog = empty("a")
    catalog.retire()
    assert catalog.released
    with pytest.raises(CatalogReleased):
        catalog.acquire()
    late: list[int] = []
    catalog.on_release(lambda: late.append(1))
    assert late == [1]


def test_lease_newest_follows_successors_of_released_catalogs() -> None:
    a, b, c = empty("a"), empty("b"), empty("c")
    held_b = b.acquire()
    a.retire(successor=b)
    b.retire(successor=c)
    assert a.released
    assert not b.released
    with a.lease_newest() as lease:
        assert lease.catalog is b  # retired but alive: the request may still run on it
    held_b.release()
    with a.lease_newest() as lease:
        assert lease.catalog is c
    c.retire()
    with pytest.raises(CatalogReleased):
        a.lease_newest()


def test_a_failing_callback_does_not_stop_the_others() -> None:
    catalog = empty("a")
    ran: list[str] = []

    def broken() -> None:
        raise RuntimeError("boom")

    catalog.on_release(broken)
    catalog.on_release(lambda: ran.append("second"))
    catalog.retire()
    assert ran == ["second"]


def test_leases_from_many_threads_release_exactly_once() -> None:
    catalog = empty("a")
    released: list[int] = []
    catalog.on_release(lambda: released.append(1))
    keep = catalog.acquire()
    catalog.retire()
    start = threading.Barrier(8)

    def churn() -> None:
        start.wait()
        for _ in range(200):
            catalog.acquire().release()

    threads = [threading.Thread(target=churn) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert released == []
    keep.release()
    assert released == [1]
