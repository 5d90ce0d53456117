"""The inspection service: the one path to an inspection, under every front-end.

A front-end (the TCP protocol, ``vision-server run``, the golden cases, the bench's HTTP
reference; a web console, a line protocol and Modbus later) parses its own wire format into an
:class:`InspectRequest` of arrays and plain values, calls :meth:`InspectionService.inspect`, and
renders the :class:`InspectReply`. The service owns everything between:

- admission: a bounded worker pool (a slot per request, BUSY when every slot is taken) and one
  budget for the bytes held for requests and replies (:meth:`InspectionService.admit`, which a
  front-end may call before it reads a request's body);
- deadlines, absolute, stamped by the front-end when the whole request had arrived (SPEC §6.1);
- images: those of the request (arrays, or a loader that decodes them in a worker), else a
  capture from the inspection's server camera; checked the same way whatever brought them;
- where a run happens: in a worker thread or process (the pool's lanes), or, for an inspection
  whose slowest recent run is at most ``inline_ms`` on raw images of the request, on the event
  loop itself, since a hop to a thread and back costs more than such a run;
- the result log, overlays (drawn in the run, encoded in a worker), configuration reload (always
  in a thread, never on the event loop) and observers of results.

Errors are :class:`protocol.CellvisionError` subclasses without a request id (the code names
the cause; the front-end that knows the request maps the code to its own form). Nothing here
knows a wire type.
"""

from __future__ import annotations

import asyncio
import logging
import resource
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any, Literal, TypeVar

import cv2
import numpy as np
import numpy.typing as npt

from protocol import (
    BadImage,
    Busy,
    CellvisionError,
    ConfigInvalid,
    DeadlineExceeded,
    ImageTooLarge,
    InvalidArgument,
    ShuttingDown,
    too_large_details,
)

from ..cameras import Camera, CameraFrame
from ..config import ServiceSettings
from ..inspections import Inspection, InspectionInput, InspectionOutcome
from ..results import ResultEntry, ResultStore
from .admission import (
    TRY_BUDGET_SHARE,
    Admission,
    ByteBudget,
    LoopCosts,
    Slot,
    Waiter,
    WorkPool,
    try_key,
)
from .catalog import Catalog
from .door import FrontDoor
from .process_lane import ProcessLane

log = logging.getLogger("vision_server")
_T = TypeVar("_T")
Image = npt.NDArray[Any]

RequestClass = Literal["production", "try"]
"""Who asks: a robot, PLC or tool (``production``) or the console's try, which runs in a lane of
its own with its own cost estimates and at most a share of the byte budget."""
FrameEncoding = Literal["png", "jpeg"]
"""How a captured frame may be compressed (None: raw arrays)."""

STORED_OVERLAY_MAX_PIXELS = 4096 * 3072
"""The largest image whose overlay the result log stores unasked (a colour copy per worker)."""

REPLY_OVERHEAD = 64 * 1024
"""Bytes of a capture reply besides the pixels (headers, metadata), generously."""


# ----------------------------------------------------------------------------- records


@dataclass(frozen=True)
class Images:
    """The images of one request: ``color`` (H, W) or (H, W, 3) uint8 BGR; ``depth`` zero or
    more (H, W) uint16 frames in millimetres, registered to ``color``."""

    color: Image
    depth: tuple[Image, ...] = ()


@dataclass(frozen=True)
class ImageNeeds:
    """What the inspection a request names takes, for a loader that decodes its images."""

    inspection: str
    depth: bool
    """Whether depth frames are taken at all."""
    max_pixels: int
    """The largest image (width x height) the service accepts."""
    size: tuple[int, int] | None = None
    """The image size (width, height) in pixels the inspection's camera declares intrinsics
    for; None when it declares none (any size is inspected)."""


ImageLoader = Callable[[ImageNeeds], Images]
"""Decodes a request's images, once the inspection is known: in a worker thread, or on the
event loop for a loader marked ``cheap`` (raw pixels viewed in place: :func:`loads_cheaply`).
Raises BadImage or ImageTooLarge for images that cannot be decoded."""


def request_bytes(images: Images | ImageLoader | None) -> int:
    """The bytes of a request's images together (colour and depth), as far as known before
    they are loaded (0: unknown); a loader says so with ``raw_bytes``."""
    if isinstance(images, Images):
        return int(images.color.nbytes) + sum(int(d.nbytes) for d in images.depth)
    return int(getattr(images, "raw_bytes", 0))


def input_bytes(image: InspectionInput) -> int:
    """The bytes of an inspection's input, colour and depth together."""
    return int(image.color.nbytes) + sum(int(d.nbytes) for d in image.depth)


def loads_cheaply(images: Images | ImageLoader | None) -> bool:
    """Whether a request's images are arrays at no cost: arrays already, or a loader that
    says so (``cheap``: it views raw pixels in place, nothing is decoded)."""
    return isinstance(images, Images) or bool(getattr(images, "cheap", False))


def deadline_after(arrived: float, deadline_ms: float | None) -> float | None:
    """The absolute deadline (``time.monotonic()`` seconds) of a request that arrived at
    ``arrived`` with a budget of ``deadline_ms`` milliseconds (None: no deadline)."""
    return None if deadline_ms is None else arrived + deadline_ms / 1000.0


