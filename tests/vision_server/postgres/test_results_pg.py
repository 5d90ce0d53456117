"""The PostgreSQL result log through its store interface, against a real, private cluster.

Parity with the SQLite log (the same entries answer the same queries), restarts, the spool while
the database is down, idempotent forwarding, and migrations from an older schema version.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from loopback import run, wait_until
from postgres import Cluster

from vision_server.results import (
    PgResultLog,
    ResultEntry,
    ResultLog,
    ResultLogError,
    ResultStore,
    StoredResult,
    open_readonly,
)
from vision_server.results.postgres_schema import SCHEMA_VERSION, migrate, schema_version
from vision_server.results.spool import Spool

psycopg = pytest.importorskip(
    "psycopg", reason="psycopg is not installed: pip install -e '.[test]' (extra postgres)"
)

T0 = 1_700_000_000.0


def entry(i: int, **kw: object) -> ResultEntry:
    fields: dict[str, object] = {
        "time": T0 + i * 0.5,
        "inspection": ("gap", "qr")[i % 2],
        "camera": "cam",
        "passed": i % 3 != 0,
        "data": {"value": float(i), "n": np.int64(i), "nan": math.nan},
        "duration_ms": 1.0 + i,
        "config_hash": "abc",
        "request_id": i,
        "peer": f"10.0.0.{i % 4}:5{i:03d}",
    }
    fields.update(kw)
    return ResultEntry(**fields)  # type: ignore[arg-type]


def comparable(row: StoredResult) -> tuple[object, ...]:
    data = {
        k: ("nan" if isinstance(v, float) and math.isnan(v) else v) for k, v in row.data.items()
    }
    return (row.time, row.inspection, row.passed, data, row.duration_ms, row.request_id, row.peer)


@pytest.fixture
def pg_log(pg_url: str, tmp_path: Path) -> Iterator[PgResultLog]:
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=0.05) as log:
        yield log


def test_the_same_entries_answer_the_same_queries_as_sqlite(
    pg_log: PgResultLog, tmp_path: Path
) -> None:
    stores: list[ResultStore] = [pg_log, ResultLog(tmp_path / "r.sqlite3", store_images="none")]
    for store in stores:
        ids = [store.record(entry(i)) for i in range(40)]
        assert all(isinstance(i, int) and i > 0 for i in ids)
    pg, lite = stores
    queries: list[dict[str, object]] = [
        {},
        {"inspection": "gap"},
        {"passed": False, "limit": 5},
        {"since": T0 + 10.0, "newest_first": False},
        {"peer": "10.0.0.1"},
        {"inspection": "qr", "passed": True, "since": T0 + 3},
    ]
    for q in queries:
        assert [comparable(r) for r in pg.query(**q)] == [  # type: ignore[arg-type]
            comparable(r)
            for r in lite.query(**q)  # type: ignore[arg-type]
        ], q
        count_q = {k: v for k, v in q.items() if k in ("since", "inspection", "passed")}
        assert pg.count(**count_q) == lite.count(**count_q)  # type: ignore[arg-type]
    # Keyset paging, newest first, from the 11th row on.
    page = pg.query(limit=10)
    rest = pg.query(limit=100, before_id=page[-1].id)
    assert [comparable(r) for r in page + rest] == [comparable(r) for r in lite.query(limit=100)]
    for got, want in zip(
        pg.timings(inspection="gap", since=T0),
        lite.timings(inspection="gap", since=T0),
        strict=True,
    ):
        np.testing.assert_array_equal(got, want)
    one = pg.query(limit=1)[0]
    got = pg.get(one.id)
    assert got is not None
    assert comparable(got) == comparable(one)
    assert pg.get(10**12) is None
    lite.close()


def test_rows_outlive_the_log_and_a_readonly_view_reads_them(pg_url: str, tmp_path: Path) -> None:
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3") as log:
        row_id = log.record(entry(7, peer="robot\x00arm"))
        assert row_id
        assert log.health()["written"] == 1
    with open_readonly(pg_url) as view:
        rows = view.query()
        assert len(rows) == 1
        assert rows[0].id == row_id
        assert rows[0].peer == "robot\ufffdarm"  # PostgreSQL's text holds no NUL
        with pytest.raises(ResultLogError, match="read-only"):
            view.record(entry(8))


def test_results_are_spooled_while_the_database_is_down_and_forwarded_after(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    spool = tmp_path / "spool.sqlite3"
    with PgResultLog(pg_url, spool=spool, retry_s=0.05, connect_timeout_s=2) as log:
        assert log.record(entry(0)) not in (None, 0)
        pg_cluster.stop_immediate()
        try:
            got = [log.record(entry(i)) for i in range(1, 21)]
            assert got == [0] * 20  # stored (in the spool), id given later
            health = log.health()
            assert health["ok"]
            assert health["spooled"] == 20
            assert not health["database_up"]
            with pytest.raises(ResultLogError, match="cannot read"):
                log.count()
        finally:
            pg_cluster.start()
        run(wait_until(lambda: log.health()["spooled"] == 0, "the spool drains", 60.0), 70.0)
        assert log.health()["database_up"]
        assert log.health()["failed"] == 0
        assert sorted(r.request_id for r in log.query(limit=100)) == list(range(21))
        # Back to direct inserts: an id again.
        assert log.record(entry(21)) not in (None, 0)
    assert Spool(spool).count() == 0


def test_while_the_database_is_down_it_is_tried_once_per_retry_not_once_per_result(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=3600) as log:
        pg_cluster.stop_immediate()
        try:
            assert [log.record(entry(i)) for i in range(50)] == [0] * 50
            # The write that found it down, and the forwarder's first try once woken.
            run(wait_until(lambda: log.errors >= 2, "the forwarder's first try"), 20.0)
            assert [log.record(entry(i)) for i in range(50, 100)] == [0] * 50
            assert log.errors == 2
        finally:
            pg_cluster.start()


def test_workers_recording_at_once_do_not_wait_for_each_others_commit(
    pg_log: PgResultLog, pg_url: str
) -> None:
    """Each recording worker has a connection of its own: with the table locked by another
    client, two records wait in the database side by side (one connection would queue the
    second behind the first in the log itself)."""
    assert pg_log.record(entry(0))
    with psycopg.connect(pg_url) as locker:
        locker.execute("LOCK TABLE results IN EXCLUSIVE MODE")
        threads = [threading.Thread(target=pg_log.record, args=(entry(i),)) for i in (1, 2)]
        for thread in threads:
            thread.start()

        def waiting() -> int:
            with psycopg.connect(pg_url, autocommit=True) as probe:
                return int(
                    probe.execute(
                        "SELECT count(*) FROM pg_stat_activity WHERE application_name = "
                        "'cellvision' AND wait_event_type = 'Lock'"
                    ).fetchone()[0]
                )

        run(wait_until(lambda: waiting() == 2, "two inserts waiting for the lock", 20.0), 30.0)
        locker.rollback()
    for thread in threads:
        thread.join()
    assert pg_log.count() == 3


def test_once_health_says_nothing_is_spooled_rows_go_to_the_database_directly(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=0.05) as log:
        assert log._spool is not None
        # The forwarder's look at the emptied spool is held until the test is done.
        take, gate = log._spool.take, threading.Event()

        def held_take(limit: int) -> list[tuple[str, tuple[object, ...]]]:
            rows = take(limit)
            if not rows:
                gate.wait(30.0)
            return rows

        log._spool.take = held_take  # type: ignore[method-assign]
        try:
            pg_cluster.stop_immediate()
            try:
                assert [log.record(entry(i)) for i in range(3)] == [0, 0, 0]
            finally:
                pg_cluster.start()
            run(wait_until(lambda: log.health()["spooled"] == 0, "the spool drains", 60.0), 70.0)
            assert log.record(entry(3)) not in (None, 0)
        finally:
            gate.set()


def test_a_row_forwarded_twice_is_stored_once(pg_url: str, tmp_path: Path) -> None:
    """The server died after the database committed a spooled row and before the spool dropped
    it: the next start forwards it again, and the row's uid makes that a no-op."""
    path = tmp_path / "spool.sqlite3"
    with PgResultLog(pg_url, spool=path, retry_s=0.05) as log:
        assert log.record(entry(1))
    spool = Spool(path)
    with psycopg.connect(pg_url) as conn:
        uid, cell = conn.execute("SELECT uid, cell FROM results").fetchone()
        values = conn.execute(
            "SELECT time, inspection, camera, passed, data, duration_ms, config_hash, "
            "request_id, peer, error FROM results"
        ).fetchone()
    spool.add(uid, (*values, uid, cell))
    spool.add("f" * 32, (*values[:7], 2, *values[8:], "f" * 32, cell))
    spool.close()
    with PgResultLog(pg_url, spool=path, retry_s=0.05) as log:
        run(wait_until(lambda: log.health()["spooled"] == 0, "the spool drains", 60.0), 70.0)
        assert sorted(r.request_id for r in log.query()) == [1, 2]


