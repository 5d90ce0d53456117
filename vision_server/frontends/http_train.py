"""Training an anomaly inspection from the console (docs/console.md, "Training an anomaly
inspection"): good images picked from the result log, or frames grabbed from the inspection's
camera, trained on as ``vision-server train`` trains, the model written beside the
configuration, ``model:`` pointed at it with the file's history, and the server reloaded.

- ``GET /api/inspections/{name}/model``: the model in force (of each anomaly step of a job).
- ``GET /api/inspections/{name}/train/images``: the inspection's stored results with an input
  image, newest first, a page at a time (the log's indexed query by inspection, bounded).
- ``GET /api/training``: the training running (its stage and count), for the page's progress.
- ``POST /api/inspections/{name}/train``: train; the integrator's (``required_role`` in
  :mod:`.http`), through the console's sign-in and CSRF rules like every other write.

One training runs at a time, server-wide (503 ``BUSY`` with ``Retry-After`` beyond): it takes a
core for tens of seconds. Its images are cut to the pixels the inspection judges as they are
read (:func:`vision_server.service.training_patches`), so whole images never pile up; the
training itself runs in a thread of its own at the lowest CPU priority, so that the event loop
keeps serving and the robots' inspections keep their cores. A training has a deadline
(:data:`DEADLINE_S`); a browser that goes away stops it at its next step (a thread cannot be
interrupted: it stops when it next reports progress), and a model it wrote then is removed.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from aiohttp import web
from numpy.typing import NDArray

from protocol import CellvisionError

from ..analysis import ANOMALY_METHODS, MAX_GOOD_IMAGES_TRAINED, MIN_GOOD_IMAGES, AnomalyError
from ..config import CellConfig, ConfigError, ModelKeyError, set_model_key
from ..inspections import AnomalyInspection, Inspection, JobInspection
from ..process import MAX_NICE, lower_this_thread
from ..results import is_row_id
from ..service import (
    CaptureRequest,
    ImageNeeds,
    InspectionService,
    Trained,
    TrainingError,
    check_usable,
    stored_image_loader,
    train_inspection,
    training_patches,
)
from . import http_save
from .http_common import Console, HttpError, audit, bounded_json, int_param

TRAIN_PATH = "/api/inspections/{name}/train"
MODEL_PATH = "/api/inspections/{name}/model"
IMAGES_PATH = "/api/inspections/{name}/train/images"
STATUS_PATH = "/api/training"

MAX_IMAGES = MAX_GOOD_IMAGES_TRAINED
"""The most images one training takes (as ``vision-server train``)."""
MAX_BODY_BYTES = 64 * 1024
"""The largest request body: 1000 result ids are about 8 KB of JSON."""
MAX_PATCH_BYTES = 256 << 20
"""The most bytes of cut images one training holds (1000 ROIs of 256x256 BGR are 197 MB)."""
DEADLINE_S = 300.0
"""How long one training may take, from its request to its model written, seconds."""
MAX_INTERVAL_MS = 10_000
"""The longest wait between two grabbed camera frames, milliseconds."""
DEFAULT_INTERVAL_MS = 200
LIST_DEFAULT = 48
LIST_MAX = 200
"""Results one page of ``train/images`` lists (default, most)."""
LIST_EXAMINED = 5000
"""The most rows one page of ``train/images`` reads (tries and rows without images included)."""
LISTED_IDS = 10
"""How many refused result ids an error message names."""


class Stopped(Exception):
    """The training was stopped: its deadline passed, or its browser went away."""


@dataclass
class Job:
    """The training running: what the page's progress shows, and its stop flag."""

    inspection: str
    step: str | None
    source: str
    wanted: int
    deadline: float
    """``time.monotonic()`` seconds."""
    started: float = field(default_factory=time.monotonic)
    stage: str = "reading images"
    images: int = 0
    message: str = ""
    stop_reason: str | None = None
    thread_running: bool = False
    """The training's thread still runs (its request was cancelled): the slot stays taken."""
    notes: list[str] = field(default_factory=list)
    """What the reply says besides the figures (failed results picked)."""

    def check(self) -> None:
        """Raise :class:`Stopped` when the training must stop now."""
        if self.stop_reason is None and time.monotonic() > self.deadline:
            self.stop_reason = f"the training's deadline ({DEADLINE_S:.0f} s) passed"
        if self.stop_reason is not None:
            raise Stopped(self.stop_reason)

    def progress(self, message: str) -> None:
        """Called by the training between its steps (in its thread)."""
        self.message = message
        self.check()

    def json(self) -> dict[str, Any]:
        return {
            "running": True,
            "inspection": self.inspection,
            "step": self.step,
            "source": self.source,
            "stage": self.stage,
            "images": self.images,
            "wanted": self.wanted,
            "message": self.message,
            "elapsed_s": round(time.monotonic() - self.started, 1),
        }


