"""Inspections that hold Python's GIL, run in worker processes with their images in shared memory.

Most of an inspection's time is in OpenCV and numpy, which release the GIL, so threads run them
in parallel. Some keep the GIL for much of their run (Python loops over candidates): two threads
then do little more than one (bench section 2b measures it per inspection: cap_locate 1.5x,
station_pose 1.3x on 2 cores), and they hold up the event loop and the cheap inspections of the
fast lane. Those named in ``server: process_inspections`` run here instead.

Each worker process (started with ``spawn``, never ``fork``: the server has threads) has a pipe
of its own and a shared-memory block of its own that lives as long as it does. The service's
thread that admitted a request takes an idle worker, copies the images once into the worker's
block, sends a message of a few hundred bytes and waits on the pipe without the GIL; the process
runs the inspection on arrays that view the block and sends the outcome back. A request thus
costs one copy and one round trip on a pipe: no pool manager thread, no queue feeder thread, no
shared-memory block created, faulted in and unlinked per request (bench section 2 counted about
200 page faults and 3 ms of the server's CPU per 786 KB locate with a block per request).

An inspection travels pickled the first time a worker runs it; afterwards by a number that the
server and the process both map to it (each keeps the same :data:`CACHED_INSPECTIONS` latest,
evicted in the same order, so the two maps never disagree).

A worker that dies (killed, or crashed in native code) fails only the request it was running,
with an ``INTERNAL_ERROR`` that says so, and is started again for the next one.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing
import pickle
import queue
import signal
import threading
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from multiprocessing.shared_memory import SharedMemory
from typing import Any

import numpy as np

from protocol.errors import InternalError, ShuttingDown

from ..inspections import Inspection, InspectionInput, InspectionOutcome
from ..process import run_this_process_at, target_niceness

Layout = tuple[tuple[int, tuple[int, ...], str], ...]
"""Where each image lies in the shared block: (offset in bytes, shape, numpy dtype string);
the colour image first, then the depth frames."""

CACHED_INSPECTIONS = 32
"""Inspections a worker keeps unpickled (a template is not decoded again for every request)."""

KEPT_BLOCK_BYTES = 64 * 1024 * 1024
"""A worker keeps its block between requests up to this size (a 4096x3000 16-bit image with a
depth frame fits); a larger request gets a block of its own, removed after it, so that one
huge image does not hold its memory for the life of the server."""

MIN_BLOCK_BYTES = 1024 * 1024

START_TIMEOUT_S = 120.0
"""How long a new process may take to import what it runs (seconds; ``spawn`` on a loaded
2-core machine takes a few)."""


@dataclass
class _Worker:
    """One worker process as the server sees it. Used by one thread at a time (it is taken from
    the idle queue and put back)."""

    process: BaseProcess
    conn: Connection
    block: SharedMemory | None = None
    known: OrderedDict[int, None] = field(default_factory=OrderedDict)
    """The inspection numbers this process holds, oldest first (mirrors the process's cache;
    a process that lacks one says so and is sent its pickle)."""
    sequence: int = 0
    """The number of the last message sent: a reply to an earlier one (left unread when its
    thread was interrupted) is recognised and dropped."""


class ProcessLane:
    """A pool of ``processes`` worker processes, started on first use. :meth:`run` blocks the
    calling thread (a worker of the service's lanes) until the outcome is back."""

    def __init__(
        self,
        processes: int,
        *,
        nice: int = 0,
        policy: str = "nice",
        opencv_threads: int | None = None,
    ) -> None:
        self.processes = processes
        self.opencv_threads = opencv_threads
        """``cv2.setNumThreads`` in each process (a spawned process starts at OpenCV's default,
        one thread per core: ``processes`` of them would oversubscribe the cores). None: as
        OpenCV starts."""
        self.niceness = target_niceness(nice) if nice > 0 else None
        """The niceness each process sets when it starts, ``nice`` above the server's own
        (vision_server/process/cpu_priority.py): the main lane's work yields the cores to the event
        loop and the fast lane. None: as inherited."""
        self.policy = policy
        """``nice`` or ``idle`` (:data:`vision_server.process.cpu_priority.POLICIES`)."""
        self._context = multiprocessing.get_context("spawn")
        self._idle: queue.SimpleQueue[_Worker | None] = queue.SimpleQueue()
        """Workers free to take a request; None once the lane is stopped (each waiter that
        takes it puts it back for the next)."""
        self._workers: list[_Worker] = []
        self._lock = threading.Lock()
        self._started = False
        self._closed = False
        self._numbers: dict[int, tuple[Inspection, int, bytes]] = {}
        """id(inspection) -> (the inspection, kept alive so that the id is not reused; its
        number; its pickle)."""
        self._next_number = itertools.count(1)

    # ------------------------------------------------------------------ life cycle

    def start(self) -> None:
        """Start the processes now and wait until each has imported what it runs (seconds,
        with ``spawn``): call it in a thread before serving, so that the first requests do
        not pay for it."""
        with self._lock:
            if self._closed:
                raise ShuttingDown("the worker processes are stopped")
            if self._started:
                return
            self._started = True
            workers = [self._spawn() for _ in range(self.processes)]
            self._workers.extend(workers)
        for worker in workers:
            self._idle.put(worker)

    def _spawn(self) -> _Worker:
        ours, theirs = self._context.Pipe(duplex=True)
        process = self._context.Process(
            target=_child_main,
            args=(theirs, self.niceness, self.policy, self.opencv_threads),
            name="cellvision-inspection",
            daemon=True,
        )
        process.start()
        theirs.close()
        if not ours.poll(START_TIMEOUT_S):
            process.kill()
            raise InternalError(
                f"a worker process did not start within {START_TIMEOUT_S:.0f} s",
            )
        ours.recv()  # its "ready": the imports are done
        return _Worker(process, ours)

    def shutdown(self) -> None:
        """Stop the processes (a running inspection's thread gets an ``INTERNAL_ERROR``) and
        remove their blocks."""
        with self._lock:
            self._closed = True
            workers, self._workers = self._workers, []
        self._idle.put(None)  # threads waiting for a worker get SHUTTING_DOWN
        for worker in workers:
            with contextlib.suppress(OSError):
                worker.conn.close()
            if worker.process.is_alive():
                worker.process.terminate()
            worker.process.join(timeout=5.0)
            if worker.process.is_alive():
                worker.process.kill()
                worker.process.join(timeout=5.0)
            _remove(worker.block)
            worker.block = None

    # ------------------------------------------------------------------ a request

    def run(self, inspection: Inspection, image: InspectionInput, *, overlay: bool) -> Any:
        """``inspection.run(image, overlay=overlay)`` in a worker process."""
        self.start()
        number, pickled = self._number(inspection)
        worker = self._idle.get()
        if worker is None:
            self._idle.put(None)
            raise ShuttingDown("the worker processes are stopped")
        try:
            status, payload = self._run_on(worker, number, pickled, image, overlay)
        except (EOFError, OSError) as exc:
            worker = self._replace(worker)
            raise InternalError(
                f"the worker process running {inspection.name!r} ended during the inspection "
                f"({type(exc).__name__}); it has been restarted",
            ) from exc
        finally:
            with self._lock:
                alive = not self._closed
            if alive:
                self._idle.put(worker)
        if status == "ok":
            return payload
        raise payload  # the inspection's own error, raised in the process

    def _run_on(
        self,
        worker: _Worker,
        number: int,
        pickled: bytes,
        image: InspectionInput,
        overlay: bool,
    ) -> tuple[str, Any]:
        """Send the request to ``worker`` and wait for its ``("ok", outcome)`` or
        ``("error", exception)``; EOFError or OSError when the process is gone."""
        arrays = (np.ascontiguousarray(image.color), *map(np.ascontiguousarray, image.depth))
        layout: list[tuple[int, tuple[int, ...], str]] = []
        size = 0
        for array in arrays:
            layout.append((size, tuple(array.shape), array.dtype.str))
            size += -(-array.nbytes // 64) * 64  # each image on its own 64-byte boundary
        one_off = size > KEPT_BLOCK_BYTES
        block = SharedMemory(create=True, size=size) if one_off else self._block(worker, size)
        try:
            for (offset, shape, dtype), array in zip(layout, arrays, strict=True):
                np.ndarray(shape, dtype, buffer=block.buf, offset=offset)[...] = array
            message = (block.name, tuple(layout), image.intrinsics, image.deadline, overlay)
            status, payload = self._exchange(worker, number, pickled, message, force=False)
            if status == "missing":  # the process lost it (its unpickling failed): send it
                status, payload = self._exchange(worker, number, pickled, message, force=True)
            return status, payload
        finally:
            if one_off:
                _remove(block)

    def _exchange(
        self,
        worker: _Worker,
        number: int,
        pickled: bytes,
        message: tuple[str, Layout, Any, float | None, bool],
        *,
        force: bool,
    ) -> tuple[str, Any]:
        """One message to ``worker`` and its reply. The inspection goes as its pickle when the
        process is not known to hold it, or ``force``; it counts as held once sent."""
        sent: bytes | None = pickled
        if not force and number in worker.known:
            worker.known.move_to_end(number)
            sent = None
        worker.sequence += 1
        sequence = worker.sequence
        worker.conn.send((sequence, number, sent, *message))
        if sent is not None:
            worker.known[number] = None
            worker.known.move_to_end(number)
            if len(worker.known) > CACHED_INSPECTIONS:
                worker.known.popitem(last=False)
        while True:
            answered, status, payload = worker.conn.recv()
            if answered == sequence:
                if status == "missing":
                    worker.known.pop(number, None)
                return status, payload

    def _block(self, worker: _Worker, size: int) -> SharedMemory:
        """The worker's own block, replaced by a larger one when ``size`` does not fit."""
        if worker.block is None or worker.block.size < size:
            _remove(worker.block)
            worker.block = SharedMemory(
                create=True, size=max(MIN_BLOCK_BYTES, 1 << (size - 1).bit_length())
            )
        return worker.block

    def _number(self, inspection: Inspection) -> tuple[int, bytes]:
        with self._lock:
            found = self._numbers.get(id(inspection))
            if found is None:
                found = (inspection, next(self._next_number), pickle.dumps(inspection))
                self._numbers[id(inspection)] = found
                # A reload replaces the inspections: the old ones go once many have come.
                while len(self._numbers) > 4 * CACHED_INSPECTIONS:
                    del self._numbers[next(iter(self._numbers))]
            return found[1], found[2]

    def _replace(self, dead: _Worker) -> _Worker:
        """A new process in place of ``dead`` (which is reaped and its block removed)."""
        with contextlib.suppress(OSError):
            dead.conn.close()
        dead.process.join(timeout=5.0)
        _remove(dead.block)
        dead.block = None
        with self._lock:
            if self._closed:
                return dead
        fresh = self._spawn()
        with self._lock:
            self._workers = [fresh if w is dead else w for w in self._workers]
        return fresh

    @property
    def pids(self) -> list[int]:
        """The worker processes' ids (for tests and diagnostics)."""
        with self._lock:
            return [w.process.pid for w in self._workers if w.process.pid is not None]


def _remove(block: SharedMemory | None) -> None:
    if block is None:
        return
    with contextlib.suppress(BufferError):
        block.close()
    with contextlib.suppress(FileNotFoundError):
        block.unlink()


# ----------------------------------------------------------------------------- in the child


def _child_main(
    conn: Connection, niceness: int | None, policy: str, opencv_threads: int | None
) -> None:
    """A worker process: answer run messages until the pipe closes."""
    # Ctrl-C reaches the whole process group; the server decides when its workers stop.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    run_this_process_at(niceness, policy)
    if opencv_threads is not None:
        import cv2

        cv2.setNumThreads(opencv_threads)
    inspections: OrderedDict[int, Inspection] = OrderedDict()
    attached: dict[str, SharedMemory] = {}
    conn.send("ready")
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        sequence, body = message[0], message[1:]
        try:
            reply: tuple[int, str, Any] = (
                sequence,
                "ok",
                _run_in_child(body, inspections, attached),
            )
        except _Missing:
            reply = (sequence, "missing", None)
        except Exception as exc:  # an inspection's error goes back to the request it failed
            reply = (sequence, "error", exc)
        try:
            conn.send(reply)
        except (EOFError, OSError):
            return
        except Exception as exc:  # an outcome or error that does not pickle
            conn.send(
                (
                    sequence,
                    "error",
                    InternalError(
                        f"the inspection's outcome could not be sent back: {exc}",
                    ),
                )
            )


class _Missing(Exception):
    """The process does not hold the inspection it was sent by number."""


def _run_in_child(
    message: tuple[Any, ...],
    inspections: OrderedDict[int, Inspection],
    attached: dict[str, SharedMemory],
) -> InspectionOutcome:
    number, pickled, block_name, layout, intrinsics, deadline, overlay = message
    if pickled is not None:
        inspections[number] = pickle.loads(pickled)
        if len(inspections) > CACHED_INSPECTIONS:
            inspections.popitem(last=False)
    elif number in inspections:
        inspections.move_to_end(number)
    else:
        raise _Missing
    inspection = inspections[number]
    block = _attach(block_name, attached)
    images = [
        np.ndarray(shape, np.dtype(dtype), buffer=block.buf, offset=offset)
        for offset, shape, dtype in layout
    ]
    color, depth = images[0], tuple(images[1:])
    outcome = inspection.run(InspectionInput(color, depth, intrinsics, deadline), overlay=overlay)
    if outcome.overlay is not None and np.shares_memory(outcome.overlay, color):
        outcome = replace(outcome, overlay=np.array(outcome.overlay))
    del images, color, depth
    if block.size > KEPT_BLOCK_BYTES:  # a one-off block: the server removes it now
        with contextlib.suppress(BufferError):
            block.close()
        del attached[block_name]
    return outcome


def _attach(name: str, attached: dict[str, SharedMemory]) -> SharedMemory:
    """The block ``name``, mapped once; blocks the server has replaced are unmapped."""
    block = attached.get(name)
    if block is None:
        for old in attached.values():
            # An array still viewing an old block keeps it mapped until it is freed.
            with contextlib.suppress(BufferError):
                old.close()
        attached.clear()
        # Python 3.11 registers an attached block with the resource tracker as if this process
        # owned it. A spawned process shares the server's tracker, where the block is already
        # registered (a set: no change); unregistering here would drop the server's entry.
        block = SharedMemory(name=name)
        attached[name] = block
    return block


__all__ = ["ProcessLane"]
