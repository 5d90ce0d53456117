"""The online board: what the console's online view shows of each inspection, kept in memory.

Fed by the service's observers (as ``cellvision_inspections_total`` is counted, console tries
left out): for each inspection, its pass and fail counts since the server started or the last
reset, the last :data:`STRIP_LENGTH` verdicts (with the result log's id of each, when it kept
one, and the time) and its last production result (time, verdict, image size, data), from
which :func:`~vision_server.inspections.result_shapes` draws its graphics when the board is
read. The board never reads the result log: reading it costs the same with 100,000 stored
results as with none. Its memory is bounded by the configuration's inspections: a fixed-length
strip and one result each; inspections a reload removed are dropped when the board is read.

``sequence`` grows by one with every change (a result, a reset): a reader that has seen it
(the page's ``If-None-Match``) is answered "unchanged" without a snapshot being built.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from ..inspections import Inspection, result_shapes
from ..results import is_try
from ..service import InspectionRecord, InspectionService

STRIP_LENGTH = 30
"""Verdicts each inspection's strip keeps, oldest dropped first."""


@dataclass(frozen=True)
class Verdict:
    """One verdict of the strip: ``time`` Unix seconds; ``result_id`` the log's row (None: not
    stored)."""

    passed: bool
    result_id: int | None
    time: float


@dataclass
class _Last:
    """An inspection's last production result, and the inspection as it ran (with the
    request's options, applied when the board is read)."""

    time: float
    passed: bool
    result_id: int | None
    image_size: tuple[int, int] | None
    data: Mapping[str, Any]
    inspection: Inspection
    options: Mapping[str, Any]
    shapes: list[dict[str, Any]] | None = None
    """Drawn once, when the board is first read after this result."""


@dataclass
class _Tally:
    passes: int = 0
    fails: int = 0
    since: float = field(default_factory=time.time)
    strip: deque[Verdict] = field(default_factory=lambda: deque(maxlen=STRIP_LENGTH))
    last: _Last | None = None


