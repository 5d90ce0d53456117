"""Impact before save: a pending change replayed over an inspection's stored images.

One engine for both askers, so that they cannot disagree: the console's impact preview
(``POST /api/inspections/{name}/impact``, :mod:`vision_server.frontends.http_impact`) and the
command line's ``vision-server replay INSPECTION --config changed.yaml``
(:mod:`vision_server.commands.replay`). Each gives it a service, a result log and the changed
inspection; :func:`replay` does the rest the same way for both:

- **The images**: the newest production results of the inspection (console tries left out)
  whose input image the log kept (``results: store_images``; the default, ``failures``, keeps
  the images of failed parts only), newest first, at most ``last`` of them. Rows are read
  through the log's indexed query by inspection, a page at a time (``before_id``), and at most
  :data:`MAX_ROWS_EXAMINED` rows are looked at: never a scan of the whole log. Each image is read
  as a try's ``source: "result"`` reads it: the stored colour image (the log keeps no depth
  frames and no second frame).
- **The baseline** is each row's stored verdict (what happened to that part); a row **flips**
  when the changed inspection's verdict differs from it. Each row's ``config_hash`` is reported,
  and whether it is the running configuration's: a flip on a row stored under another
  configuration may come from that older change, not from this one.
- **Bounded**: one image at a time through the service's try lane (``request_class="try"``,
  its admission, its one low-priority thread: production keeps its threads), a deadline for the
  whole run, no row written to the result log (:attr:`InspectRequest.record`), and only the
  flipped rows' overlays kept, at most :data:`MAX_OVERLAYS`, as small JPEG thumbnails. A caller
  that goes away cancels the run (the awaiting task is cancelled between or during images).

Times are Unix seconds (rows) or ``time.monotonic()`` seconds (deadlines); sizes are pixels.
"""

from __future__ import annotations

import asyncio
import base64
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2

from protocol import (
    CellvisionError,
    DeadlineExceeded,
    ImageEncoding,
    ImagePayload,
    InvalidArgument,
    array_from_payload,
)
from protocol.images import compressed_header

from ..cameras import CameraSettings
from ..config import ConfigError, Tuner, parse_draft
from ..inspections import Inspection
from ..results import TRY_PEER_PREFIX, ProductionRows, ResultStore, StoredResult
from .admission import Admission, Waiter, try_key
from .catalog import Catalog
from .core import (
    ImageLoader,
    ImageNeeds,
    Images,
    InspectionService,
    InspectRequest,
    check_image_size,
)

__all__ = [
    "DEFAULT_LAST",
    "IMPACT_PEER",
    "MAX_LAST",
    "MAX_OVERLAYS",
    "MAX_ROWS_EXAMINED",
    "Change",
    "ChangeRefused",
    "Flip",
    "ImpactReport",
    "ReplayFailure",
    "changed_inspection",
    "replay",
    "stored_image_loader",
]

DEFAULT_LAST = 100
"""Stored images replayed when the asker does not say."""
MAX_LAST = 1000
"""The most stored images one run replays."""
MAX_ROWS_EXAMINED = 20_000
"""The most result rows one run looks at to find its images (the default ``store_images:
failures`` keeps few): the bound on what a run reads of the log, whatever ``last`` is."""
PAGE_ROWS = 500
"""Rows read per query of the log."""
MAX_OVERLAYS = 24
"""Flipped rows whose overlay comes back as a thumbnail; later flips get none (their stored
images remain at ``/api/results/{id}/image.png``)."""
MAX_FAILURES = 20
"""Rows whose replay failed that are listed one by one (all are counted)."""
THUMBNAIL_SIDE_PX = 320
"""The longer side of an overlay thumbnail, pixels."""
THUMBNAIL_JPEG_QUALITY = 80
THUMBNAIL_MARGIN_PX = 48
"""The least margin around an inspection's ROI in a thumbnail, pixels."""
IMPACT_PEER = TRY_PEER_PREFIX + "impact"
"""The peer of every replayed run: a console try's prefix, so that no observer of results (the
Prometheus counters, the running counts) takes a replay for a production result."""


class ChangeRefused(ValueError):
    """A pending change that cannot be run: ``code`` (``INVALID_ARGUMENT`` for options,
    ``CONFIG_INVALID`` for a whole config), ``key`` (the key path at fault, ``""`` if none)."""

    def __init__(self, code: str, message: str, key: str = "") -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.key = key