@dataclass(frozen=True)
class InspectRequest:
    """One inspection to run.

    ``images``: arrays, a loader run in a worker (for encoded images), or None to capture from
    the inspection's server camera. ``overlay``: None for no overlay, ``"array"`` for the drawn
    image only, or an image file extension (``".png"``) to have it encoded in the worker too.
    ``options``: per-request parameters, validated like the configuration (SPEC §6.3).
    ``arrived`` and ``deadline``: ``time.monotonic()`` seconds; the front-end stamps ``arrived``
    when the whole request was received. ``peer`` and ``request_id`` only go to the result log.
    """

    inspection: str
    images: Images | ImageLoader | None = None
    overlay: str | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    arrived: float = field(default_factory=time.monotonic)
    deadline: float | None = None
    peer: str = ""
    request_id: int = 0
    request_class: RequestClass = "production"
    """``try``: a console try, with its own lane, cost estimates and share of the byte budget
    (:data:`~.admission.TRY_PREFIX`); production keeps its threads, slots and a reserve."""
    prepared: Inspection | None = None
    """The inspection to run instead of the catalog's ``inspection`` tuned with ``options``,
    built and validated by the caller: a console try of an edited or a new inspection (from
    its whole mapping by the loader's rules, :func:`vision_server.config.parse_draft`; then
    ``config`` holds that mapping and ``inspection``, its name, need not be configured), or an
    impact preview's changed inspection, built once for all its images."""
    config: Mapping[str, Any] | None = None
    """The whole mapping ``prepared`` was built from, for the result log's row (a try's)."""
    record: bool = True
    """False: the result log gets no row for this run. An impact preview replays images the
    log already holds, up to 1000 at a time: a row each would flood the log with copies of
    results it has (and push real ones out of its image budget), for runs of a configuration
    nobody saved."""
    operator: str = ""
    """Who asked (a console try's signed-in user): recorded as the row's operator."""


@dataclass(frozen=True)
class Overlay:
    """An inspection's drawing: ``image`` BGR uint8; ``encoded`` the bytes of an image file of
    ``format`` (``".png"``), or None when only the array was asked for."""

    image: Image
    format: str = "array"
    encoded: bytes | None = None


@dataclass(frozen=True)
class InspectReply:
    """What one inspection found. ``compute_ms``: the inspection's own run; ``total_ms``: from
    the request's arrival to the reply. ``stored``: whether the result log kept it (None
    without a log)."""

    inspection: str
    camera: str
    passed: bool
    data: dict[str, Any]
    compute_ms: float
    total_ms: float
    config_hash: str
    stored: bool | None = None
    overlay: Overlay | None = None
    result_id: int | None = None
    """The row's id in the result log, when the log gave one (RESULT ``result_id``)."""
    image_size: tuple[int, int] | None = None
    """``(width, height)`` in pixels of the colour image the inspection ran on."""

    @property
    def timing(self) -> dict[str, float]:
        return {"compute_ms": round(self.compute_ms, 3), "total_ms": round(self.total_ms, 3)}


@dataclass(frozen=True)
class InspectionRecord:
    """What observers of results get for each answered inspection."""

    request: InspectRequest
    reply: InspectReply
    captured: Images | None = None
    """The frames a server camera gave for this run (None when the request brought its
    images): the live view of a triggered camera shows them instead of reading one itself."""


@dataclass(frozen=True)
class ReloadRecord:
    """One reload through the service: ``time`` Unix seconds; ``ok`` false when refused, with
    the validator's ``message``; ``config_hash`` of the configuration now served ("" if refused)."""

    time: float
    ok: bool
    config_hash: str
    message: str = ""


@dataclass(frozen=True)
class CaptureRequest:
    """``count`` distinct frames from server camera ``camera``; ``encoding`` compresses the
    colour frames (None: raw); ``max_reply_bytes``: what the asker can receive (None: only the
    service's budget bounds it). Times as in :class:`InspectRequest`."""

    camera: str
    count: int = 1
    depth: bool = False
    encoding: FrameEncoding | None = None
    max_reply_bytes: int | None = None
    arrived: float = field(default_factory=time.monotonic)
    deadline: float | None = None


@dataclass(frozen=True)
class CapturedFrame:
    """One frame: ``color`` BGR/gray uint8 (``encoded``: its compressed bytes when asked for),
    ``depth`` (H, W) uint16 millimetres when asked for, ``timestamp`` in Unix seconds."""

    color: Image
    timestamp: float
    depth: Image | None = None
    encoded: bytes | None = None


@dataclass(frozen=True)
class CaptureReply:
    camera: str
    frames: tuple[CapturedFrame, ...]
    intrinsics: dict[str, Any] | None


def _inspection_of(request: InspectRequest, catalog: Catalog) -> Inspection:
    """The inspection ``request`` runs: its prepared one, else the catalog's
    (UNKNOWN_INSPECTION)."""
    if request.prepared is not None:
        return request.prepared
    return catalog.inspection(request.inspection)


# ----------------------------------------------------------------------------- the service


