"""The console's live view: each camera's current frame as JPEG, shared by every viewer.

Server cameras are read through the service's capture (admission, the pool, the capture
timeout), at most ``max_fps`` times per second per camera: a viewer asking sooner gets the
cached JPEG, and viewers asking at once wait for the same capture. Request cameras show the
last image a robot sent, and triggered cameras (a GenICam camera with a software or hardware
trigger) and sequences (a folder replay, whose every grab takes the next file) the last frame an
inspection took, learnt from the service's observers of results and encoded only when someone
looks (and at most ``max_fps`` times per second): looking never takes a frame of theirs.

The view is best effort: its JPEG encoding (the live view's main cost, several ms a frame at
1024x768) runs in one thread of its own at the lowest priority (niceness 19 on Linux), below
the main lane and its worker processes, so that on a saturated cell an open console slows its
own frames, not the inspections (bench section 2d measures both).
"""

from __future__ import annotations

import asyncio
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import cv2

from ..process import MAX_NICE, lower_this_thread
from ..service import (
    CaptureRequest,
    ImageLoader,
    ImageNeeds,
    Images,
    InspectionRecord,
    InspectionService,
)

JPEG_QUALITY = 85


@dataclass(frozen=True)
class LiveFrame:
    """One frame as the console shows it: ``jpeg`` bytes, ``width``/``height`` pixels,
    ``timestamp`` Unix seconds of the capture (or of the robot's request)."""

    jpeg: bytes
    width: int
    height: int
    timestamp: float
    read_at: float
    """``time.monotonic()`` when the server began to read it (for the rate cap)."""


@dataclass
class _Sent:
    """The last images a robot sent for a request camera (not decoded yet), or the last frames
    an inspection took from a triggered camera."""

    images: Images | ImageLoader
    inspection: str
    timestamp: float


class LiveView:
    """Frames of every camera for any number of viewers. ``close()`` unsubscribes."""

    def __init__(self, service: InspectionService, max_fps: float) -> None:
        self.service = service
        self.min_interval_s = 1.0 / max_fps if max_fps > 0 else 0.0
        self._frames: dict[str, LiveFrame] = {}
        self._locks: dict[str, asyncio.Lock] = {}
        self._sent: dict[str, _Sent] = {}
        self._rates: dict[str, tuple[float, int, float | None]] = {}
        self._encoder = ThreadPoolExecutor(
            1, thread_name_prefix="live-view", initializer=lower_this_thread, initargs=(MAX_NICE,)
        )
        self._unsubscribe = service.subscribe(self._on_result)

    def close(self) -> None:
        self._unsubscribe()
        self._encoder.shutdown(wait=False, cancel_futures=True)

    async def _encode(self, fn: Any, *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self._encoder, fn, *args)

    def _on_result(self, record: InspectionRecord) -> None:
        camera = self.service.catalog.cameras.get(record.reply.camera)
        if camera is None:
            return
        if camera.source == "request":
            images = record.request.images
        elif not camera.view_takes_frames:
            images = record.captured
        else:
            return  # a stored image run through a fixed camera's inspection is not its view
        if images is not None:
            self._sent[record.reply.camera] = _Sent(images, record.reply.inspection, time.time())

    def last_taken(self, camera: str) -> Images | ImageLoader | None:
        """The images the last inspection took from ``camera`` (or a robot sent for it), None
        before any: what a try on a camera the console must not read runs on."""
        sent = self._sent.get(camera)
        return None if sent is None else sent.images

    def newest(self, camera: str) -> LiveFrame | None:
        """The last frame shown of ``camera`` (None before any)."""
        return self._frames.get(camera)

    def measured_fps(self, camera: str, frames_read: int | None) -> float | None:
        """Frames per second of a camera's counter since the previous call (None at first)."""
        now = time.monotonic()
        if frames_read is None:
            return None
        previous = self._rates.get(camera)
        fps = None if previous is None else previous[2]
        if previous is None or now - previous[0] >= 1.0:
            if previous is not None and now > previous[0]:
                fps = round((frames_read - previous[1]) / (now - previous[0]), 1)
            self._rates[camera] = (now, frames_read, fps)
        return fps

    async def frame(self, name: str) -> LiveFrame | None:
        """The current frame of camera ``name`` (UNKNOWN_CAMERA when there is none such);
        None for a request camera that has had no image yet."""
        camera = self.service.catalog.camera(name)
        lock = self._locks.setdefault(name, asyncio.Lock())
        async with lock:  # viewers asking at once share one read
            cached = self._frames.get(name)
            started = time.monotonic()
            # The cap counts from when the previous read began, less a tenth for the viewer's
            # timer jitter: a page asking every interval gets a new frame each time.
            if cached is not None and started - cached.read_at < 0.9 * self.min_interval_s:
                return cached
            if camera.source == "request" or not camera.view_takes_frames:
                # Never a read of its own for a triggered camera (it would fire a trigger, or
                # take a frame the cell's trigger line started for a robot's inspection) nor
                # for a sequence (the robot's next inspection would skip the frame read).
                fresh = await self._sent_frame(name, cached)
            else:
                fresh = await self._captured(name, started)
            if fresh is not None:
                self._frames[name] = fresh
            return fresh

    async def _captured(self, name: str, started: float) -> LiveFrame:
        # Raw from the service (a cheap grab), encoded here at the view's low priority.
        reply = await self.service.capture(CaptureRequest(name))
        frame = reply.frames[0]
        height, width = frame.color.shape[:2]
        jpeg = await self._encode(_jpeg, frame.color)
        return LiveFrame(jpeg, width, height, frame.timestamp, started)

    async def _sent_frame(self, name: str, cached: LiveFrame | None) -> LiveFrame | None:
        sent = self._sent.get(name)
        if sent is None:
            return None
        if cached is not None and cached.timestamp >= sent.timestamp:
            return cached
        max_pixels = self.service.settings.max_image_pixels
        needs = ImageNeeds(sent.inspection, True, max_pixels)
        frame: LiveFrame = await self._encode(_encode_sent, sent, needs)
        return frame


def _encode_sent(sent: _Sent, needs: ImageNeeds) -> LiveFrame:
    """Decode (a loader's encoded images) and re-encode as JPEG, in a thread."""
    images = sent.images if isinstance(sent.images, Images) else sent.images(needs)
    color: Any = images.color
    height, width = color.shape[:2]
    jpeg = _jpeg(color)
    return LiveFrame(jpeg, width, height, sent.timestamp, time.monotonic())


def _jpeg(image: Any) -> bytes:
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise ValueError("OpenCV could not encode the frame as JPEG")
    return bytes(buffer.tobytes())


__all__ = ["LiveFrame", "LiveView"]
