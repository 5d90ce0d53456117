"""An inspection's newest production rows, a page at a time (vision_server/results/scan.py):
newest first, tries and other inspections left out, and never more rows read than allowed."""

from __future__ import annotations

import itertools
from pathlib import Path

from vision_server.results import TRY_PEER_PREFIX, ProductionRows, ResultEntry, ResultLog


def _fill(log: ResultLog) -> list[int]:
    """60 rows of 'a', every third a console try, between rows of 'b'; the ids of a's
    production rows, newest first."""
    kept = []
    for i in range(60):
        peer = TRY_PEER_PREFIX + "127.0.0.1:1" if i % 3 == 0 else "10.0.0.7:1"
        entry = ResultEntry(1000.0 + i, "a", "qc", True, {}, 1.0, "h", peer=peer)
        row = log.record(entry)
        log.record(ResultEntry(1000.0 + i, "b", "qc", True, {}, 1.0, "h"))
        if i % 3:
            assert row is not None
            kept.append(row)
    return kept[::-1]


def test_rows_come_newest_first_without_tries_across_pages(tmp_path: Path) -> None:
    with ResultLog(tmp_path / "log.sqlite3", store_images="none") as log:
        kept = _fill(log)
        rows = ProductionRows(log, "a", page_rows=7, max_examined=1000)
        assert [r.id for r in rows] == kept
        assert not rows.limited
        assert rows.examined == 60


def test_the_walk_stops_at_its_bound_and_says_so(tmp_path: Path) -> None:
    with ResultLog(tmp_path / "log.sqlite3", store_images="none") as log:
        kept = _fill(log)
        rows = ProductionRows(log, "a", page_rows=7, max_examined=30)
        assert [r.id for r in rows] == kept[:20]  # 30 rows read, a third of them tries
        assert rows.limited
        assert rows.examined == 30
        first = ProductionRows(log, "a", page_rows=5, max_examined=1000)
        assert [r.id for r in itertools.islice(first, 3)] == kept[:3]
        assert first.examined == 5  # one page read for the three asked