def test_a_spooled_row_the_database_refuses_is_dropped_not_blocking_the_rest(
    pg_url: str, tmp_path: Path
) -> None:
    path = tmp_path / "spool.sqlite3"
    with PgResultLog(pg_url, spool=path, retry_s=0.05):
        pass  # creates the schema
    spool = Spool(path)
    values = (T0, "gap", "cam", True, "{}", 1.0, "h", 0, "peer", None)
    for request_id, peer in enumerate(("a", "nul\x00in text", "b")):
        uid = f"{request_id:032x}"
        spool.add(uid, (*values[:7], request_id, peer, None, uid, "cell"))
    spool.close()
    with PgResultLog(pg_url, spool=path, retry_s=0.05) as log:
        run(wait_until(lambda: log.health()["spooled"] == 0, "the spool drains", 60.0), 70.0)
        assert sorted(r.peer for r in log.query()) == ["a", "b"]
        health = log.health()
        assert health["failed"] == 1
        assert not health["ok"]
        assert "refuses spooled result 00000000000000000000000000000001" in health["last_error"]


def test_a_database_down_at_start_spools_and_migrates_once_it_is_back(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    pg_cluster.stop_immediate()
    try:
        log = PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=0.05)
        assert log.record(entry(3)) == 0
        assert "connection failed" in (log.health()["last_error"] or "")
    finally:
        pg_cluster.start()
    with log:
        run(wait_until(lambda: log.health()["spooled"] == 0, "the spool drains", 60.0), 70.0)
        assert [r.request_id for r in log.query()] == [3]