class InspectionService:
    """Runs inspections and captures for every front-end. See the module.

    ``reloader`` builds the catalog of a re-read configuration (raises ``ConfigError``); None
    when the service was not started from a configuration file.
    """

    def __init__(
        self,
        catalog: Catalog,
        settings: ServiceSettings | None = None,
        *,
        results: ResultStore | None = None,
        reloader: Callable[[], Catalog] | None = None,
    ) -> None:
        self.settings = settings or ServiceSettings()
        self._catalog = catalog
        self.results = results
        self.reloader = reloader
        self.processes = (
            ProcessLane(
                self.settings.workers,
                nice=self.settings.main_lane_nice,
                policy=self.settings.main_lane_policy,
                opencv_threads=self.settings.opencv_thread_count(),
            )
            if self.settings.process_inspections
            else None
        )
        """Worker processes for the inspections that hold the GIL (started on first use)."""
        self.pool = WorkPool(
            self.settings.workers,
            self.settings.queue_depth,
            fast_workers=self.settings.fast_workers,
            fast_lane_ms=self.settings.fast_lane_ms,
            max_queue_ms=self.settings.max_queue_ms,
            main_lane_nice=self.settings.main_lane_nice,
        )
        self.loop_costs = LoopCosts()
        """Each inspection's slowest recent time per pixel to get its images and run,
        wherever it ran (ms, :class:`RunClock`): what a run could hold the event loop for
        (:meth:`_runs_inline`). Forgotten when the catalog is replaced."""
        self.budget = ByteBudget(self.settings.max_buffered_bytes)
        self.door = FrontDoor(self.settings.max_connections_total)
        """What every front-end's connections and sign-ins go through (:mod:`.door`)."""
        self._observers: list[Callable[[InspectionRecord], None]] = []
        self.health_parts: dict[str, Callable[[], dict[str, Any]]] = {}
        """Reports of front-ends that hold results of their own (``mqtt``: its spool), each
        a dict with ``ok``: merged into :meth:`health` under its name."""
        self._reload_lock = threading.Lock()
        self.busy_count = 0
        """BUSY answers of :meth:`admit` and the pool since start (for health and metrics)."""
        self.reloads: deque[ReloadRecord] = deque(maxlen=50)
        self.on_reloaded: Callable[[Catalog], None] | None = None
        """Called (in the reload's thread) once a reloaded catalog is the one served."""
        """The latest reloads through :meth:`reload`, oldest first, refused ones too."""
        self.reload_counts = {True: 0, False: 0}
        """Reloads since start by outcome (True: done)."""

    # ------------------------------------------------------------------ catalog, lifecycle

    @property
    def catalog(self) -> Catalog:
        """The catalog new requests are served with."""
        return self._catalog

    def replace_catalog(self, catalog: Catalog) -> None:
        """Serve new requests with ``catalog``; requests already running finish on the old,
        whose lease they hold (retiring it is its owner's job, see CellRuntime.reload)."""
        self._catalog = catalog
        # An inspection changed under the same name costs what it costs now: measured again.
        self.loop_costs = LoopCosts()

    async def reload(self) -> Catalog:
        """Re-read the configuration through ``reloader`` in a thread (building a catalog opens
        cameras; the catalog it replaces closes its own later) and serve new requests with it.
        INVALID_ARGUMENT without a reloader; CONFIG_INVALID when the configuration is refused
        (the old one stays)."""
        if self.reloader is None:
            raise InvalidArgument("this server was started without a configuration file")
        return await asyncio.to_thread(self._reload)

    def _reload(self) -> Catalog:
        assert self.reloader is not None
        with self._reload_lock:  # SIGHUP, RELOAD and a console may ask at once
            try:
                catalog = self.reloader()
            except CellvisionError as exc:
                self._reloaded(ReloadRecord(time.time(), False, "", exc.message))
                raise
            except ValueError as exc:  # ConfigError
                self._reloaded(ReloadRecord(time.time(), False, "", str(exc)))
                raise ConfigInvalid(str(exc)) from None
            self.replace_catalog(catalog)
            notes = "; ".join(catalog.notes)
            self._reloaded(ReloadRecord(time.time(), True, catalog.config_hash, notes))
            if self.on_reloaded is not None:  # only now is the new catalog the one served
                self.on_reloaded(catalog)
        log.info("configuration reloaded (config hash %s)", catalog.config_hash)
        return catalog

    def _reloaded(self, record: ReloadRecord) -> None:
        self.reloads.append(record)
        self.reload_counts[record.ok] += 1

    def close(self) -> None:
        """Stop the worker pool (running jobs finish in their threads) and the processes."""
        self.pool.shutdown()
        if self.processes is not None:
            self.processes.shutdown()

    # ------------------------------------------------------------------ observers, health

    def subscribe(self, observer: Callable[[InspectionRecord], None]) -> Callable[[], None]:
        """Call ``observer`` (on the event loop) with every answered inspection; returns the
        function that unsubscribes it. An observer that raises is logged, never fails a
        request."""
        self._observers.append(observer)

        def unsubscribe() -> None:
            if observer in self._observers:
                self._observers.remove(observer)

        return unsubscribe

    def _notify(self, record: InspectionRecord) -> None:
        for observer in list(self._observers):
            try:
                observer(record)
            except Exception:
                log.exception("an observer of results failed")

    def health(self) -> dict[str, Any]:
        """``ok`` false once the result log lost a row since start (see
        :meth:`ResultLog.health`), the admission counters and the log's; and each of
        :attr:`health_parts` (``ok`` false when one of them is not ok)."""
        report: dict[str, Any] = {"ok": True, "admission": self.admission_counters()}
        if self.results is not None:
            result_log = self.results.health()
            report["ok"] = bool(result_log["ok"])
            report["result_log"] = result_log
        for name, part in self.health_parts.items():
            report[name] = part()
            report["ok"] = report["ok"] and bool(report[name].get("ok", True))
        return report

    def admission_counters(self) -> dict[str, Any]:
        """What bounds the service now: worker slots and the byte budget."""
        return {
            "pool_admitted": self.pool.admitted,
            "pool_capacity": self.pool.capacity,
            "pool_waiting": self.pool.waiting,
            "buffered_bytes": self.budget.used,
            "buffered_bytes_peak": self.budget.peak,
            "max_buffered_bytes": self.budget.limit,
            "buffer_refusals": self.budget.refused,
        }

    # ------------------------------------------------------------------ admission

    @staticmethod
    def request_key(request: InspectRequest) -> str:
        """The pool's and the cost model's key of ``request``: its inspection's name, a try's
        its own (:func:`~.admission.try_key`)."""
        if request.prepared is not None and request.config is not None:
            # Drafts may have any name: their costs are learnt per type, a bounded set.
            return try_key(f"draft {request.prepared.type}")
        if request.request_class == "try":
            return try_key(request.inspection)
        return request.inspection

    def admit(
        self,
        *,
        work: bool = True,
        body_bytes: int = 0,
        key: str | None = None,
        request_class: RequestClass = "production",
    ) -> Admission:
        """Reserve what a request will hold, before its body is read: a worker slot (``work``;
        ``key``: the inspection's name, which decides its lane and weight) and ``body_bytes`` of
        the budget. Raises BUSY, with a retry-after hint, when either is taken. The front-end
        hands the admission to :meth:`inspect` / :meth:`capture` and releases it once its reply
        is sent (a reply's bytes are added to it)."""
        admission = Admission(self.pool, self.budget)
        if work and not admission.take_slot(key):
            raise self._busy(key)
        if request_class == "try":
            if body_bytes > 0 and not admission.take_bytes(body_bytes, share=TRY_BUDGET_SHARE):
                admission.release()
                raise self._memory_busy(
                    "tries' request bodies",
                    body_bytes,
                    key,
                    f"; tries may hold {TRY_BUDGET_SHARE:.0%} of them, production keeps the rest",
                )
            return admission
        self._take_bytes(admission, body_bytes, key)
        return admission

    async def admit_when_free(self, key: str | None, *, deadline: float | None = None) -> Admission:
        """A worker slot for ``key`` (an inspection's name), waiting for one in its lane's
        queue (first come, first served) at most ``admission_wait_s`` and not past
        ``deadline`` (monotonic seconds); then BUSY with a retry-after hint. For front-ends
        whose request has already arrived whole (a line-protocol trigger)."""
        reserved = self.pool.reserve_or_wait(key)
        if isinstance(reserved, Waiter):
            timeout_s = self.settings.admission_wait_s
            if deadline is not None:
                timeout_s = min(timeout_s, max(deadline - time.monotonic(), 0.0))
            slot = await reserved.wait(timeout_s)
            if slot is None:
                if deadline is not None and time.monotonic() >= deadline:
                    raise DeadlineExceeded("the deadline passed while no worker slot was free")
                raise self._busy(key, waited=True)
            reserved = slot
        admission = Admission(self.pool, self.budget)
        admission.hold_slot(reserved)
        return admission

    async def slot_after(self, waiter: Waiter) -> Slot:
        """Wait for ``waiter``'s slot (from :meth:`WorkPool.reserve_or_wait`), at most
        ``admission_wait_s``; then BUSY with a retry-after hint."""
        slot = await waiter.wait(self.settings.admission_wait_s)
        if slot is None:
            raise self._busy(waiter.key, waited=True)
        return slot

    def _take_bytes(self, admission: Admission, body_bytes: int, key: str | None) -> None:
        if body_bytes > 0 and not admission.take_bytes(body_bytes):
            admission.release()
            raise self._memory_busy("request bodies", body_bytes, key)

    def _memory_busy(self, what: str, size: int, key: str | None, hint: str = "") -> Busy:
        """The BUSY of a reservation the byte budget could not take (``what``: request bodies
        or replies), counted, with its size and a retry-after hint."""
        self.busy_count += 1
        return Busy(
            f"the server's memory for {what} is taken ({self.budget.used} of "
            f"{self.budget.limit} bytes{hint}); try again",
            details={"size": size, "retry_after_ms": self.retry_after_ms(key)},
        )

    def retry_after_ms(self, key: str | None) -> int:
        """When a request for ``key`` refused now could be admitted: the work queued ahead of
        it in its lane over the lane's threads, in milliseconds (at least 1)."""
        return max(1, min(round(self.pool.expected_wait_ms(key)), 60_000))

    def _busy(self, key: str | None, *, waited: bool = False) -> Busy:
        self.busy_count += 1
        how = f" after waiting {self.settings.admission_wait_s:g} s" if waited else ""
        return Busy(
            f"{self.pool.full_because(key)}{how}; try again",
            details={"retry_after_ms": self.retry_after_ms(key)},
        )

    # ------------------------------------------------------------------ inspect

    async def inspect(
        self, request: InspectRequest, *, admission: Admission | None = None
    ) -> InspectReply:
        """Run ``request``: its images (or a capture), the named inspection (in the pool, or on
        the event loop when it is cheap: :meth:`_runs_inline`), the result log, the overlay.
        Without ``admission`` a slot is taken here (BUSY when none is free) and given back when
        done."""
        own = admission is None
        key = self.request_key(request)
        held = self.admit(key=key) if admission is None else admission
        try:
            # The lease keeps the catalog's cameras open until this request is done with them.
            with self._catalog.lease_newest() as lease:
                return await self._inspect(request, lease.catalog, held)
        finally:
            if own:
                held.release()

    async def _inspect(
        self, request: InspectRequest, catalog: Catalog, admission: Admission
    ) -> InspectReply:
        catalog.camera(_inspection_of(request, catalog).camera)
        # From here on the request has an inspection and a camera to log an error row under
        # (SPEC §6.3): an unknown inspection or camera has none.
        rows = _RowOnce()
        if not request.record:
            rows.claim()  # claimed for nobody: neither the run nor an error writes a row
        try:
            return await self._inspect_known(request, catalog, admission, rows)
        except (Busy, ShuttingDown):
            raise  # refused before it ran, not a run to log (and no disk load under overload)
        except CellvisionError as exc:
            await self._error_row(request, catalog, rows, f"{exc.code.name}: {exc.message}")
            raise
        except Exception as exc:  # a bug: the front-end answers INTERNAL_ERROR, logged as such
            await self._error_row(request, catalog, rows, f"INTERNAL_ERROR: {exc!r}")
            raise

    async def _error_row(
        self, request: InspectRequest, catalog: Catalog, rows: _RowOnce, error: str
    ) -> None:
        """Log a request that ends in ``error`` unless its run already wrote its row."""
        if self.results is None or not rows.claim():
            return
        inspection = _inspection_of(request, catalog)
        entry = _entry(request, catalog, inspection.name, inspection.camera)
        # Its duration is from the request's arrival (perf_counter and monotonic both tick
        # in seconds; only their difference is used).
        t0 = time.perf_counter() - (time.monotonic() - request.arrived)
        # The log writes to disk or a database: not on the event loop.
        await asyncio.to_thread(self._record, entry, t0, error=error)

    async def _inspect_known(
        self, request: InspectRequest, catalog: Catalog, admission: Admission, rows: _RowOnce
    ) -> InspectReply:
        inspection = request.prepared
        if inspection is None:
            inspection = catalog.tuned(catalog.inspection(request.inspection), request.options)
        camera = catalog.camera(inspection.camera)
        declared = camera.intrinsics
        needs = ImageNeeds(
            inspection.name,
            inspection.uses_depth,
            self.settings.max_image_pixels,
            None if declared is None else (declared.width, declared.height),
        )
        images = request.images
        sources: list[str] = []  # the files a folder camera read: which images this is about
        acquire: Callable[[], InspectionInput]
        if images is not None:
            # Images in the request are inspected whatever the camera: a tool camera's, or a
            # stored image run through a fixed camera's inspection (SPEC §6.3).
            given = images

            def acquire() -> InspectionInput:
                loaded = given if isinstance(given, Images) else given(needs)
                check_images(loaded, needs)
                return InspectionInput(loaded.color, loaded.depth, camera.intrinsics)

        elif camera.source == "request":
            raise BadImage(
                f"inspection {inspection.name!r} uses camera {camera.name!r}, whose images "
                "arrive in the request, and the request has none"
            )
        else:
            timeout_s = self._capture_timeout(request.deadline)

            def acquire() -> InspectionInput:
                frames = camera.grab_many(inspection.frames, timeout_s=timeout_s)
                sources.extend(f.source for f in frames if f.source is not None)
                depth = tuple(f.depth for f in frames if f.depth is not None)
                return InspectionInput(
                    frames[0].color, depth if inspection.uses_depth else (), camera.intrinsics
                )

        in_process = inspection.name in self.settings.process_inspections
        captured: list[Images] = []

        size: list[tuple[int, int]] = []  # the image's (width, height), for observers

        def prepare() -> tuple[InspectionInput, ResultEntry | None, bool]:
            """The images, checked, and the result log's entry for them (None: no row is
            written); whether the run draws an overlay."""
            image = replace(acquire(), deadline=request.deadline)
            size.append((int(image.color.shape[1]), int(image.color.shape[0])))
            if request.images is None:
                captured.append(Images(image.color, image.depth))
            if request.overlay is not None:
                self._admit_overlay(image.color, admission)
            entry = None
            if self.results is not None and request.record:
                entry = _entry(request, catalog, inspection.name, camera.name, image.color)
            # The log stores the overlay beside the input it keeps (drawing costs ~0.1 ms; the
            # policy's pass/fail choice is only known after the run). Not for very large
            # images: a colour copy of 16 MP is 48 MB more per worker, for a picture the
            # console shows at screen size; their rows keep the input only.
            draw = request.overlay is not None or (
                request.record
                and self.results is not None
                and self.results.keeps_images
                and image.color.shape[0] * image.color.shape[1] <= STORED_OVERLAY_MAX_PIXELS
            )
            return image, entry, draw

        def run(image: InspectionInput, draw: bool) -> InspectionOutcome:
            if self.processes is not None and in_process:
                ran: InspectionOutcome = self.processes.run(inspection, image, overlay=draw)
                return ran
            return inspection.run(image, overlay=draw)

        def failed(entry: ResultEntry | None, t0: float, exc: CellvisionError) -> None:
            if entry is not None and rows.claim():
                self._record(entry, t0, error=f"{exc.code.name}: {exc.message}")

        def finish(
            outcome: InspectionOutcome, entry: ResultEntry | None, t0: float
        ) -> tuple[InspectionOutcome, Overlay | None, bool | None, int | None]:
            """The result log's row and the overlay's encoding: disk and CPU work that is
            never done on the event loop."""
            if sources:
                outcome = replace(outcome, data={**outcome.data, "source_files": sources})
            stored: bool | None = None
            row_id: int | None = None
            # A run its request gave up on (DEADLINE_EXCEEDED) already has its error row.
            if entry is not None and rows.claim():
                stored, row_id = self._record_row(
                    replace(
                        entry, passed=outcome.passed, data=outcome.data, overlay=outcome.overlay
                    ),
                    t0,
                )
            overlay = None
            if request.overlay is not None and outcome.overlay is not None:
                # Encoding is CPU work too: here, not on the event loop of every connection.
                overlay = _overlay(outcome.overlay, request.overlay)
            return outcome, overlay, stored, row_id

        # The table this request learns into (a reload starts a new one: runs of the old
        # catalog must not teach it).
        loop_costs = self.loop_costs

        def work() -> tuple[InspectionOutcome, float, Overlay | None, bool | None, int | None]:
            # What a run would cost on the loop: loading there is only ever viewing raw
            # pixels, so a decode or a camera's grab here is not counted.
            started = RunClock(on_loop=False) if cheap else None
            image, entry, draw = prepare()
            started = started or RunClock(on_loop=False)
            t0 = time.perf_counter()
            try:
                outcome = run(image, draw)
            except Exception as exc:  # a bug that burnt the CPU first counts as much
                loop_costs.observe(loop_key, started.cost_ms(), input_bytes(image))
                if isinstance(exc, CellvisionError):
                    failed(entry, t0, exc)
                raise
            compute_ms = (time.perf_counter() - t0) * 1000.0
            loop_costs.observe(loop_key, started.cost_ms(), input_bytes(image))
            outcome, overlay, stored, row_id = finish(outcome, entry, t0)
            return outcome, compute_ms, overlay, stored, row_id

        key = self.request_key(request)
        loop_key = self._loop_key(request, key)
        cheap = loads_cheaply(request.images)
        if not in_process and self._runs_inline(request, loop_key, loop_costs):
            outcome, compute_ms, overlay, stored, row_id = await self._inline(
                prepare,
                run,
                failed,
                finish,
                request,
                admission,
                hold=catalog,
                key=key,
                loop_key=loop_key,
                loop_costs=loop_costs,
            )
        else:
            outcome, compute_ms, overlay, stored, row_id = await self._in_pool(
                work, request.arrived, request.deadline, admission, hold=catalog, key=key
            )
        reply = InspectReply(
            inspection.name,
            camera.name,
            outcome.passed,
            outcome.data,
            compute_ms,
            (time.monotonic() - request.arrived) * 1000.0,
            catalog.config_hash,
            stored,
            overlay,
            row_id,
            size[0] if size else None,
        )
        self._notify(InspectionRecord(request, reply, captured[0] if captured else None))
        return reply

    def _loop_key(self, request: InspectRequest, key: str) -> str:
        """What :attr:`loop_costs` knows a request's run by: its pool key, and whether the run
        draws an overlay (asked for, or kept by the result log)."""
        draws = request.overlay is not None or (
            request.record and self.results is not None and self.results.keeps_images
        )
        return f"{key} +overlay" if draws else key

    def _runs_inline(self, request: InspectRequest, loop_key: str, costs: LoopCosts) -> bool:
        """Whether ``request`` runs on the event loop itself: a production inspection without
        options (they may make it another computation), whose images came in the request as
        raw pixels (nothing to decode, no camera to wait for), and whose slowest recent cost
        per byte of image for that (viewing the images, checks, the run, drawing) makes at
        most ``inline_ms`` on this request's images, no larger than the largest measured
        (:class:`~.admission.LoopCosts`). A thread hop costs
        two wake-ups and a hand-over of the GIL, more than such a run; the result log's row
        and an overlay's encoding still go to a thread."""
        limit = self.settings.inline_ms
        if limit <= 0 or request.request_class != "production" or request.prepared is not None:
            return False
        if request.options or not loads_cheaply(request.images):
            return False
        cost = costs.estimate(loop_key, request_bytes(request.images))
        return cost is not None and cost <= limit

    async def _inline(
        self,
        prepare: Callable[[], tuple[InspectionInput, ResultEntry | None, bool]],
        run: Callable[[InspectionInput, bool], InspectionOutcome],
        failed: Callable[[ResultEntry | None, float, CellvisionError], None],
        finish: Callable[
            [InspectionOutcome, ResultEntry | None, float],
            tuple[InspectionOutcome, Overlay | None, bool | None, int | None],
        ],
        request: InspectRequest,
        admission: Admission,
        *,
        hold: Catalog,
        key: str,
        loop_key: str,
        loop_costs: LoopCosts,
    ) -> tuple[InspectionOutcome, float, Overlay | None, bool | None, int | None]:
        """:meth:`_in_pool` for a cheap run (:meth:`_runs_inline`): ``prepare`` and ``run``
        here, on the event loop, on the slot ``admission`` holds; ``finish`` (the result
        log, the overlay's encoding) and ``failed`` (an error's row) in the slot's lane
        thread when they have work to do, awaited until the request's deadline."""
        deadline = request.deadline
        if deadline is not None and deadline <= time.monotonic():
            budget_ms = round((deadline - request.arrived) * 1000.0, 3)
            raise DeadlineExceeded(f"not done within the request's deadline of {budget_ms:g} ms")
        slot = admission.hand_slot_to_pool() or self.pool.try_reserve(key)
        if slot is None:
            raise self._busy(key)
        loop = asyncio.get_running_loop()
        lease = hold.acquire()

        def done(_: object = None) -> None:
            lease.release()
            self.pool.release(slot)

        handed_over = False  # the slot and the lease go with work handed to a thread
        try:
            started = RunClock(on_loop=True)
            image, entry, draw = prepare()
            t0 = time.perf_counter()
            try:
                outcome = run(image, draw)
            except Exception as exc:  # a bug that burnt the CPU first counts as much
                loop_costs.observe(loop_key, started.cost_ms(), input_bytes(image))
                if entry is None or not isinstance(exc, CellvisionError):
                    raise  # (another error's row is written by the caller)
                failing = loop.run_in_executor(slot.lane.executor, failed, entry, t0, exc)
                failing.add_done_callback(done)
                handed_over = True
                await self._until(failing, request.arrived, deadline)
                raise
            compute_ms = (time.perf_counter() - t0) * 1000.0
            loop_costs.observe(loop_key, started.cost_ms(), input_bytes(image))
            self.pool.costs.observe(key, started.wall_ms())
            if deadline is not None and time.monotonic() > deadline:
                # As in a worker: a run done after its deadline is not answered as a result
                # (the request's error row is written by the caller).
                budget_ms = round((deadline - request.arrived) * 1000.0, 3)
                raise DeadlineExceeded(
                    f"not done within the request's deadline of {budget_ms:g} ms"
                )
            if request.overlay is None and entry is None:
                finished, overlay, stored, row_id = finish(outcome, entry, t0)  # nothing to do
                return finished, compute_ms, overlay, stored, row_id
            finishing = loop.run_in_executor(slot.lane.executor, finish, outcome, entry, t0)
            finishing.add_done_callback(done)
            handed_over = True
            finished, overlay, stored, row_id = await self._until(
                finishing, request.arrived, deadline
            )
            return finished, compute_ms, overlay, stored, row_id
        finally:
            if not handed_over:
                done()

    async def _until(
        self, future: asyncio.Future[_T], arrived: float, deadline: float | None
    ) -> _T:
        """``future``'s result, or DEADLINE_EXCEEDED once ``deadline`` (monotonic seconds) has
        passed. The work goes on whatever happens to the caller, a cancellation too (it holds
        its slot, its lease and its result log row until it ends: a job cancelled while queued
        would never give them back)."""
        if deadline is None:
            return await asyncio.shield(future)
        budget_ms = round((deadline - arrived) * 1000.0, 3)
        try:
            loop = asyncio.get_running_loop()
            # The loop's clock is time.monotonic(): the deadline is absolute on it.
            async with asyncio.timeout_at(loop.time() + (deadline - time.monotonic())):
                return await asyncio.shield(future)
        except TimeoutError:
            raise DeadlineExceeded(
                f"not done within the request's deadline of {budget_ms:g} ms"
            ) from None

    def _admit_overlay(self, color: Image, admission: Admission) -> None:
        """Reserve the bytes of the overlay a reply will carry before the inspection runs: it
        is drawn in colour at the input's size, and its PNG is at most about that raw size
        (noise does not compress). BUSY when the service's memory for replies is taken, so
        that clients that ask for overlays and read slowly cannot hold more than the budget."""
        height, width = color.shape[:2]
        estimate = width * height * 3 + REPLY_OVERHEAD
        if not admission.take_bytes(estimate):
            hint = f"; an overlay of {width}x{height} needs about {estimate}, ask without one"
            raise self._memory_busy("replies", estimate, None, hint)

    def _record(self, entry: ResultEntry, t0: float, *, error: str | None = None) -> bool | None:
        """Log one run before its answer is sent; return whether the row was written (None
        without a result log). The log never raises: a full disk is counted and logged, the
        answer still goes out, with ``stored: false`` (SPEC §6.3), and :meth:`health` turns
        not ok. An error row that fails is counted the same way (its error carries no flag)."""
        return self._record_row(entry, t0, error=error)[0]

    def _record_row(
        self, entry: ResultEntry, t0: float, *, error: str | None = None
    ) -> tuple[bool | None, int | None]:
        """:meth:`_record`, and the row's id when the log gave one (a PostgreSQL log that
        spooled the row gives none yet)."""
        if self.results is None:
            return None, None
        duration_ms = (time.perf_counter() - t0) * 1000.0
        row_id = self.results.record(replace(entry, duration_ms=duration_ms, error=error))
        return row_id is not None, (row_id if row_id else None)

    def _capture_timeout(self, deadline: float | None) -> float:
        if deadline is None:
            return self.settings.capture_timeout_s
        return max(min(self.settings.capture_timeout_s, deadline - time.monotonic()), 0.0)

    # ------------------------------------------------------------------ capture

    async def capture(
        self, request: CaptureRequest, *, admission: Admission | None = None
    ) -> CaptureReply:
        """``count`` distinct frames from a server camera.

        The reply is bounded in bytes, not in frames: it must fit ``max_reply_bytes`` and the
        service's byte budget, checked before the frames are taken (from the first frame); its
        bytes are added to ``admission`` (released by the front-end once the reply is sent)."""
        own = admission is None
        held = self.admit(key=capture_key(request.camera)) if admission is None else admission
        try:
            with self._catalog.lease_newest() as lease:
                return await self._capture(request, lease.catalog, held)
        finally:
            if own:
                held.release()

    async def _capture(
        self, request: CaptureRequest, catalog: Catalog, admission: Admission
    ) -> CaptureReply:
        camera = catalog.camera(request.camera)
        if camera.source == "request":
            raise InvalidArgument(
                f"camera {camera.name!r} gets its images from the request: it cannot capture"
            )
        if request.depth and not camera.has_depth:
            raise InvalidArgument(f"camera {camera.name!r} has no depth")
        timeout_s = self._capture_timeout(request.deadline)

        def work() -> list[CapturedFrame]:
            frames = _capture_frames(
                camera,
                request.count,
                timeout_s,
                lambda first: self._admit_reply(request, first, admission),
            )
            out = []
            for frame in frames:
                encoded = None
                if request.encoding is not None:
                    encoded = encode_image(frame.color, "." + request.encoding)
                depth = frame.depth if request.depth else None
                out.append(CapturedFrame(frame.color, frame.timestamp, depth, encoded))
            return out

        frames = await self._in_pool(
            work,
            request.arrived,
            request.deadline,
            admission,
            hold=catalog,
            key=capture_key(camera.name),
        )
        intrinsics = None if camera.intrinsics is None else camera.intrinsics.to_dict()
        return CaptureReply(camera.name, tuple(frames), intrinsics)

    def _admit_reply(
        self, request: CaptureRequest, first: CameraFrame, admission: Admission
    ) -> None:
        """Refuse a capture whose reply could not be received or held, before grabbing the
        rest of its frames. Raw sizes bound the encoded ones (checked again when sent)."""
        per_frame = first.color.nbytes
        if request.encoding is not None:
            # Compressed frames of one scene have similar sizes; twice the first one's, at most
            # raw, bounds them (and the encoded reply is checked again before it is sent).
            encoded = len(encode_image(first.color, "." + request.encoding))
            per_frame = min(per_frame, 2 * encoded)
        if request.depth and first.depth is not None:
            per_frame += first.depth.nbytes
        estimate = per_frame * request.count + REPLY_OVERHEAD
        budget = self.settings.max_buffered_bytes
        limit = budget if request.max_reply_bytes is None else min(request.max_reply_bytes, budget)
        if estimate > limit:
            who = (
                "the client accepts (HELLO max_frame_bytes)"
                if limit == request.max_reply_bytes
                else "the server may hold for replies (max_buffered_bytes)"
            )
            raise InvalidArgument(
                f"{request.count} frames of about {per_frame} bytes each make a reply of about "
                f"{estimate} bytes, more than the {limit} bytes {who}; ask for fewer frames "
                "or a compressed encoding",
                details={"size": estimate, "max_size": limit},
            )
        if not admission.take_bytes(estimate):
            raise self._memory_busy("replies", estimate, capture_key(request.camera))

    # ------------------------------------------------------------------ the pool

    async def _in_pool(
        self,
        fn: Callable[[], _T],
        arrived: float,
        deadline: float | None,
        admission: Admission,
        *,
        hold: Catalog,
        key: str,
    ) -> _T:
        """Run ``fn`` in the pool, on the slot ``admission`` reserved if it holds one, and wait
        for it until ``deadline``. ``hold``: the catalog ``fn`` uses, leased until ``fn``
        returns, which may be after the request gave up (its deadline passed)."""
        budget_ms = None if deadline is None else round((deadline - arrived) * 1000.0, 3)
        if deadline is not None and deadline <= time.monotonic():
            # Already late (it waited to be read, or in a front-end): do not start the work.
            raise DeadlineExceeded(f"not done within the request's deadline of {budget_ms:g} ms")
        lease = hold.acquire()

        def leased() -> _T:
            with lease:
                return fn()

        slot = admission.hand_slot_to_pool() or self.pool.try_reserve(key)
        if slot is None:
            lease.release()
            raise self._busy(key)
        return await self._until(self.pool.submit(slot, leased), arrived, deadline)