@dataclass(frozen=True)
class Ask:
    """A training request's body, checked."""

    source: str
    ids: tuple[int, ...] = ()
    frames: int = 0
    interval_ms: int = DEFAULT_INTERVAL_MS
    step: str | None = None
    method: str | None = None
    false_reject: float | None = None


class TrainRoutes:
    """The training routes of ``console`` (its configuration file, save lock, reload) over
    ``service`` (its catalog, result log and camera captures)."""

    def __init__(self, console: Console, service: InspectionService) -> None:
        self.console = console
        self.service = service
        self.job: Job | None = None
        self._executor: concurrent.futures.ThreadPoolExecutor | None = None

    def add_to(self, router: web.UrlDispatcher) -> None:
        router.add_post(TRAIN_PATH, self.train)
        router.add_get(MODEL_PATH, self.model)
        router.add_get(IMAGES_PATH, self.images)
        router.add_get(STATUS_PATH, self.status)

    def executor(self) -> concurrent.futures.ThreadPoolExecutor:
        """The training's own thread, at the lowest CPU priority (made on first use)."""
        if self._executor is None:
            self._executor = concurrent.futures.ThreadPoolExecutor(
                1,
                thread_name_prefix="console-train",
                initializer=lower_this_thread,
                initargs=(MAX_NICE,),
            )
        return self._executor

    # ------------------------------------------------------------------ reads

    async def status(self, request: web.Request) -> web.Response:
        job = self.job
        body = job.json() if job is not None else {"running": False}
        return web.json_response(body, headers={"Cache-Control": "no-store"})

    async def model(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        catalog = self.service.catalog
        inspection = catalog.inspection(name)  # UNKNOWN_INSPECTION: 404
        targets = _anomaly_targets(inspection)
        camera = catalog.camera(inspection.camera)
        grabs = camera.source != "request" and camera.view_takes_frames
        return web.json_response(
            {
                "inspection": name,
                "type": inspection.type,
                "camera": camera.name,
                "camera_grabs": grabs,
                "config_hash": catalog.config_hash,
                "models": [_model_json(step, settings) for step, settings in targets],
            },
            headers={"Cache-Control": "no-store"},
        )

    async def images(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        self.service.catalog.inspection(name)
        log = self._log()
        limit = int_param(request.query, "limit", LIST_DEFAULT, 1, LIST_MAX)
        before = int_param(request.query, "before_id", None, 1, None)
        listed, next_before, examined = await asyncio.to_thread(
            _stored_rows, log, name, limit, before
        )
        return web.json_response(
            {
                "results": listed,
                "next_before_id": next_before,
                "examined": examined,
                "store_images": getattr(log, "store_images", None),
            },
            headers={"Cache-Control": "no-store"},
        )

    def _log(self) -> Any:
        log = self.service.results
        if log is None:
            raise HttpError(404, "NO_RESULT_LOG", "this server keeps no result log")
        return log

    # ------------------------------------------------------------------ training

    async def train(self, request: web.Request) -> web.Response:
        name = request.match_info["name"]
        catalog = self.service.catalog
        inspection = catalog.inspection(name)  # UNKNOWN_INSPECTION: 404
        targets = _anomaly_targets(inspection)  # NOT_TRAINABLE: 400
        path = self.console.writable_config()  # CONFIG_REFUSED: 403
        body = await bounded_json(request, MAX_BODY_BYTES, self.console.settings.request_timeout_s)
        ask = _parse(body, [step for step, _ in targets], isinstance(inspection, JobInspection))
        if self.job is not None:  # before any work: a second training costs nothing
            raise HttpError(
                503,
                "BUSY",
                f"a training of {self.job.inspection!r} is running ({self.job.stage}); one "
                "training runs at a time: try again when it ends",
                retry_after=10,
            )
        wanted = len(ask.ids) if ask.source == "results" else ask.frames
        job = Job(name, ask.step, ask.source, wanted, time.monotonic() + DEADLINE_S)
        self.job = job
        try:
            trained, patches, skipped = await self._run(job, path, name, ask)
            job.stage = "writing the configuration"
            # Shielded: once the file is being written, a browser that goes away does not
            # leave it half done (the model named but removed, or the server not reloaded).
            saved, catalog = await asyncio.shield(
                self._commit(path, name, trained, self.console.who(request), patches)
            )
        finally:
            if not job.thread_running:
                self.job = None
        report = trained.report
        report = trained.report
        audit.info(
            "console: %s trained %r%s on %d images (%s): %s, configuration version %d",
            self.console.who(request),
            name,
            f" step {ask.step!r}" if ask.step else "",
            report.images,
            ask.source,
            trained.relative,
            saved.version.number,
        )
        return web.json_response(
            {
                "inspection": name,
                "step": trained.step,
                "model": trained.relative,
                "version": trained.model.version,
                "method": trained.model.method,
                "images": report.images,
                "threshold": report.threshold,
                "false_reject": report.false_reject,
                "held_out_rejected": report.held_out_rejected,
                "held_out_scores": [round(s, 6) for s in report.held_out_scores],
                "seconds": round(time.monotonic() - job.started, 3),
                "training_seconds": round(report.seconds, 3),
                "skipped": list(skipped),
                "config_hash": catalog.config_hash,
                "config_version": saved.version.number,
                "notes": [*job.notes, *catalog.notes],
            }
        )

    async def _commit(
        self, path: Path, name: str, trained: Trained, who: str, images: int
    ) -> tuple[http_save.Saved, Any]:
        """Point ``model:`` at the new file, write it with the history and reload (the old
        text back and 422 when the server refuses it); the model file is removed when the
        configuration does not end up naming it."""
        try:
            async with self.console.save_lock:
                saved = await asyncio.to_thread(_point_at_model, path, name, trained, who, images)
                catalog = await self.console.reload_or_undo(
                    saved, what=f"the server did not take {trained.relative}: "
                )
        except BaseException:
            with contextlib.suppress(OSError):
                trained.path.unlink()
            raise
        return saved, catalog

    async def _run(
        self, job: Job, path: Path, name: str, ask: Ask
    ) -> tuple[Trained, int, list[str]]:
        """Read the images, cut them and train; the model file is written, the configuration
        not yet. Returns the training, the file's text it was made from, the images trained
        on and those left out (named)."""
        text, config = await asyncio.to_thread(_read_config, path)
        inspection = next((i for i in config.inspections if i.name == name), None)
        if inspection is None:
            raise HttpError(
                409,
                "CONFIG_REFUSED",
                f"{path.name} no longer has an inspection {name!r} (edited since the last "
                "reload): reload the server first",
            )
        cut = Cutter(inspection, ask.step)
        try:
            if ask.source == "results":
                await self._read_results(job, name, ask.ids, cut)
            else:
                await self._grab_frames(job, name, ask.frames, ask.interval_ms, cut)
        except Stopped as exc:
            raise HttpError(504, "DEADLINE_EXCEEDED", f"training stopped: {exc}") from None
        try:
            check_usable(len(cut.patches), cut.skipped)
        except TrainingError as exc:
            raise HttpError(
                400, "NOT_TRAINABLE", str(exc), details={"skipped": cut.skipped[:LISTED_IDS]}
            ) from None
        if len(cut.patches) < MIN_GOOD_IMAGES:
            left = ""
            if cut.skipped:
                left = f" ({len(cut.skipped)} left out: {'; '.join(cut.skipped[:3])})"
            raise HttpError(
                400,
                "TOO_FEW_IMAGES",
                f"{len(cut.patches)} usable images{left}: training needs at least "
                f"{MIN_GOOD_IMAGES} (30 or more set a steadier threshold)",
                details={"images": len(cut.patches), "minimum": MIN_GOOD_IMAGES},
            )
        job.stage = "training"
        job.images = len(cut.patches)
        loop = asyncio.get_running_loop()
        work = loop.run_in_executor(
            self.executor(),
            lambda: train_inspection(
                config,
                text,
                name,
                cut.patches,
                step=ask.step,
                method=ask.method,
                false_reject=ask.false_reject,
                progress=job.progress,
                cut=True,
            ),
        )
        try:
            # Shielded: a cancelled request (its browser gone) stops the thread at its next
            # step through the job's flag; the file it may have written is removed after.
            trained = await asyncio.shield(work)
        except asyncio.CancelledError:
            job.stop_reason = "the browser went away"
            job.thread_running = True
            work.add_done_callback(lambda done: self._after_cancel(job, done))
            raise
        except Stopped as exc:
            raise HttpError(504, "DEADLINE_EXCEEDED", f"training stopped: {exc}") from None
        except TrainingError as exc:
            raise HttpError(400, "NOT_TRAINABLE", str(exc)) from None
        except (AnomalyError, ModelKeyError) as exc:
            raise HttpError(400, "TRAINING_REFUSED", str(exc)) from None
        except OSError as exc:
            raise HttpError(
                500, "WRITE_FAILED", f"the model file cannot be written: {exc}"
            ) from None
        return trained, len(cut.patches), cut.skipped

    def _after_cancel(self, job: Job, done: asyncio.Future[Trained]) -> None:
        """The thread of a cancelled training ended: remove the model it wrote (no
        configuration names it) and free the slot."""
        if not done.cancelled() and done.exception() is None:
            with contextlib.suppress(OSError):
                done.result().path.unlink()
        if self.job is job:
            self.job = None

    async def _read_results(self, job: Job, name: str, ids: Sequence[int], cut: Cutter) -> None:
        """Cut the stored input image of each result (read and cut in a worker, one at a time:
        only the cut pixels stay). 400 naming every id without a stored input image."""
        log = self._log()
        camera = self.service.catalog.inspection(name).camera
        paths, others, failed = await asyncio.to_thread(_stored_paths, log, ids, camera)
        if others:
            shown = ", ".join(str(i) for i in others[:LISTED_IDS])
            raise HttpError(
                400,
                "OTHER_CAMERA",
                f"{len(others)} of the results come from another camera than {camera!r} "
                f"({shown}): a model learns {name!r}'s parts from its own camera's images",
                details={"result_ids": others[:LISTED_IDS]},
            )
        if failed:
            job.notes.append(
                f"{len(failed)} of the results picked failed when they were inspected "
                f"(e.g. {failed[0]}): a model learns that what it is trained on is good"
            )
        missing = [i for i in ids if paths.get(i) is None]
        if missing:
            shown = ", ".join(str(i) for i in missing[:LISTED_IDS])
            more = f" and {len(missing) - LISTED_IDS} more" if len(missing) > LISTED_IDS else ""
            raise HttpError(
                400,
                "NO_STORED_IMAGE",
                f"{len(missing)} of the results have no stored input image (no such result, "
                f"or the log did not keep its image): {shown}{more}; pick results that have one",
                details={"result_ids": missing[:LISTED_IDS]},
            )
        needs = self._needs(name)
        for number, result_id in enumerate(ids, 1):
            job.check()
            job.message = f"result {result_id} ({number}/{len(ids)})"
            stored = paths[result_id]
            assert stored is not None
            try:
                await asyncio.to_thread(_cut_stored, cut, stored, needs, f"result {result_id}")
            except CellvisionError as exc:
                raise HttpError(
                    400,
                    exc.code.name,
                    f"result {result_id}: {exc.message}",
                    details={"result_ids": [result_id]},
                ) from None
            job.images = len(cut.patches)

    async def _grab_frames(
        self, job: Job, name: str, frames: int, interval_ms: int, cut: Cutter
    ) -> None:
        """Grab ``frames`` frames of the inspection's camera through the service's capture
        (its admission and timeouts), ``interval_ms`` apart, cutting each as it comes."""
        inspection = self.service.catalog.inspection(name)
        camera = self.service.catalog.camera(inspection.camera)
        if camera.source == "request":
            raise HttpError(
                400,
                "NO_CAMERA_FRAMES",
                f"camera {camera.name!r} gets its images from robots: train on stored results",
            )
        if not camera.view_takes_frames:
            raise HttpError(
                400,
                "NO_CAMERA_FRAMES",
                f"camera {camera.name!r} ({camera.source}) is triggered or replays a sequence: its "
                "frames belong to the cell's inspections; train on stored results",
            )
        for number in range(1, frames + 1):
            job.check()
            job.message = f"frame {number}/{frames}"
            reply = await self.service.capture(CaptureRequest(camera.name))
            image = reply.frames[0].color
            await asyncio.to_thread(cut.add, image, f"frame {number}")
            job.images = len(cut.patches)
            if number < frames and interval_ms > 0:
                await asyncio.sleep(interval_ms / 1000.0)

    def _needs(self, name: str) -> ImageNeeds:
        """What a stored image must be to be read for inspection ``name``: its camera's size."""
        catalog = self.service.catalog
        inspection = catalog.inspection(name)
        declared = catalog.camera(inspection.camera).intrinsics
        return ImageNeeds(
            name,
            False,
            self.service.settings.max_image_pixels,
            None if declared is None else (declared.width, declared.height),
        )

    def close(self) -> None:
        """Stop taking trainings (one running ends at its next step: the server stops)."""
        if self.job is not None:
            self.job.stop_reason = "the server stops"
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


class Cutter:
    """Cuts whole images to what ``inspection`` (its anomaly step ``step``) judges, keeping
    only the cut pixels, within :data:`MAX_PATCH_BYTES`."""

    def __init__(self, inspection: Inspection, step: str | None) -> None:
        self.inspection = inspection
        self.step = step
        self.patches: list[NDArray[np.uint8]] = []
        self.skipped: list[str] = []
        self.bytes = 0

    def add(self, image: NDArray[np.uint8], label: str) -> None:
        try:
            cut, left_out = training_patches(self.inspection, [image], step=self.step)
        except TrainingError as exc:
            raise HttpError(400, "NOT_TRAINABLE", str(exc)) from None
        self.skipped.extend(f"{label}: {why.split(': ', 1)[-1]}" for why in left_out)
        for patch in cut:
            self.bytes += patch.nbytes
            if self.bytes > MAX_PATCH_BYTES:
                raise HttpError(
                    413,
                    "TOO_LARGE",
                    f"the images cut so far hold {self.bytes >> 20} MiB, a training holds at "
                    f"most {MAX_PATCH_BYTES >> 20} MiB: train on fewer images or a smaller ROI",
                )
            self.patches.append(patch)


# ----------------------------------------------------------------------------- helpers


def _anomaly_targets(inspection: Inspection) -> list[tuple[str | None, Any]]:
    """(step name or None, its AnomalySettings) of each anomaly part; 400 NOT_TRAINABLE."""
    if isinstance(inspection, AnomalyInspection):
        return [(None, inspection.settings)]
    if isinstance(inspection, JobInspection):
        steps: list[tuple[str | None, Any]] = [
            (s.name, getattr(s, "settings", None)) for s in inspection.steps if s.type == "anomaly"
        ]
        if steps:
            return steps
        raise HttpError(
            400,
            "NOT_TRAINABLE",
            f"job {inspection.name!r} has no anomaly step: only anomaly inspections and jobs "
            "with an anomaly step are trained",
        )
    raise HttpError(
        400,
        "NOT_TRAINABLE",
        f"{inspection.name!r} is a {inspection.type} inspection: only anomaly inspections and "
        "jobs with an anomaly step are trained",
    )


def _model_json(step: str | None, settings: Any) -> dict[str, Any]:
    """The model of one anomaly part as ``GET .../model`` shows it."""
    model = settings.model
    out: dict[str, Any] = {
        "step": step,
        "file": settings.model_file,
        "trained": model is not None,
        "threshold": settings.limit,
        "threshold_override": settings.threshold,
        "method": settings.method,
        "false_reject": settings.false_reject,
    }
    if model is not None:
        meta = model.meta
        out.update(
            {
                "method": model.method,
                "version": model.version,
                "model_threshold": model.threshold,
                "model_false_reject": model.false_reject,
                "image_size": list(model.image_size),
                "trained_at": meta.get("trained_at"),
                "images": len(meta.get("images", ())),
                "held_out_scores": list(meta.get("held_out", ()))[:MAX_IMAGES],
                "sha256": model.digest[:16],
            }
        )
    return out


def _parse(body: dict[str, Any], steps: list[str | None], is_job: bool) -> Ask:
    """The training request of ``body``; 400 ``BAD_REQUEST`` naming the key at fault."""

    def bad(message: str, key: str | None = None) -> HttpError:
        return HttpError(400, "BAD_REQUEST", message, details={"key": key} if key else None)

    allowed = {"source", "ids", "frames", "interval_ms", "step", "method", "false_reject"}
    unknown = sorted(set(body) - allowed)
    if unknown:
        raise bad(f"unknown key {unknown[0]!r}: the body takes {', '.join(sorted(allowed))}")
    source = body.get("source")
    if source not in ("results", "camera"):
        raise bad("source must be 'results' (with ids) or 'camera' (with frames)", "source")
    step = body.get("step")
    if step is not None and not isinstance(step, str):
        raise bad("step must be a job step's name", "step")
    if is_job:
        if step is None:
            if len(steps) != 1:
                raise HttpError(
                    400,
                    "NOT_TRAINABLE",
                    f"the job has {len(steps)} anomaly steps ({', '.join(map(str, steps))}): "
                    "name one as step",
                )
            step = steps[0]
        elif step not in steps:
            raise HttpError(
                400,
                "NOT_TRAINABLE",
                f"the job has no anomaly step {step!r} (its anomaly steps: "
                f"{', '.join(map(str, steps))})",
            )
    elif step is not None:
        raise HttpError(400, "NOT_TRAINABLE", "an anomaly inspection has no steps: leave out step")
    method = body.get("method")
    if method is not None and method not in ANOMALY_METHODS:
        raise bad(f"method must be one of {', '.join(ANOMALY_METHODS)}, got {method!r}", "method")
    rate = body.get("false_reject")
    if rate is not None:
        if (
            isinstance(rate, bool)
            or not isinstance(rate, int | float)
            or not math.isfinite(rate)
            or not 0.0 < rate < 0.5
        ):
            raise bad(f"false_reject must be a rate in (0, 0.5), got {rate!r}", "false_reject")
        rate = float(rate)
    if source == "results":
        for key in ("frames", "interval_ms"):
            if key in body:
                raise bad(f"{key} is for source 'camera'", key)
        ids = body.get("ids")
        if not isinstance(ids, list) or not ids:
            raise bad("ids must be a non-empty list of result ids", "ids")
        if len(ids) > MAX_IMAGES:
            raise HttpError(
                400,
                "TOO_MANY_IMAGES",
                f"{len(ids)} results: a training takes at most {MAX_IMAGES} images",
            )
        wrong = next((i for i in ids if not is_row_id(i)), None)
        if wrong is not None:
            raise bad(f"ids must be result ids (integers >= 1), got {json.dumps(wrong)}", "ids")
        unique = tuple(dict.fromkeys(ids))
        return Ask("results", ids=unique, step=step, method=method, false_reject=rate)
    if "ids" in body:
        raise bad("ids is for source 'results'", "ids")
    frames = body.get("frames")
    if isinstance(frames, bool) or not isinstance(frames, int) or frames < 1:
        raise bad(f"frames must be a whole number of frames, got {frames!r}", "frames")
    if frames > MAX_IMAGES:
        raise HttpError(
            400, "TOO_MANY_IMAGES", f"{frames} frames: a training takes at most {MAX_IMAGES} images"
        )
    if frames < MIN_GOOD_IMAGES:
        raise HttpError(
            400,
            "TOO_FEW_IMAGES",
            f"{frames} frames: training needs at least {MIN_GOOD_IMAGES}",
            details={"images": frames, "minimum": MIN_GOOD_IMAGES},
        )
    interval = body.get("interval_ms", DEFAULT_INTERVAL_MS)
    if isinstance(interval, bool) or not isinstance(interval, int):
        raise bad(f"interval_ms must be a whole number of milliseconds, got {interval!r}")
    if not 0 <= interval <= MAX_INTERVAL_MS:
        raise bad(f"interval_ms must be in 0..{MAX_INTERVAL_MS}", "interval_ms")
    if frames * interval / 1000.0 > DEADLINE_S / 2:
        raise bad(
            f"{frames} frames {interval} ms apart take {frames * interval / 1000:.0f} s: a "
            f"training may take {DEADLINE_S:.0f} s in all, half of it for grabbing",
            "interval_ms",
        )
    return Ask(
        "camera", frames=frames, interval_ms=interval, step=step, method=method, false_reject=rate
    )


def _read_config(path: Path) -> tuple[str, CellConfig]:
    """The configuration file's text and its configuration (as ``serve`` loads it): what the
    training cuts by and writes ``model:`` into. 422 when it does not load."""
    try:
        text = path.read_bytes().decode("utf-8")
        return text, http_save.validate(text, path)
    except (OSError, UnicodeError) as exc:
        raise HttpError(500, "WRITE_FAILED", f"{path.name} cannot be read: {exc}") from None
    except ConfigError as exc:
        raise HttpError(
            422,
            "CONFIG_REFUSED",
            f"{path.name} is invalid as it is now (an edit outside the console, not loaded "
            f"yet): {exc}",
        ) from None


def _point_at_model(
    path: Path, name: str, trained: Trained, who: str, images: int
) -> http_save.Saved:
    """Set ``model:`` of ``name`` (its step) in the file as it is now (a save may have come
    since the training began: its text is kept), validate and write it with the history."""
    old = path.read_bytes()
    try:
        text = set_model_key(old.decode("utf-8"), name, trained.relative, step=trained.step)
        http_save.validate(text, path)
    except (ModelKeyError, ConfigError, UnicodeError) as exc:
        raise HttpError(422, "CONFIG_REFUSED", f"{path.name}: {exc}") from None
    try:
        version = http_save.write_version(
            path,
            text,
            old=old,
            who=who,
            why=f"trained {trained.relative} on {images} images in the console",
        )
    except http_save.SaveRefused as exc:
        raise HttpError(422, "CONFIG_REFUSED", str(exc)) from None
    return http_save.Saved(path, old, version)


def _cut_stored(cut: Cutter, path: Path, needs: ImageNeeds, label: str) -> None:
    """Read a stored input image as a try reads it (its size checked before decoding) and cut
    it (in a worker)."""
    cut.add(stored_image_loader(path)(needs).color, label)


def _stored_paths(
    log: Any, ids: Sequence[int], camera: str
) -> tuple[dict[int, Path | None], list[int], list[int]]:
    """Each result's stored input image (None: no such row, or no image kept), the ids of
    results of another camera than ``camera``, and those of failed results."""
    out: dict[int, Path | None] = {}
    others: list[int] = []
    failed: list[int] = []
    for result_id in ids:
        row = log.get(result_id)
        path = None if row is None else row.image_path
        out[result_id] = path if path is not None and path.is_file() else None
        if row is not None and row.camera != camera:
            others.append(result_id)
        elif row is not None and not row.passed:
            failed.append(result_id)
    return out, others, failed


def _stored_rows(
    log: Any, name: str, limit: int, before: int | None
) -> tuple[list[dict[str, Any]], int | None, int]:
    """Up to ``limit`` of ``name``'s rows with a stored input image, newest first (before
    ``before``), read through the log's indexed query by inspection, at most
    :data:`LIST_EXAMINED` rows; the rows, the ``before_id`` of the next page (None: no more)
    and the rows read."""
    found: list[dict[str, Any]] = []
    examined = 0
    cursor = before
    while examined < LIST_EXAMINED:
        page_size = min(200, LIST_EXAMINED - examined)
        page = log.query(inspection=name, limit=page_size, before_id=cursor)
        examined += len(page)
        for row in page:
            cursor = row.id
            path = row.image_path
            if path is None or not path.is_file():
                continue
            found.append(
                {
                    "id": row.id,
                    "time": row.time,
                    "passed": row.passed,
                    "error": row.error,
                    "try": row.is_try,
                    "config_hash": row.config_hash,
                    "has_overlay": row.overlay_path is not None and row.overlay_path.is_file(),
                    "score": row.data.get("score") if isinstance(row.data, dict) else None,
                }
            )
            if len(found) == limit:
                return found, row.id, examined
        if len(page) < page_size:
            return found, None, examined
    return found, cursor, examined


__all__ = ["IMAGES_PATH", "MODEL_PATH", "STATUS_PATH", "TRAIN_PATH", "TrainRoutes"]