@dataclass(frozen=True)
class Change:
    """The pending change: ``options`` laid over the inspection as configured (a try's options,
    nested mappings for nested keys), or ``config``, the whole edited inspection mapping."""

    options: Mapping[str, Any] | None = None
    config: Mapping[str, Any] | None = None


def changed_inspection(
    catalog: Catalog,
    name: str,
    change: Change,
    *,
    cameras: Mapping[str, CameraSettings] | None = None,
) -> Inspection:
    """Inspection ``name`` of ``catalog`` with ``change``, validated as a try validates it.

    Options go through :meth:`Catalog.tuned` (the try's own path: INVALID_ARGUMENT naming the
    option). A whole config is read by the configuration's own parser, with the file's folder
    and cameras (ChangeRefused CONFIG_INVALID with the key path); its ``name`` must be
    ``name`` and its ``camera`` the inspection's (the stored images are that camera's).
    ``cameras``: the camera settings to read a config with (default: the file's), e.g. with
    the image size each running camera declares. UNKNOWN_INSPECTION when ``name`` is not
    configured."""
    base = catalog.inspection(name)
    if (change.options is None) == (change.config is None):
        raise ChangeRefused("INVALID_ARGUMENT", "give the change as options or as config, one")
    if change.options is not None:
        try:
            return catalog.tuned(base, change.options)
        except InvalidArgument as exc:
            key = str((exc.details or {}).get("option", ""))
            raise ChangeRefused("INVALID_ARGUMENT", exc.message, key) from None
    config = dict(change.config or {})
    tuner = catalog.tune
    if not isinstance(tuner, Tuner):
        raise ChangeRefused(
            "INVALID_ARGUMENT",
            f"inspection {name!r} does not come from a configuration file: it takes no config",
        )
    for key, wanted in (("name", name), ("camera", base.camera)):
        if config.get(key) != wanted:
            raise ChangeRefused(
                "CONFIG_INVALID",
                f"config -> {key}: must be {wanted!r} (the {key} of the inspection whose stored "
                f"images are replayed), got {config.get(key)!r}",
                key,
            )
    try:
        # The loader's rules for a whole mapping, as a try of it: a file it names must lie in
        # the configuration's folder (a request never makes the server read a path it chose).
        return parse_draft(
            config,
            base_dir=tuner.base_dir,
            cameras=tuner.cameras if cameras is None else cameras,
            written=tuner.written.get(name),
        )
    except ConfigError as exc:
        key = exc.path or ""
        raise ChangeRefused(
            "CONFIG_INVALID", f"config -> {key or '?'}: {exc.reason}", key
        ) from None


# ----------------------------------------------------------------------------- the report


@dataclass(frozen=True)
class Flip:
    """A stored result whose verdict the change turns: ``stored`` and ``new`` verdicts
    (True: pass), the row's ``config_hash`` and whether it is the running configuration's;
    ``overlay`` a ``data:image/jpeg`` thumbnail of the new overlay (None past the first
    :data:`MAX_OVERLAYS` flips)."""

    result_id: int
    time: float
    stored: bool
    new: bool
    stored_config_hash: str
    current_config: bool
    overlay: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            "result_id": self.result_id,
            "time": self.time,
            "stored": _verdict(self.stored),
            "new": _verdict(self.new),
            "stored_config_hash": self.stored_config_hash,
            "current_config": self.current_config,
            "overlay": self.overlay,
        }


@dataclass(frozen=True)
class ReplayFailure:
    """A stored result the change could not be run on: its error ``code`` and ``message``."""

    result_id: int
    code: str
    message: str

    def to_json(self) -> dict[str, Any]:
        return {"result_id": self.result_id, "code": self.code, "message": self.message}


