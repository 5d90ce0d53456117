"""Inspections that hold Python's GIL, run in worker processes with their images in shared memory.

Most of an inspection's time is in OpenCV and numpy, which release the GIL, so threads run them
in parallel. Some keep the GIL for much of their run (Python loops over candidates): two threads
then do little more than one (bench section 2b measures it per inspection: cap_locate 1.5x,
station_pose 1.3x on 2 cores), and they hold up the event loop and the cheap inspections of the
fast lane. Those named in ``server: process_inspections`` run here instead: the worker thread
that admitted the request copies its images once into a shared-memory block, a process of the
pool (started with ``spawn``, never ``fork``: the server has threads) maps the block, runs the
inspection and sends back the outcome; the thread waits without the GIL.

The inspection object travels pickled with each run (a few hundred bytes; a process keeps the
last ones it unpickled, so a template is not decoded again for every request).
"""

from __future__ import annotations

import contextlib
import multiprocessing
import pickle
import threading
from collections import OrderedDict
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from multiprocessing import resource_tracker
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from .catalog import Inspection, InspectionInput, InspectionOutcome
from .cpu_priority import run_this_process_at, target_niceness

Layout = tuple[tuple[int, tuple[int, ...], str], ...]
"""Where each image lies in the shared block: (offset in bytes, shape, numpy dtype string);
the colour image first, then the depth frames."""

CACHED_INSPECTIONS = 32


class ProcessLane:
    """A pool of ``processes`` worker processes, started on first use. :meth:`run` blocks the
    calling thread (a worker of the service's lanes) until the outcome is back."""

    def __init__(self, processes: int, *, nice: int = 0, policy: str = "nice") -> None:
        self.processes = processes
        self.niceness = target_niceness(nice) if nice > 0 else None
        """The niceness each process sets when it starts, ``nice`` above the server's own
        (vision_server/cpu_priority.py): the main lane's work yields the cores to the event
        loop and the fast lane. None: as inherited."""
        self.policy = policy
        """``nice`` or ``idle`` (:data:`vision_server.cpu_priority.POLICIES`)."""
        self._pool: ProcessPoolExecutor | None = None
        self._lock = threading.Lock()

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = ProcessPoolExecutor(
                    self.processes,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=run_this_process_at,
                    initargs=(self.niceness, self.policy),
                )
            return self._pool

    def start(self) -> None:
        """Start the processes now and wait until each has imported what it runs (seconds,
        with ``spawn``): call it in a thread before serving, so that the first requests do
        not pay for it."""
        pool = self._executor()
        for done in [pool.submit(_ready) for _ in range(self.processes)]:
            done.result()

    def run(self, inspection: Inspection, image: InspectionInput, *, overlay: bool) -> Any:
        """``inspection.run(image, overlay=overlay)`` in a worker process."""
        arrays = (np.ascontiguousarray(image.color), *map(np.ascontiguousarray, image.depth))
        layout: list[tuple[int, tuple[int, ...], str]] = []
        size = 0
        for array in arrays:
            layout.append((size, tuple(array.shape), array.dtype.str))
            size += -(-array.nbytes // 64) * 64  # each image on its own 64-byte boundary
        block = SharedMemory(create=True, size=max(size, 1))
        try:
            for (offset, shape, dtype), array in zip(layout, arrays, strict=True):
                np.ndarray(shape, dtype, buffer=block.buf, offset=offset)[...] = array
            future = self._executor().submit(
                _run_in_child,
                pickle.dumps(inspection),
                block.name,
                tuple(layout),
                image.intrinsics,
                overlay,
            )
            return future.result()
        finally:
            block.close()
            block.unlink()

    def shutdown(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


# ----------------------------------------------------------------------------- in the child

_inspections: OrderedDict[bytes, Inspection] = OrderedDict()


def _ready() -> None:
    """A first task for a new process: the imports are done once this runs."""


def _inspection(pickled: bytes) -> Inspection:
    found = _inspections.get(pickled)
    if found is None:
        found = pickle.loads(pickled)
        _inspections[pickled] = found
        if len(_inspections) > CACHED_INSPECTIONS:
            _inspections.popitem(last=False)
    else:
        _inspections.move_to_end(pickled)
    return found


def _run_in_child(
    pickled: bytes, block_name: str, layout: Layout, intrinsics: Any, overlay: bool
) -> InspectionOutcome:
    inspection = _inspection(pickled)
    block = SharedMemory(name=block_name)
    # Python 3.11 registers an attached block with the resource tracker as if this process
    # owned it; the parent unlinks it, so this process must not.
    resource_tracker.unregister(block._name, "shared_memory")  # type: ignore[attr-defined]
    try:
        images = [
            np.ndarray(shape, np.dtype(dtype), buffer=block.buf, offset=offset)
            for offset, shape, dtype in layout
        ]
        color, depth = images[0], tuple(images[1:])
        outcome = inspection.run(InspectionInput(color, depth, intrinsics), overlay=overlay)
        if outcome.overlay is not None and np.shares_memory(outcome.overlay, color):
            outcome = replace(outcome, overlay=np.array(outcome.overlay))
        del images, color, depth
        return outcome
    finally:
        # An array still viewing the block keeps it mapped until it is freed.
        with contextlib.suppress(BufferError):
            block.close()


__all__ = ["ProcessLane"]
