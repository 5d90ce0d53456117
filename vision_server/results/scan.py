"""The newest production results of one inspection, read a page at a time.

What the console's reads (``/api/inspections/{name}/reads``), the impact preview and
``vision-server replay`` all walk: an inspection's rows newest first, console tries skipped,
through the log's indexed query by inspection (``before_id`` paging), never a scan of the
whole log: at most ``max_examined`` rows are read, tries included.
"""

from __future__ import annotations

from collections.abc import Iterator

from .store import ResultStore, StoredResult


class ProductionRows:
    """Iterates ``inspection``'s production rows of ``log``, newest first, reading pages of
    ``page_rows``; stops after ``max_examined`` rows read (then :attr:`limited` is True)."""

    def __init__(
        self, log: ResultStore, inspection: str, *, page_rows: int, max_examined: int
    ) -> None:
        self.log = log
        self.inspection = inspection
        self.page_rows = max(1, page_rows)
        self.max_examined = max_examined
        self.examined = 0
        self.limited = False
        """Whether the walk stopped at ``max_examined`` with rows left unread."""

    def __iter__(self) -> Iterator[StoredResult]:
        before: int | None = None
        while True:
            if self.examined >= self.max_examined:
                self.limited = True
                return
            limit = min(self.page_rows, self.max_examined - self.examined)
            page = self.log.query(inspection=self.inspection, limit=limit, before_id=before)
            self.examined += len(page)
            for row in page:
                if not row.is_try:
                    yield row
            if len(page) < limit:
                return
            before = page[-1].id


__all__ = ["ProductionRows"]
