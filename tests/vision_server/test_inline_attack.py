"""An attack review of issue 33's inline runs (``inline_ms``), kept as regression tests: what a
client controls must not decide how long a run "known to be cheap" holds the event loop, and a
run on the loop keeps the deadline a run in a worker keeps.

- The request's image size and its options (which re-tune the inspection: another ``measure``,
  another ``roi``) are part of the judgement: a presence check measured on small images must
  not count blobs in a 16 MP image on the loop (every other connection would stall).
- A run that fails slowly counts as slow.
- A run on the loop that raises does not wait for its error row past the deadline (a result
  log that hangs), and a run that overruns its deadline is answered DEADLINE_EXCEEDED.

Which thread ran what is recorded by the inspections (a proxy around the configured ones);
nothing here measures time.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from inline_runs import FailsSlowly, until_on_the_loop
from loopback import run

from protocol import BadImage, DeadlineExceeded
from vision_server import Catalog, InspectionInput, InspectionOutcome
from vision_server.cameras import RequestCamera, RequestCameraSettings
from vision_server.config import ServiceSettings, load_config
from vision_server.results import ResultEntry, ResultLog
from vision_server.service import Images, InspectionService, InspectRequest, deadline_after

SMALL = np.full((48, 64), 120, np.uint8)

CELL = """
cameras:
  tool: {source: request}
inspections:
  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 10,
     roi: [0, 0, 16, 16]}
  - {name: blobs, type: presence, camera: tool, measure: blob_count, min: 0}
"""


def configured_catalog(tmp_path: Path) -> Catalog:
    (tmp_path / "cell.yaml").write_text(CELL)
    config = load_config(tmp_path / "cell.yaml")
    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        list(config.inspections),
        tune=config.tune,
    )


class Noting:
    """A configured inspection that notes the thread of each run in ``threads``."""

    def __init__(self, inner: Any, threads: list[str]) -> None:
        self._inner = inner
        self._threads = threads

    def __getattr__(self, name: str) -> Any:
        return getattr(self._inner, name)

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        self._threads.append(threading.current_thread().name)
        outcome: InspectionOutcome = self._inner.run(image, overlay=overlay)
        return outcome


def noting_catalog(tmp_path: Path, threads: list[str]) -> Catalog:
    """:func:`configured_catalog` whose inspections, and those a request's options make,
    note their threads."""
    (tmp_path / "cell.yaml").write_text(CELL)
    config = load_config(tmp_path / "cell.yaml")
    tune = config.tune

    def tuned(name: str, options: Any) -> Any:
        return Noting(tune(name, options), threads)

    return Catalog.build(
        [RequestCamera("tool", RequestCameraSettings())],
        [Noting(i, threads) for i in config.inspections],
        tune=tuned,
    )


def test_options_that_make_a_cheap_inspection_expensive_are_not_run_on_the_loop(
    tmp_path: Path,
) -> None:
    """A presence check over a 16x16 ROI is measured at a few microseconds; a request may tune
    it to count blobs over a whole 4096x4096 image (hundreds of ms of OpenCV). That run goes
    to a worker (OpenCV releases the GIL there), however the server judged the inspection's
    earlier runs. On the first version of inline runs it ran on the loop and stalled it for
    320-440 ms."""
    threads: list[str] = []
    catalog = noting_catalog(tmp_path, threads)
    big = np.random.default_rng(0).integers(0, 255, (4096, 4096), dtype=np.uint8)

    async def body() -> None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            # Measured cheap: from now on it runs on the loop.
            await until_on_the_loop(
                lambda: service.inspect(InspectRequest("bright", Images(SMALL))), threads
            )
            options = {"measure": "blob_count", "roi": [0, 0, 4096, 4096]}
            await service.inspect(InspectRequest("bright", Images(big), options=options))
        finally:
            service.close()

    run(body())
    assert threads[-1].startswith("inspect"), threads[-2:]


def test_a_large_image_to_an_inspection_measured_on_small_ones_is_not_run_on_the_loop(
    tmp_path: Path,
) -> None:
    """No options at all: a blob count measured on 64x48 images (cheap: it runs on the loop)
    gets one 4096x4096 image, within max_image_pixels: that run goes to a worker (the
    estimate is per byte of image, and never beyond the largest image measured). On the first
    version of inline runs it stalled the loop for 270-300 ms."""
    threads: list[str] = []
    catalog = noting_catalog(tmp_path, threads)
    big = np.random.default_rng(0).integers(0, 255, (4096, 4096), dtype=np.uint8)

    async def body() -> None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            # Until its first runs' cost (a cold start) has decayed: then it runs on the loop.
            await until_on_the_loop(
                lambda: service.inspect(InspectRequest("blobs", Images(SMALL))), threads
            )
            await service.inspect(InspectRequest("blobs", Images(big)))
        finally:
            service.close()

    run(body())
    assert threads[-1].startswith("inspect"), threads[-2:]


class SlowLog(ResultLog):
    """The SQLite result log, whose error rows take ``slow_s`` (a database that hangs)."""

    def __init__(self, path: Path, slow_s: float) -> None:
        super().__init__(path)
        self.slow_s = slow_s
        self.gate = threading.Event()

    def record(self, entry: ResultEntry) -> int | None:
        if entry.error:
            self.gate.wait(self.slow_s)
        return super().record(entry)


class Flaky:
    """A cheap inspection whose runs raise once ``fail`` is set (a part not found)."""

    name = "flaky"
    camera = "tool"
    type = "test_flaky"
    uses_depth = False
    frames = 1

    def __init__(self) -> None:
        self.fail = False

    def run(self, image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
        if self.fail:
            raise BadImage("this part is not in the image")
        return InspectionOutcome(True, {"mean": float(image.color.mean())})


@pytest.mark.parametrize("inline_ms", [0.0, 0.5], ids=["pool", "inline-allowed"])
def test_a_failing_run_answers_at_its_deadline_when_the_result_log_hangs(
    tmp_path: Path, inline_ms: float
) -> None:
    """A run that raises while the result log hangs on its error row: with a 200 ms deadline
    the request ends DEADLINE_EXCEEDED while the log still hangs, as it does in a worker (the
    first version of inline runs waited for the row, then raised the run's error)."""
    flaky = Flaky()
    log = SlowLog(tmp_path / "results.db", slow_s=20.0)
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [flaky])

    async def body() -> tuple[bool, BaseException | None]:
        service = InspectionService(
            catalog, ServiceSettings(workers=1, queue_depth=4, inline_ms=inline_ms), results=log
        )
        try:
            for _ in range(3):
                await service.inspect(InspectRequest("flaky", Images(SMALL)))
            flaky.fail = True
            arrived = time.monotonic()
            request = InspectRequest(
                "flaky", Images(SMALL), arrived=arrived, deadline=deadline_after(arrived, 200.0)
            )
            caught: BaseException | None = None
            try:
                await service.inspect(request)
            except Exception as exc:  # noqa: BLE001 - which one is the verdict
                caught = exc
            return not log.gate.is_set(), caught
        finally:
            log.gate.set()
            service.close()

    try:
        log_still_hung, caught = run(body())
    finally:
        log.close()
    assert isinstance(caught, DeadlineExceeded), repr(caught)
    assert log_still_hung  # answered at the deadline, not after the row