# ----------------------------------------------------------------------------- helpers


BLOCKED_MS = 5.0
"""A run in a worker whose wall time exceeds its CPU time by more than this blocked on
something (a lock, I/O, a sleep): its wall time is what it would hold the event loop for."""


class RunClock:
    """What a run would hold the event loop for (ms).

    On the loop itself: its CPU time, which a preemption under load does not inflate, unless
    the thread gave up the CPU on its own during the run (blocked on a lock, I/O, a sleep, the
    GIL: a voluntary context switch), when the loop was held for the whole wall time. In a
    worker thread: its CPU time too (its wall time counts waits for the GIL, which the loop
    holds meanwhile), unless it waited more than :data:`BLOCKED_MS` beyond it."""

    def __init__(self, *, on_loop: bool) -> None:
        self._on_loop = on_loop
        self._wall = time.perf_counter()
        self._cpu = time.thread_time()
        self._switches = _voluntary_switches() if on_loop else 0

    def wall_ms(self) -> float:
        return (time.perf_counter() - self._wall) * 1000.0

    def cost_ms(self) -> float:
        cpu_ms = (time.thread_time() - self._cpu) * 1000.0
        wall_ms = self.wall_ms()
        if self._on_loop:
            blocked = _voluntary_switches() != self._switches
        else:
            blocked = wall_ms - cpu_ms > BLOCKED_MS
        return max(wall_ms, cpu_ms) if blocked else cpu_ms


