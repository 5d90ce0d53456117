"""In-process throughput of an inspection: the catalog's inspection object called directly on
one image by a pool of threads (or of processes, for the inspections the server runs in
worker processes) for a fixed window, no protocol, no server. It is the
machine's limit that a server is compared with, and it tells whether an inspection releases
the GIL (its throughput with N threads against one thread).
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2

from .env import Env

PROCESS_TIMEOUT_S = 300.0
"""How long :func:`process_rate` waits for its processes (imports, warm-up and window)."""


def cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@dataclass(frozen=True)
class Rate:
    """``calls`` completed by ``threads`` threads in a window of ``seconds`` (wall), with
    OpenCV's own thread count ``cv_threads`` in each; ``cpu_s``: this process's CPU time from
    the window's start until the last call ended, ``elapsed_s`` later. When a worker's first
    call ended after the window (a loaded machine, a short window), that call counts and
    ``seconds`` is ``elapsed_s``."""

    threads: int
    cv_threads: int
    calls: int
    seconds: float
    cpu_s: float
    elapsed_s: float
    model: str = "threads"
    """``threads`` (one process, :func:`rate`) or ``processes`` (:func:`process_rate`)."""

    @property
    def rps(self) -> float:
        return self.calls / self.seconds if self.seconds > 0 else float("nan")

    @property
    def cpu_pct(self) -> float:
        """CPU use over the window, 100 % = one core."""
        return 100.0 * self.cpu_s / self.elapsed_s if self.elapsed_s > 0 else float("nan")


def combined(rates: list[Rate]) -> Rate:
    """Several windows of the same setting as one: calls, seconds and CPU added up."""
    first = rates[0]
    return Rate(
        first.threads,
        first.cv_threads,
        sum(r.calls for r in rates),
        sum(r.seconds for r in rates),
        sum(r.cpu_s for r in rates),
        sum(r.elapsed_s for r in rates),
        first.model,
    )


def runner(env: Env, inspection: str, image: Any, depth: tuple[Any, ...] = ()) -> Callable[[], Any]:
    """A call of the bench catalog's ``inspection`` on ``image`` (and ``depth``), with its
    camera's intrinsics, as a worker of the server would make it (no overlay)."""
    from vision_server import InspectionInput

    catalog = env.catalog.catalog
    target = catalog.inspection(inspection)
    intrinsics = getattr(catalog.cameras.get(target.camera), "intrinsics", None)
    given = InspectionInput(image, depth, intrinsics)

    def call() -> Any:
        return target.run(given, overlay=False)

    return call


def rate(
    call: Callable[[], Any],
    *,
    threads: int,
    window_s: float,
    cv_threads: int | None = None,
    warmup: int = 2,
) -> Rate:
    """Calls per second of ``call`` made by ``threads`` threads at once over ``window_s``.

    ``cv_threads``: ``cv2.setNumThreads`` inside each worker before it starts (None: OpenCV's
    default, as the server leaves it); the setting is OpenCV's, process-wide, and restored
    afterwards. Each thread makes ``warmup`` calls first; the window opens when all are done.
    A call counts when it ends inside the window."""
    previous = cv2.getNumThreads()
    window: dict[str, float] = {}

    def open_window() -> None:  # the barrier's action: runs once, before any thread goes on
        window["start"] = time.perf_counter()
        window["end"] = window["start"] + window_s
        window["cpu"] = time.process_time()

    barrier = threading.Barrier(threads, action=open_window)

    def setup() -> None:
        if cv_threads is not None:
            cv2.setNumThreads(cv_threads)

    def loop() -> tuple[int, bool]:
        for _ in range(warmup):
            call()
        barrier.wait()
        return _count_calls(call, window["end"])

    try:
        with ThreadPoolExecutor(threads, initializer=setup) as pool:
            futures = [pool.submit(loop) for _ in range(threads)]
            counts = [f.result() for f in futures]
        cpu_s = time.process_time() - window["cpu"]
        elapsed_s = time.perf_counter() - window["start"]
        in_effect = cv_threads if cv_threads is not None else previous
    finally:
        cv2.setNumThreads(previous)
    calls = sum(done for done, _ in counts)
    late = any(late for _, late in counts)
    return Rate(threads, in_effect, calls, elapsed_s if late else window_s, cpu_s, elapsed_s)


def _count_calls(call: Callable[[], Any], end: float) -> tuple[int, bool]:
    """Call ``call`` until ``end`` (a perf_counter time) and count the calls that ended
    before it; at least one call is counted: on a machine so loaded that not one ends inside
    the window, the first one is counted and the window reaches to its end (the second value,
    ``late``, says so), rather than report no rate at all."""
    done = 0
    late = False
    while done == 0 or time.perf_counter() < end:
        call()
        if time.perf_counter() <= end:
            done += 1
        elif done == 0:
            done, late = 1, True
    return done, late


def _process_loop(
    config: Path,
    inspection: str,
    image: Any,
    depth: tuple[Any, ...],
    cv_threads: int,
    warmup: int,
    window_s: float,
    barrier: Any,
    out: Any,
) -> None:
    """One process of :func:`process_rate`: loads the bench catalog itself, as a worker
    process of the server does, and counts the calls that end inside its window."""
    from .cell import load_catalog

    cv2.setNumThreads(cv_threads)
    catalog = load_catalog(config).catalog
    target = catalog.inspection(inspection)
    intrinsics = getattr(catalog.cameras.get(target.camera), "intrinsics", None)
    from vision_server import InspectionInput

    given = InspectionInput(image, depth, intrinsics)
    for _ in range(warmup):
        target.run(given, overlay=False)
    barrier.wait()
    start, cpu0 = time.perf_counter(), time.process_time()
    done, late = _count_calls(lambda: target.run(given, overlay=False), start + window_s)
    out.put((done, time.process_time() - cpu0, time.perf_counter() - start, late))


def process_rate(
    env: Env,
    inspection: str,
    image: Any,
    *,
    processes: int,
    window_s: float,
    depth: tuple[Any, ...] = (),
    warmup: int = 2,
) -> Rate:
    """Calls per second of ``inspection`` made by ``processes`` processes at once (each with
    one OpenCV thread, no protocol, no shared memory: each has its own copy of the image):
    the limit of the worker model the server uses for inspections that hold the GIL. CPU is
    the processes' own, summed."""
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(processes)
    out = context.Queue()
    workers = [
        context.Process(
            target=_process_loop,
            args=(
                env.config_path,
                inspection,
                image,
                depth,
                1,
                warmup,
                window_s,
                barrier,
                out,
            ),
            name=f"bench-limit-{inspection}-{index}",
        )
        for index in range(processes)
    ]
    for worker in workers:
        worker.start()
    try:
        counts = [out.get(timeout=PROCESS_TIMEOUT_S) for _ in workers]
    finally:
        for worker in workers:
            worker.join(10.0)
            if worker.is_alive():
                worker.terminate()
    elapsed_s = max(c[2] for c in counts)
    return Rate(
        processes,
        1,
        sum(c[0] for c in counts),
        elapsed_s if any(c[3] for c in counts) else window_s,
        sum(c[1] for c in counts),
        elapsed_s,
        model="processes",
    )