def slow_search() -> FailsSlowly:
    """A search that finds nothing after the work: NOT_FOUND-like, a CellvisionError."""
    return FailsSlowly("search", lambda: BadImage("nothing found"))


def test_a_run_that_fails_slowly_on_the_loop_counts_as_slow() -> None:
    """After a 30 ms run, the inspection leaves the loop (``test_one_slow_run_keeps_an_
    inspection_off_the_loop``), but only when the slow run returned: a run that raises is never
    measured (``loop_costs.observe`` comes after ``run``, in ``_inline`` and in ``work``). A
    client that can make a cheap inspection fail slowly (an input where a search finds nothing)
    holds the event loop on every such request, for ever."""
    search = slow_search()
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [search])

    async def body() -> None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            for _ in range(3):
                await service.inspect(InspectRequest("search", Images(SMALL)))
            search.fail_after_ms = 30.0
            for _ in range(5):
                with pytest.raises(BadImage):
                    await service.inspect(InspectRequest("search", Images(SMALL)))
        finally:
            service.close()

    loop_thread = threading.current_thread().name
    run(body())
    failing = search.threads[3:]
    assert failing.count(loop_thread) <= 1, failing


def test_a_run_on_the_loop_that_overruns_its_deadline_is_not_answered_as_a_result() -> None:
    """A run in a worker that outlives its request's deadline is answered DEADLINE_EXCEEDED
    at the deadline (``_until``). On the loop (``_inline``) the deadline is checked only
    before the run: a run measured cheap that then takes 40 ms with a 10 ms deadline is
    answered with its RESULT at 40 ms (without a result log or overlay nothing after the run
    looks at the deadline)."""
    search = slow_search()
    catalog = Catalog.build([RequestCamera("tool", RequestCameraSettings())], [search])

    async def body() -> BaseException | None:
        service = InspectionService(catalog, ServiceSettings(workers=1, queue_depth=4))
        try:
            for _ in range(3):
                await service.inspect(InspectRequest("search", Images(SMALL)))
            slow = SlowRun(search, 40.0)
            arrived = time.monotonic()
            request = InspectRequest(
                "search", Images(SMALL), arrived=arrived, deadline=deadline_after(arrived, 10.0)
            )
            try:
                with slow:
                    await service.inspect(request)
            except Exception as exc:  # noqa: BLE001 - which one is the verdict
                return exc
            return None
        finally:
            service.close()

    caught = run(body())
    assert isinstance(caught, DeadlineExceeded), repr(caught)


class SlowRun:
    """While entered, ``search``'s runs pass after spinning ``ms``."""

    def __init__(self, search: FailsSlowly, ms: float) -> None:
        self.search = search
        self.ms = ms
        self.original = search.run

    def __enter__(self) -> None:
        ms = self.ms
        original = self.original

        def slow(image: InspectionInput, *, overlay: bool) -> InspectionOutcome:
            end = time.perf_counter() + ms / 1000.0
            while time.perf_counter() < end:
                pass
            return original(image, overlay=overlay)

        self.search.run = slow  # type: ignore[method-assign]

    def __exit__(self, *exc: object) -> None:
        self.search.run = self.original  # type: ignore[method-assign]