def _voluntary_switches() -> int:
    """This thread's voluntary context switches so far (Linux counts them per thread)."""
    return resource.getrusage(resource.RUSAGE_THREAD).ru_nvcsw


def _entry(
    request: InspectRequest,
    catalog: Catalog,
    inspection: str,
    camera: str,
    image: Image | None = None,
) -> ResultEntry:
    """The result log's row for ``request`` before its outcome is known (not passed, no
    data): the run fills those in, an error row adds its error."""
    return ResultEntry(
        time=time.time(),
        inspection=inspection,
        camera=camera,
        passed=False,
        data={},
        duration_ms=0.0,
        config_hash=catalog.config_hash,
        request_id=request.request_id,
        peer=request.peer,
        image=image,
        options=request.options,
        config=request.config,
        operator=request.operator,
    )


class _RowOnce:
    """Who writes a request's row in the result log: the run (its verdict, or its error) or
    the request's error path, whichever claims it first (a request given up at its deadline
    while its run goes on gets one row, not two). Claimed from threads and the event loop."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._claimed = False

    def claim(self) -> bool:
        """True the first time only."""
        with self._lock:
            if self._claimed:
                return False
            self._claimed = True
            return True


def capture_key(camera: str) -> str:
    """The cost model's key for CAPTURE on ``camera`` (inspections use their names)."""
    return f"capture:{camera}"