@dataclass
class ImpactReport:
    """What a run found. ``considered``: production results of the inspection looked at;
    ``with_image``: those with a stored image, each replayed; ``flipped`` newest first;
    ``unchanged``: replayed with the stored verdict; ``failed``: replays that ended in an error
    (the first :data:`MAX_FAILURES` listed in ``errors``). ``complete`` is false when the
    deadline stopped the run (``stopped_by``). ``elapsed_s``: wall-clock seconds."""

    inspection: str
    last: int
    current_config_hash: str
    considered: int = 0
    with_image: int = 0
    flipped: list[Flip] = field(default_factory=list)
    unchanged: int = 0
    failed: int = 0
    errors: list[ReplayFailure] = field(default_factory=list)
    rows_limited: bool = False
    """True when :data:`MAX_ROWS_EXAMINED` rows were looked at before ``last`` images were
    found (older images exist perhaps, not replayed)."""
    complete: bool = True
    stopped_by: str | None = None
    elapsed_s: float = 0.0
    with_image_by_verdict: dict[str, int] = field(default_factory=lambda: {"pass": 0, "fail": 0})

    def to_json(self) -> dict[str, Any]:
        """The answer of ``POST /api/inspections/{name}/impact`` and ``replay --json``."""
        return {
            "inspection": self.inspection,
            "last": self.last,
            "current_config_hash": self.current_config_hash,
            "considered": self.considered,
            "with_image": self.with_image,
            "with_image_by_verdict": dict(self.with_image_by_verdict),
            "flipped": [f.to_json() for f in self.flipped],
            "pass_to_fail": sum(1 for f in self.flipped if f.stored and not f.new),
            "fail_to_pass": sum(1 for f in self.flipped if not f.stored and f.new),
            "unchanged": self.unchanged,
            "failed": self.failed,
            "errors": [e.to_json() for e in self.errors],
            "rows_limited": self.rows_limited,
            "complete": self.complete,
            "stopped_by": self.stopped_by,
            "elapsed_s": round(self.elapsed_s, 3),
        }


def _verdict(passed: bool) -> str:
    return "pass" if passed else "fail"


# ----------------------------------------------------------------------------- the run


def stored_rows(
    log: ResultStore, inspection: str, last: int, report: ImpactReport
) -> Iterator[StoredResult]:
    """The newest production results of ``inspection`` with a stored image, at most ``last``,
    newest first; counts what it looked at in ``report``. Reads pages of the log's indexed
    query by inspection (``before_id``), at most :data:`MAX_ROWS_EXAMINED` rows."""
    rows = ProductionRows(log, inspection, page_rows=PAGE_ROWS, max_examined=MAX_ROWS_EXAMINED)
    found = 0
    for row in rows:
        report.considered += 1
        # An error row has no verdict of its own to compare with (and rarely an image).
        if row.error is not None or row.image_path is None or not row.image_path.is_file():
            continue
        found += 1
        yield row
        if found >= last:
            return
    report.rows_limited = rows.limited


def stored_image_loader(path: Path) -> ImageLoader:
    """A loader for a stored input image, as a try's ``source: "result"`` reads it: the PNG's
    header checked against the pixel limit and the camera's size before anything is decoded;
    colour only (the log keeps no depth frames)."""

    def load(needs: ImageNeeds) -> Images:
        payload = ImagePayload(ImageEncoding.PNG, 0, 0, path.read_bytes())
        header = compressed_header(payload, max_pixels=needs.max_pixels)
        check_image_size(header.width, header.height, needs)
        return Images(array_from_payload(payload, max_pixels=needs.max_pixels))

    return load


async def replay(
    service: InspectionService,
    log: ResultStore,
    inspection: Inspection,
    *,
    last: int = DEFAULT_LAST,
    current_config_hash: str,
    deadline: float,
    per_image_s: float = 30.0,
) -> ImpactReport:
    """Run ``inspection`` (the changed one, named as the configured one it changes) on the
    stored images of its name in ``log`` through ``service``'s try lane; see the module.

    ``last``: at most this many images (1..:data:`MAX_LAST`); ``current_config_hash``: the
    running configuration's hash, to mark rows stored under another; ``deadline``: when the
    run stops (``time.monotonic()`` seconds), the report then says so; ``per_image_s``: the
    deadline of one image's run. Cancelling the awaiting task stops the run."""
    if not 1 <= last <= MAX_LAST:
        raise ValueError(f"last must be in 1..{MAX_LAST}, got {last}")
    started = time.monotonic()
    report = ImpactReport(inspection.name, last, current_config_hash)
    rows = stored_rows(log, inspection.name, last, report)
    while True:
        if time.monotonic() >= deadline:
            report.complete, report.stopped_by = False, "deadline"
            break
        # The log is read in a thread: a page of rows is disk work, not the event loop's.
        row = await asyncio.to_thread(next, rows, None)
        if row is None:
            break
        report.with_image += 1
        report.with_image_by_verdict[_verdict(row.passed)] += 1
        try:
            passed, overlay = await _run_one(service, inspection, row, deadline, per_image_s)
        except DeadlineExceeded as exc:
            if time.monotonic() >= deadline:
                report.with_image -= 1  # not run: the run's own deadline, not this image
                report.with_image_by_verdict[_verdict(row.passed)] -= 1
                report.complete, report.stopped_by = False, "deadline"
                break
            _failed(report, row, exc)
            continue
        except CellvisionError as exc:
            _failed(report, row, exc)
            continue
        if passed == row.passed:
            report.unchanged += 1
            continue
        thumbnail = None
        if overlay is not None and sum(f.overlay is not None for f in report.flipped) < (
            MAX_OVERLAYS
        ):
            thumbnail = await asyncio.to_thread(_thumbnail, overlay, _roi_of(inspection))
        report.flipped.append(
            Flip(
                row.id,
                row.time,
                row.passed,
                passed,
                row.config_hash,
                row.config_hash == current_config_hash,
                thumbnail,
            )
        )
    report.elapsed_s = time.monotonic() - started
    return report