def test_a_database_down_at_start_is_reached_once_back_even_with_nothing_to_forward(
    pg_cluster: Cluster, pg_url: str, tmp_path: Path
) -> None:
    pg_cluster.stop_immediate()
    try:
        log = PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3", retry_s=0.05)
        assert not log.health()["database_up"]
    finally:
        pg_cluster.start()
    with log:
        run(wait_until(lambda: log.health()["database_up"], "the database is reached", 60.0), 70.0)
        with psycopg.connect(pg_url) as conn:
            assert schema_version(conn) == SCHEMA_VERSION  # created without a result to write
        assert log.record(entry(1)) not in (None, 0)  # straight to the database


def test_an_older_schema_is_upgraded_and_its_rows_kept(pg_url: str, tmp_path: Path) -> None:
    with psycopg.connect(pg_url, autocommit=True) as conn:
        migrate(conn, "test", target=1)
        assert schema_version(conn) == 1
        conn.execute(
            "INSERT INTO results (time, inspection, camera, passed, data, duration_ms, "
            "config_hash, request_id, peer) VALUES (%s, 'old', 'cam', true, '{\"v\":1}', 2.0, "
            "'h', 5, 'p')",
            (T0,),
        )
    with PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3") as log:
        assert log.record(entry(9))
        assert [r.inspection for r in log.query(newest_first=False)] == ["old", "qr"]
        assert log.query(inspection="old")[0].data == {"v": 1}
    with psycopg.connect(pg_url) as conn:
        assert schema_version(conn) == SCHEMA_VERSION == 3


def test_cells_starting_at_once_on_a_new_database_migrate_it_once(
    pg_url: str, tmp_path: Path
) -> None:
    logs: list[PgResultLog] = []
    errors: list[BaseException] = []

    def open_one(i: int) -> None:
        try:
            logs.append(PgResultLog(pg_url, spool=tmp_path / f"spool{i}.sqlite3"))
        except BaseException as exc:
            errors.append(exc)

    threads = [threading.Thread(target=open_one, args=(i,)) for i in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    try:
        assert errors == []
        assert all(log.record(entry(i)) for i, log in enumerate(logs))
        assert logs[0].count() == 4
    finally:
        for log in logs:
            log.close()


def test_a_newer_schema_or_a_foreign_table_is_refused(pg_url: str, tmp_path: Path) -> None:
    with psycopg.connect(pg_url, autocommit=True) as conn:
        conn.execute("CREATE TABLE results (x int)")
    with pytest.raises(ResultLogError, match="not a cellvision result log"):
        PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3")
    with psycopg.connect(pg_url, autocommit=True) as conn:
        conn.execute("DROP TABLE results")
        migrate(conn, "test")
        conn.execute("UPDATE schema_version SET version = %s", (SCHEMA_VERSION + 1,))
    with pytest.raises(ResultLogError, match="newer than this cellvision"):
        PgResultLog(pg_url, spool=tmp_path / "spool.sqlite3")


def test_a_readonly_view_of_an_empty_database_says_to_start_the_server(pg_url: str) -> None:
    with pytest.raises(ResultLogError, match="start the server on it once"):
        open_readonly(pg_url)