def check_images(images: Images, needs: ImageNeeds) -> None:
    """Refuse images an inspection cannot take, whoever decoded them: BAD_IMAGE naming the
    cause, IMAGE_TOO_LARGE beyond the pixel limit."""
    color = images.color
    if not isinstance(color, np.ndarray) or color.dtype != np.uint8:
        dtype = getattr(color, "dtype", type(color).__name__)
        raise BadImage(f"the colour image must be 8-bit (gray8, bgr8, 8-bit PNG/JPEG), got {dtype}")
    if not (color.ndim == 2 or (color.ndim == 3 and color.shape[2] == 3)):
        raise BadImage(f"the colour image must be (H, W) or (H, W, 3), got shape {color.shape}")
    height, width = color.shape[:2]
    if width * height > needs.max_pixels:
        raise ImageTooLarge(
            f"the colour image has {width}x{height} = {width * height} pixels, the limit is "
            f"{needs.max_pixels}",
            details=too_large_details(width, height, needs.max_pixels),
        )
    check_image_size(width, height, needs)
    if images.depth and not needs.depth:
        raise BadImage(
            f"inspection {needs.inspection!r} takes no depth image, the request has "
            f"{len(images.depth)}"
        )
    for index, frame in enumerate(images.depth):
        if frame.dtype != np.uint16 or frame.ndim != 2:
            raise BadImage(
                f"depth image {index} must be uint16 millimetres (depth16 or 16-bit PNG), "
                f"got {frame.dtype} with shape {frame.shape}"
            )
        if frame.shape != color.shape[:2]:
            raise BadImage(
                f"depth image {index} is {frame.shape[1]}x{frame.shape[0]}, the colour image "
                f"is {width}x{height}: they must be registered"
            )


