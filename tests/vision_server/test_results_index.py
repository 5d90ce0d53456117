"""The result log's queries for the console: every filter is served by an index (checked with
``EXPLAIN QUERY PLAN``, not by timing), paging follows the order shown, and the statistics read
their three columns from a covering index."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vision_server.frontends.http import stats_of
from vision_server.results import ResultEntry, ResultLog

T0 = 1_700_000_000.0


def entry(n: int, *, t: float, inspection: str, passed: bool, peer: str) -> ResultEntry:
    return ResultEntry(
        time=t,
        inspection=inspection,
        camera="qc",
        passed=passed,
        data={"n": n},
        duration_ms=float(n % 10),
        config_hash="abc",
        request_id=n,
        peer=peer,
    )


@pytest.fixture
def log(tmp_path: Path) -> Iterator[ResultLog]:
    with ResultLog(tmp_path / "results.db", store_images="none") as opened:
        for n in range(40):
            opened.record(
                entry(
                    n,
                    t=T0 + n,
                    inspection=("magnet_check", "cap_locate")[n % 2],
                    passed=n % 3 != 0,
                    peer=f"10.0.0.{n % 4}:4000{n % 5}",
                )
            )
        yield opened


def plan(log: ResultLog, **filters: Any) -> str:
    sql, params = log.query_sql(limit=51, **filters)
    return "\n".join(row[3] for row in log._conn.execute("EXPLAIN QUERY PLAN " + sql, params))


@pytest.mark.parametrize(
    ("filters", "index"),
    [
        ({}, "results_by_time"),
        ({"since": T0 + 5}, "results_by_time"),
        ({"inspection": "magnet_check"}, "results_by_inspection"),
        ({"inspection": "magnet_check", "since": T0 + 5}, "results_by_inspection"),
        ({"passed": False}, "results_by_verdict"),
        ({"passed": False, "since": T0 + 5}, "results_by_verdict"),
        ({"inspection": "magnet_check", "passed": False}, "results_by_inspection_verdict"),
        ({"peer": "10.0.0.1"}, "results_by_peer"),
        ({"before_id": 20}, "results_by_time"),
        ({"inspection": "cap_locate", "before_id": 20}, "results_by_inspection"),
    ],
)
def test_every_console_filter_reads_through_an_index(
    log: ResultLog, filters: dict[str, Any], index: str
) -> None:
    text = plan(log, **filters)
    main = text.splitlines()[0]
    assert f"USING INDEX {index} " in main + " " or f"COVERING INDEX {index} " in main + " ", text
    # Never the whole table: a SCAN without an index reads every row of a 100k-row log.
    assert not any(
        line.startswith("SCAN results") and "INDEX" not in line for line in text.splitlines()
    ), text
    # Filtered by an equality, the rows come in time order: no sort of all matches.
    if "peer" not in filters:
        assert "TEMP B-TREE FOR ORDER BY" not in text, text


def test_the_statistics_read_a_covering_index(log: ResultLog) -> None:
    sql = "SELECT time, passed, duration_ms FROM results WHERE time >= ? AND inspection = ?"
    text = "\n".join(r[3] for r in log._conn.execute("EXPLAIN QUERY PLAN " + sql, (T0, "x")))
    assert "COVERING INDEX results_by_inspection" in text


def test_paging_follows_time_order_when_ids_do_not(tmp_path: Path) -> None:
    # Workers finish out of order: a later id can carry an earlier time (stamped at the start).
    times = [T0 + t for t in (0, 5, 1, 6, 2, 7, 3, 8, 4, 9)]
    with ResultLog(tmp_path / "results.db", store_images="none") as log:
        for n, t in enumerate(times):
            log.record(entry(n, t=t, inspection="magnet_check", passed=True, peer="a:1"))
        seen: list[int] = []
        before: int | None = None
        while True:
            page = log.query(limit=3, before_id=before)
            if not page:
                break
            seen += [r.request_id for r in page]
            before = page[-1].id
        by_time = sorted(range(len(times)), key=lambda n: times[n], reverse=True)
        assert seen == by_time
        oldest_first = log.query(limit=3, newest_first=False, before_id=log.query(limit=1)[0].id)
        assert oldest_first == []


def test_a_peer_prefix_is_a_prefix_not_a_pattern(tmp_path: Path) -> None:
    with ResultLog(tmp_path / "results.db", store_images="none") as log:
        for n, peer in enumerate(["10.0.0.1:5", "10.0.0.10:5", "10.0.0.2:5", "a_b:1", "axb:1"]):
            log.record(entry(n, t=T0 + n, inspection="m", passed=True, peer=peer))
        assert {r.peer for r in log.query(peer="10.0.0.1")} == {"10.0.0.1:5", "10.0.0.10:5"}
        assert {r.peer for r in log.query(peer="10.0.0.1:")} == {"10.0.0.1:5"}
        assert {r.peer for r in log.query(peer="a_")} == {"a_b:1"}
        assert {r.peer for r in log.query(peer="\U0010ffff")} == set()


def test_timings_and_stats_of_a_window(log: ResultLog) -> None:
    times, passed, durations = log.timings(inspection="magnet_check", since=T0 + 10)
    assert list(times) == [T0 + n for n in range(10, 40, 2)]
    assert list(passed) == [n % 3 != 0 for n in range(10, 40, 2)]
    assert list(durations) == [float(n % 10) for n in range(10, 40, 2)]
    stats = stats_of(log, "magnet_check", now=T0 + 40, window=240.0)
    assert stats["count"] == 20
    assert stats["pass"] == sum(1 for n in range(0, 40, 2) if n % 3 != 0)
    assert stats["fail"] == 20 - stats["pass"]
    assert stats["p50_ms"] == pytest.approx(np.percentile([n % 10 for n in range(0, 40, 2)], 50))
    assert len(stats["series"]) == 24
    assert sum(b["count"] for b in stats["series"]) == 20
    assert stats["series"][0]["count"] == 0  # 240 s before "now": nothing yet
    assert stats["series"][0]["pass_rate"] is None
    empty = stats_of(log, "nothing", now=T0 + 40, window=240.0)
    assert empty["count"] == 0
    assert empty["pass_rate"] is None
