"""The statistics' cache of the result log (vision_server/results/timings_cache.py) gives, row
for row, what the log itself gives, while rows are written between asks (some with earlier
times, as a spool sends them late), windows move, widen and narrow, and tries come in; and it
holds no more rows than its bound."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from vision_server.results import TRY_PEER_PREFIX, ResultEntry, ResultLog, TimingsCache

T0 = 1_760_000_000.0


def _write(log: ResultLog, rng: np.random.Generator, n: int, start: float) -> None:
    for _ in range(n):
        late = rng.random() < 0.1  # written now, stamped up to 10 minutes earlier
        log.record(
            ResultEntry(
                time=start + float(rng.uniform(-600.0, 0.0) if late else rng.uniform(0, 60)),
                inspection=str(rng.choice(["a", "b"])),
                camera="qc",
                passed=bool(rng.random() < 0.9),
                data={},
                duration_ms=float(rng.gamma(2.0, 2.0)),
                config_hash="h",
                peer=TRY_PEER_PREFIX + "1.2.3.4:5" if rng.random() < 0.05 else "10.0.0.7:1",
            )
        )


def _same(cache: TimingsCache, log: ResultLog, inspection: str, since: float) -> int:
    got = cache.timings(inspection=inspection, since=since)
    want = log.timings(inspection=inspection, since=since)

    # Rows of one time may come in another order: compare as sorted triples.
    def rows(t: tuple[np.ndarray, np.ndarray, np.ndarray]) -> list[tuple[float, bool, float]]:
        return sorted(zip(t[0].tolist(), t[1].tolist(), t[2].tolist(), strict=True))

    assert rows(got) == rows(want)
    assert np.all(np.diff(got[0]) >= 0), "oldest first"
    return len(got[0])


def test_the_cache_answers_what_the_log_answers_as_rows_come(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    with ResultLog(tmp_path / "log.sqlite3", store_images="none") as log:
        cache = TimingsCache(log)
        now = T0
        _write(log, rng, 300, now)
        seen = 0
        for step in range(40):
            now += 60.0
            _write(log, rng, int(rng.integers(0, 30)), now)
            window = float(rng.choice([600.0, 1800.0, 3600.0, 7200.0]))
            for inspection in ("a", "b", "never"):
                seen += _same(cache, log, inspection, now - window)
            if step % 7 == 0:  # the same window asked twice with nothing new
                _same(cache, log, "a", now - window)
        assert seen > 1000


def test_the_cache_holds_at_most_its_bound(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    with ResultLog(tmp_path / "log.sqlite3", store_images="none") as log:
        _write(log, rng, 400, T0)
        cache = TimingsCache(log, max_rows=150)
        for _ in range(3):
            _same(cache, log, "a", T0 - 1000)
            _same(cache, log, "b", T0 - 1000)
            assert sum(w.size for w in cache._windows.values()) <= 150


@pytest.mark.parametrize("since", [T0 + 10, T0 + 1e9])
def test_an_empty_window_is_empty(tmp_path: Path, since: float) -> None:
    with ResultLog(tmp_path / "log.sqlite3", store_images="none") as log:
        _write(log, np.random.default_rng(5), 20, T0)
        cache = TimingsCache(log)
        for _ in range(2):
            times, passed, durations = cache.timings(inspection="a", since=since)
            assert (
                len(times)
                == len(passed)
                == len(durations)
                == len(log.timings(inspection="a", since=since)[0])
            )