def check_image_size(width: int, height: int, needs: ImageNeeds) -> None:
    """BAD_IMAGE, naming both sizes, when a colour image of ``width`` x ``height`` pixels is not
    the size its camera's intrinsics are for (SPEC §4.1); a loader may call it with a file
    header's size, before it decodes anything."""
    if needs.size is None or (width, height) == needs.size:
        return
    # The camera's intrinsics are for its own image size: millimetres, poses and the base
    # frame computed from an image of another size would be silently wrong.
    raise BadImage(
        f"the colour image is {width}x{height}, the camera's intrinsics are for "
        f"{needs.size[0]}x{needs.size[1]}: send an image of the camera's size",
        details={
            "width": width,
            "height": height,
            "expected_width": needs.size[0],
            "expected_height": needs.size[1],
        },
    )


def encode_image(image: Image, suffix: str) -> bytes:
    """``image`` as the bytes of an image file with extension ``suffix`` (``".png"``)."""
    ok, buffer = cv2.imencode(suffix, image)
    if not ok:
        raise ValueError(f"OpenCV could not encode the image as {suffix}")
    return bytes(buffer.tobytes())


def _overlay(image: Image, wanted: str) -> Overlay:
    if wanted == "array":
        return Overlay(image)
    return Overlay(image, wanted, encode_image(image, wanted))


def _capture_frames(
    camera: Camera, count: int, timeout_s: float, admit: Callable[[CameraFrame], None]
) -> list[CameraFrame]:
    """``count`` distinct successive frames; ``admit(first frame)`` may refuse the rest (a reply
    too large) before they are taken."""
    deadline = time.monotonic() + timeout_s
    first = camera.grab_many(1, timeout_s=timeout_s)[0]
    admit(first)
    frames = [first]
    try:
        while len(frames) < count:
            remaining = max(deadline - time.monotonic(), 0.0)
            frames.append(camera.grab(timeout_s=remaining, newer_than=frames[-1].index))
    except CellvisionError as exc:
        exc.message = f"got {len(frames)} of {count} frames within {timeout_s:.3g} s: {exc.message}"
        raise
    return frames


__all__ = [
    "CaptureReply",
    "CaptureRequest",
    "CapturedFrame",
    "ImageLoader",
    "ImageNeeds",
    "Images",
    "InspectReply",
    "InspectRequest",
    "InspectionRecord",
    "InspectionService",
    "Overlay",
    "ReloadRecord",
    "check_image_size",
    "check_images",
    "deadline_after",
    "encode_image",
]