async def _run_one(
    service: InspectionService,
    inspection: Inspection,
    row: StoredResult,
    deadline: float,
    per_image_s: float,
) -> tuple[bool, Any]:
    """One stored image through the try lane: its verdict and overlay array (or None).

    The run waits for the try lane's slot (another try may hold the lane's one thread) until
    the run's deadline: a preview is never the reason a person's try is refused BUSY, and never
    takes a production thread."""
    assert row.image_path is not None
    admission = await _try_lane_slot(service, try_key(inspection.name), deadline)
    try:
        reply = await service.inspect(
            InspectRequest(
                inspection.name,
                images=stored_image_loader(row.image_path),
                overlay="array",
                prepared=inspection,
                deadline=min(deadline, time.monotonic() + per_image_s),
                peer=IMPACT_PEER,
                request_id=row.id,
                request_class="try",
                # No row: the log holds this part already (see InspectRequest.record).
                record=False,
            ),
            admission=admission,
        )
    finally:
        admission.release()
    overlay = None if reply.overlay is None else reply.overlay.image
    return reply.passed, overlay


async def _try_lane_slot(service: InspectionService, key: str, deadline: float) -> Admission:
    """A place in the try lane for ``key``, waited for in the lane's queue (first come, first
    served) until ``deadline``, then DEADLINE_EXCEEDED. Not :meth:`admit_when_free`: its BUSY
    after ``admission_wait_s`` would count in the server's BUSY answers, which a preview
    waiting behind a person's try is not."""
    reserved = service.pool.reserve_or_wait(key)
    if isinstance(reserved, Waiter):
        slot = await reserved.wait(max(deadline - time.monotonic(), 0.0))
        if slot is None:
            raise DeadlineExceeded("the try lane stayed busy until the preview's deadline")
        reserved = slot
    admission = Admission(service.pool, service.budget)
    admission.hold_slot(reserved)
    return admission


def _failed(report: ImpactReport, row: StoredResult, exc: CellvisionError) -> None:
    report.failed += 1
    if len(report.errors) < MAX_FAILURES:
        report.errors.append(ReplayFailure(row.id, exc.code.name, exc.message))


def _roi_of(inspection: Inspection) -> tuple[int, int, int, int] | None:
    """The inspection's ROI ``(u, v, width, height)`` in pixels, None when it has none."""
    roi = getattr(getattr(inspection, "common", None), "roi", None)
    if isinstance(roi, tuple) and len(roi) == 4 and all(isinstance(v, int) for v in roi):
        return roi
    return None


def _thumbnail(image: Any, roi: tuple[int, int, int, int] | None) -> str | None:
    """A ``data:image/jpeg`` URL of ``image`` scaled so that its longer side is at most
    :data:`THUMBNAIL_SIDE_PX` (never enlarged); None when it cannot be encoded. With a
    ``roi`` (pixels) the thumbnail shows the ROI and as much again around it (at least
    :data:`THUMBNAIL_MARGIN_PX`), where the change shows, not a whole frame shrunk."""
    if roi is not None:
        u, v, w, h = roi
        margin_u = max(w, THUMBNAIL_MARGIN_PX)
        margin_v = max(h, THUMBNAIL_MARGIN_PX)
        rows, cols = image.shape[:2]
        top, bottom = max(v - margin_v, 0), min(v + h + margin_v, rows)
        left, right = max(u - margin_u, 0), min(u + w + margin_u, cols)
        if bottom > top and right > left:
            image = image[top:bottom, left:right]
    height, width = image.shape[:2]
    scale = min(1.0, THUMBNAIL_SIDE_PX / max(width, height, 1))
    if scale < 1.0:
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, THUMBNAIL_JPEG_QUALITY])
    if not ok:
        return None
    return "data:image/jpeg;base64," + base64.b64encode(jpeg.tobytes()).decode("ascii")
