"""Statistics' columns of the result log, read once and then only what was written since.

The console's statistics (``GET /api/stats``: count, pass rate, p50/p99 per inspection over a
window) are made of every production row in the window: 100,000 rows a day on a busy cell.
Reading them all for every page open cost 50 ms on a quiet machine and 200 ms on a loaded one,
most of it building the rows in Python. :class:`TimingsCache` keeps, per inspection, the
columns of the window it was last asked for, and on the next ask reads only the rows written
after the last one it holds (a range of the primary key, :meth:`ResultStore.timing_rows`),
appends them and drops what left the window. The log is append-only (rows are never deleted
or changed in these columns) and, where the cache is used, gives ids in the order rows commit
(``ResultStore.ids_in_commit_order``: SQLite's one writer, not PostgreSQL's sequence shared by
many cells), so the answer is the log's, row for row.

Bounded: at most ``max_rows`` rows are held over all inspections; an inspection whose window
holds more is read from the log each time, as before. A wider window than the one held is read
whole once.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from .store import ResultStore

MAX_ROWS = 2_000_000
"""Rows held over all inspections (about 25 bytes each: 50 MB at most)."""


@dataclass
class _Window:
    """One inspection's rows with ``time >= since``, by time, up to row ``upto``."""

    since: float
    upto: int
    times: np.ndarray
    passed: np.ndarray
    durations: np.ndarray

    @property
    def size(self) -> int:
        return len(self.times)


class TimingsCache:
    """:meth:`ResultStore.timings` of ``log``, read incrementally (see the module)."""

    def __init__(self, log: ResultStore, *, max_rows: int = MAX_ROWS) -> None:
        self.log = log
        self.max_rows = max_rows
        self._windows: dict[str, _Window] = {}
        self._lock = threading.Lock()

    def timings(
        self, *, inspection: str, since: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As :meth:`ResultStore.timings`: time (Unix seconds), verdict and duration (ms) of
        every production result of ``inspection`` with ``time >= since``, oldest first."""
        with self._lock:
            window = self._windows.get(inspection)
            if window is None or since < window.since:
                window = self._read_whole(inspection, since)
            else:
                window = self._catch_up(inspection, window, since)
            held = sum(w.size for name, w in self._windows.items() if name != inspection)
            if held + window.size <= self.max_rows:
                self._windows[inspection] = window
            else:
                self._windows.pop(inspection, None)
            return window.times, window.passed, window.durations

    def _read_whole(self, inspection: str, since: float) -> _Window:
        rows = self.log.timing_rows(inspection=inspection, since=since)
        return _Window(since, rows.upto, rows.times, rows.passed, rows.durations)

    def _catch_up(self, inspection: str, window: _Window, since: float) -> _Window:
        new = self.log.timing_rows(inspection=inspection, after_id=window.upto)
        keep = new.times >= since
        times = np.concatenate([window.times, new.times[keep]])
        passed = np.concatenate([window.passed, new.passed[keep]])
        durations = np.concatenate([window.durations, new.durations[keep]])
        if keep.any() and np.any(np.diff(times[window.size - 1 if window.size else 0 :]) < 0):
            # The new rows come by id: one written late with an earlier time (a spool sent
            # on, a try's clock) puts them out of time order. By time again.
            order = np.argsort(times, kind="stable")
            times, passed, durations = times[order], passed[order], durations[order]
        first = int(np.searchsorted(times, since, side="left"))
        return _Window(
            since,
            max(new.upto, window.upto),
            times[first:],
            passed[first:],
            durations[first:],
        )


__all__ = ["MAX_ROWS", "TimingsCache"]
