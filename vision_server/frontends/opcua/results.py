"""The results an OPC UA client can read back (OPC 40100-1 §7.10, ResultManagementType): each
job's result, kept by its ResultId in a bounded ring, newest last.

A result is kept while it is among the last ``kept`` (``opcua: results_kept``); an older id
answers "not found" (the result log still has the row: its ``result_id`` is in the content).
Plain records only: :mod:`.model` turns them into the nodeset's ResultDataType.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

RESULT_UNDEFINED = 0
RESULT_COMPLETED = 1
"""ResultStateDataType (§12.19): processing was carried out (the verdict is in the content)."""
RESULT_PROCESSING = 2
RESULT_ABORTED = 3
RESULT_FAILED = 4
"""Processing failed: the content names the error (cellvision's error code and message)."""


@dataclass(frozen=True)
class JobResult:
    """One job's result. Times are UTC datetimes; durations milliseconds."""

    result_id: str
    job_id: str
    recipe: str
    """The inspection the job ran (the recipe's id)."""
    config_hash: str
    """The configuration served when it ran: the recipe's and the configuration's version."""
    state: int
    """ResultStateDataType: :data:`RESULT_COMPLETED`, :data:`RESULT_ABORTED` or
    :data:`RESULT_FAILED`."""
    started: datetime
    ended: datetime
    meas_id: str = ""
    part_id: str = ""
    product_id: str = ""
    passed: bool = False
    data: dict[str, Any] = field(default_factory=dict)
    camera: str = ""
    error_code: str = ""
    error_message: str = ""
    compute_ms: float = 0.0
    log_id: int | None = None
    """The result log's row id (RESULT ``result_id`` of the binary protocol), when it gave one."""

    @property
    def processing_ms(self) -> float:
        return (self.ended - self.started).total_seconds() * 1000.0

    def content(self) -> dict[str, Any]:
        """The result's content as cellvision defines it (docs/opcua.md "Results"): the verdict,
        the inspection's data (SPEC §6.3) and, for a failed job, the error."""
        body: dict[str, Any] = {
            "inspection": self.recipe,
            "camera": self.camera,
            "passed": self.passed,
            "data": self.data,
            "config_hash": self.config_hash,
            "compute_ms": round(self.compute_ms, 3),
            "result_log_id": self.log_id,
        }
        if self.error_code:
            body["error"] = {"code": self.error_code, "message": self.error_message}
        return body

    def content_json(self) -> str:
        return json.dumps(self.content(), separators=(",", ":"), allow_nan=False, default=str)


@dataclass
class ResultFilter:
    """GetResultListFiltered's criteria; an empty text (or None) matches anything."""

    state: int = RESULT_UNDEFINED
    """0: any state."""
    meas_id: str = ""
    part_id: str = ""
    recipe: str = ""
    config_hash: str = ""
    product_id: str = ""
    job_id: str = ""

    def matches(self, result: JobResult) -> bool:
        return (
            (not self.state or result.state == self.state)
            and (not self.meas_id or result.meas_id == self.meas_id)
            and (not self.part_id or result.part_id == self.part_id)
            and (not self.recipe or result.recipe == self.recipe)
            and (not self.config_hash or result.config_hash == self.config_hash)
            and (not self.product_id or result.product_id == self.product_id)
            and (not self.job_id or result.job_id == self.job_id)
        )


class ResultRing:
    """The last ``kept`` results by id (bounded memory: the oldest goes first)."""

    def __init__(self, kept: int) -> None:
        if kept < 1:
            raise ValueError(f"results kept must be at least 1, got {kept}")
        self.kept = kept
        self._results: OrderedDict[str, JobResult] = OrderedDict()

    def add(self, result: JobResult) -> None:
        self._results[result.result_id] = result
        self._results.move_to_end(result.result_id)
        while len(self._results) > self.kept:
            self._results.popitem(last=False)

    def get(self, result_id: str) -> JobResult | None:
        return self._results.get(result_id)

    def latest(self) -> JobResult | None:
        return next(reversed(self._results.values()), None)

    def __len__(self) -> int:
        return len(self._results)

    def newest_first(self) -> Iterator[JobResult]:
        return reversed(self._results.values())

    def filtered(
        self, criteria: ResultFilter, *, start: int, most: int
    ) -> tuple[list[JobResult], int, bool]:
        """The matching results newest first from index ``start``, at most ``most`` (0: no
        bound beyond the ring's); with the number that match in all and whether this page
        reaches the last of them."""
        matching = [r for r in self.newest_first() if criteria.matches(r)]
        end = len(matching) if most <= 0 else start + most
        page = matching[start:end]
        return page, len(matching), end >= len(matching)


__all__ = [
    "RESULT_ABORTED",
    "RESULT_COMPLETED",
    "RESULT_FAILED",
    "RESULT_PROCESSING",
    "RESULT_UNDEFINED",
    "JobResult",
    "ResultFilter",
    "ResultRing",
]