class OnlineBoard:
    """The board of ``service``'s production results; ``close()`` unsubscribes."""

    def __init__(self, service: InspectionService, *, strip_length: int = STRIP_LENGTH) -> None:
        self.service = service
        self.strip_length = strip_length
        self.started_at = time.time()
        self.sequence = 0
        self.epoch = uuid.uuid4().hex[:8]
        """Tells one board's sequence numbers from another's (a restarted server)."""
        self._tallies: dict[str, _Tally] = {}
        # The observer runs on the event loop, a read may run in a worker thread (drawing a
        # result with request options rebuilds the inspection): one lock for both.
        self._lock = threading.Lock()
        self._cache: tuple[str, dict[str, Any]] | None = None
        self._unsubscribe: Callable[[], None] = service.subscribe(self._on_result)

    # ------------------------------------------------------------------ feeding

    def _on_result(self, record: InspectionRecord) -> None:
        request, reply = record.request, record.reply
        if is_try(request.peer) or request.request_class == "try":
            return  # a console try is not production (a tuned option may pass a bad part)
        inspection = self.service.catalog.inspections.get(reply.inspection)
        now = time.time()
        with self._lock:
            tally = self._tallies.get(reply.inspection)
            if tally is None:
                tally = self._tallies[reply.inspection] = _Tally(
                    since=self.started_at, strip=deque(maxlen=self.strip_length)
                )
            if reply.passed:
                tally.passes += 1
            else:
                tally.fails += 1
            tally.strip.append(Verdict(reply.passed, reply.result_id, now))
            if inspection is not None:
                tally.last = _Last(
                    now,
                    reply.passed,
                    reply.result_id,
                    reply.image_size,
                    reply.data,
                    inspection,
                    dict(request.options),
                )
            self.sequence += 1

    def reset(self, inspection: str | None = None) -> list[str]:
        """Zero the counts and clear the strips of ``inspection`` (None: of every one); the
        last result's graphics stay. Returns the names reset."""
        now = time.time()
        with self._lock:
            names = list(self._tallies) if inspection is None else [inspection]
            for name in names:
                old = self._tallies.get(name)
                fresh = _Tally(since=now, strip=deque(maxlen=self.strip_length))
                if old is not None:
                    fresh.last = old.last
                self._tallies[name] = fresh
            if inspection is None:
                self.started_at = now  # inspections with no result yet count from now too
            self.sequence += 1
        return names

    def close(self) -> None:
        self._unsubscribe()

    # ------------------------------------------------------------------ reading

    def etag(self) -> str:
        """Changes whenever the snapshot would: a result, a reset, a reload."""
        return f'"{self.epoch}-{self.sequence}-{self.service.catalog.config_hash}"'

    def snapshot(self) -> tuple[str, dict[str, Any]]:
        """``(etag, board)``: per camera, its inspections with counts, strip and last result
        (docs/console.md, ``GET /api/online``). Built once per change."""
        with self._lock:
            tag = self.etag()
            if self._cache is not None and self._cache[0] == tag:
                return self._cache
            undrawn = [
                t.last
                for t in self._tallies.values()
                if t.last is not None and t.last.shapes is None
            ]
        # Drawing (it may rebuild an inspection with a request's options) outside the lock:
        # the observer that takes the lock runs on the event loop, for every result.
        for last in undrawn:
            last.shapes = self._shapes(last)
        with self._lock:
            tag = self.etag()
            catalog = self.service.catalog
            for gone in [name for name in self._tallies if name not in catalog.inspections]:
                del self._tallies[gone]
            cameras: dict[str, list[dict[str, Any]]] = {name: [] for name in catalog.cameras}
            for name, inspection in catalog.inspections.items():
                tally = self._tallies.get(name) or _Tally(since=self.started_at)
                entry = self._entry(name, inspection.type, tally)
                cameras.setdefault(inspection.camera, []).append(entry)
            board = {
                "sequence": self.sequence,
                "strip_length": self.strip_length,
                "cameras": [
                    {"name": camera, "inspections": entries} for camera, entries in cameras.items()
                ],
            }
            drawn = all(t.last is None or t.last.shapes is not None for t in self._tallies.values())
            if not drawn:  # a result came meanwhile: shown without shapes, drawn next time
                return tag[:-1] + '-undrawn"', board
            self._cache = (tag, board)
            return self._cache

    def _entry(self, name: str, kind: str, tally: _Tally) -> dict[str, Any]:
        total = tally.passes + tally.fails
        last = tally.last
        return {
            "name": name,
            "type": kind,
            "pass": tally.passes,
            "fail": tally.fails,
            "total": total,
            "yield": None if total == 0 else round(tally.passes / total, 4),
            "since": tally.since,
            "strip": [
                {"passed": v.passed, "result_id": v.result_id, "time": v.time} for v in tally.strip
            ],
            "last": None if last is None else self._last_json(last),
        }

    def _last_json(self, last: _Last) -> dict[str, Any]:
        return {
            "time": last.time,
            "passed": last.passed,
            "result_id": last.result_id,
            "image_size": None if last.image_size is None else list(last.image_size),
            "summary": summary(last.data),
            "shapes": last.shapes or [],
        }

    def _shapes(self, last: _Last) -> list[dict[str, Any]]:
        inspection = last.inspection
        if last.options:
            # The ROI and values the request ran with, as the run used them (a reload may have
            # changed what the options fit: then the configuration's).
            with contextlib.suppress(Exception):
                inspection = self.service.catalog.tuned(inspection, last.options)
        return result_shapes(inspection, last.data, last.passed)


SUMMARY_KEYS = ("text", "value", "count", "reason")
"""What a verdict's line says of a result, the first of these its data has."""


def summary(data: Mapping[str, Any]) -> str:
    """A short line for the verdict box: for a job the steps that failed; else the decoded
    text, the measured value, the count found, or the reason it failed (at most 60
    characters)."""
    steps, failed = data.get("steps"), data.get("failed")
    if isinstance(steps, dict) and isinstance(failed, list):
        if not failed:
            return f"{len(steps)} steps passed"
        text = "failed: " + ", ".join(str(f) for f in failed)
        return text if len(text) <= 60 else text[:59] + "…"
    for key in SUMMARY_KEYS:
        value = data.get(key)
        if value is None or isinstance(value, dict | list):
            continue
        if isinstance(value, float):
            if not math.isfinite(value):
                continue
            value = f"{value:.3f}"
        prefix = f"{data['measure']} = " if key == "value" and "measure" in data else ""
        text = f"{prefix}{key} {value}" if key == "count" else f"{prefix}{value}"
        return text if len(text) <= 60 else text[:59] + "…"
    return ""


__all__ = ["STRIP_LENGTH", "OnlineBoard", "Verdict", "summary"]
