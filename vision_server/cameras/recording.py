"""Recordings of a camera: what a cell's camera saw, kept losslessly for replay and tuning.

The format (version 1; docs/recording.md) is a directory::

    my_recording/
      recording.json              # the manifest, below
      frame_000000.png            # frame 0's colour image, as the camera gave it
      frame_000000.depth.png      # frame 0's depth image (cameras with depth only)
      frame_000001.png
      ...

Colour images are PNG, lossless, in the layout the camera gave: 8-bit gray (``gray8``), 16-bit
gray (``gray16``) or 8-bit BGR (``bgr8``, stored by OpenCV as an RGB PNG). Depth images are
16-bit single-channel PNG in millimetres (0 = no depth), registered to the colour image.

``recording.json`` is one JSON object::

    format        "cellvision-recording"
    version       1
    camera        the camera's name in the configuration
    source        its source (sim, folder, opencv, realsense, genicam, recording, ...)
    settings      its settings as configured, shown as to clients: paths as the configuration
                  wrote them (an absolute one by its last component), a stream URL without its
                  password; intrinsics and mount as the configuration's keys
    intrinsics    the intrinsics the camera reported (configuration keys: width, height, fx, fy,
                  cx, cy, distortion), or null
    config_hash   the configuration's hash (as ``check-config`` prints it), or ""
    started       ISO 8601 UTC time the recording started; started_s: the same, Unix seconds
    complete      true once the writer closed it (false: interrupted; every listed frame is
                  still whole)
    stopped_by    "frames", "bytes", "duration" (a bound), "closed" (the writer was closed
                  first), or null while recording
    frames        one object per frame, in order: index (0, 1, ...: its position), color (file
                  name), color_format (gray8 | gray16 | bgr8), width, height, depth (file name
                  or null), timestamp_s (the camera's timestamp: Unix seconds on the camera's
                  clock, which is the server's ``time.time()`` when the frame was read from
                  the device, file or renderer), wall_time_s (Unix seconds when the writer
                  stored it), bytes (the frame's files), source (the file a folder camera read,
                  or null)

:class:`RecordingWriter` writes one, within optional bounds (frames, bytes of frame files,
seconds): it stops cleanly at whichever is reached first, and a frame that would overrun one is
not written. The manifest is replaced atomically (a new file renamed over the old) after the
first frame, then at most every ``sync_interval_s`` seconds, and at close, each time after the
frame files it lists were flushed to the disk: a recording that was interrupted (Ctrl-C, a
kill, a power cut) replays every frame its manifest lists.

:class:`RecordingReader` reads one: the manifest at once (bounded in size), the frames one at a
time when asked (never all at once). A bad recording gives :class:`RecordingError` (a
``ValueError``) naming the cause: no manifest, another format or version, a malformed or
absurd manifest, a missing, oversized or undecodable frame file, or one whose PNG header says
another size or layout than the manifest.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import stat
import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from protocol import CameraUnavailable

from ..process import decoder_limits
from .base import Camera, CameraFrame, public_path
from .clock import SYSTEM_CLOCK, Clock
from .mount import CameraMount
from .opencv import _redact
from .settings import Intrinsics, RecordingCameraSettings

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "MANIFEST",
    "MAX_FRAMES",
    "RecordedFrame",
    "RecordingCamera",
    "RecordingError",
    "RecordingFrame",
    "RecordingReader",
    "RecordingWriter",
    "public_settings",
]

FORMAT = "cellvision-recording"
FORMAT_VERSION = 1
MANIFEST = "recording.json"
MAX_FRAMES = 200_000
"""The most frames one recording holds (the writer stops there; a reader refuses more)."""
MAX_MANIFEST_BYTES = 128 * 1024 * 1024
"""A manifest larger than this is refused before it is parsed (about 300 bytes a frame)."""
MAX_SIDE = 32_768
"""The largest width or height of a recorded image, in pixels."""


def max_pixels() -> int:
    """The most pixels a recorded image may have: the limit OpenCV decodes within in this
    process (the server's ``max_image_pixels``, :mod:`vision_server.process.decoder_limits`),
    its default when the process does not know it. A frame beyond it could not be replayed."""
    return decoder_limits.loaded_limit() or decoder_limits.DEFAULT_MAX_IMAGE_PIXELS


ColorFormat = Literal["gray8", "gray16", "bgr8"]
COLOR_FORMATS: tuple[ColorFormat, ...] = ("gray8", "gray16", "bgr8")
StopReason = Literal["frames", "bytes", "duration", "closed"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# (bit depth, PNG colour type) of each layout: 0 gray, 2 RGB (OpenCV writes BGR arrays so).
_PNG_LAYOUT: dict[str, tuple[int, int]] = {
    "gray8": (8, 0),
    "gray16": (16, 0),
    "bgr8": (8, 2),
    "depth": (16, 0),
}
_CHANNELS_BYTES = {"gray8": (1, 1), "gray16": (1, 2), "bgr8": (3, 1), "depth": (1, 2)}
_FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,200}\.png")


class RecordingError(ValueError):
    """A recording that cannot be written or read; the message names the path and the cause."""


@dataclass(frozen=True)
class RecordedFrame:
    """One frame's entry in the manifest (see the module for the fields)."""

    index: int
    color: str
    color_format: ColorFormat
    width: int
    height: int
    depth: str | None
    timestamp_s: float
    wall_time_s: float
    bytes: int
    source: str | None = None

    def to_json(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class RecordingFrame:
    """A frame read back: its entry, its colour image as recorded (uint8 gray or BGR, or
    uint16 gray) and its depth image (uint16 mm) or None."""

    entry: RecordedFrame
    color: NDArray[Any]
    depth: NDArray[np.uint16] | None

    def color8(self) -> NDArray[np.uint8]:
        """The colour image as the inspections take it: 8-bit (16-bit gray scaled, rounded)."""
        if self.color.dtype == np.uint8:
            return np.asarray(self.color, dtype=np.uint8)
        return np.asarray(cv2.convertScaleAbs(self.color, alpha=1.0 / 256.0), dtype=np.uint8)


def color_format(color: NDArray[Any]) -> ColorFormat:
    """The layout of a colour image; ``RecordingError`` for one a recording cannot hold."""
    if color.dtype == np.uint8 and color.ndim == 2:
        return "gray8"
    if color.dtype == np.uint16 and color.ndim == 2:
        return "gray16"
    if color.dtype == np.uint8 and color.ndim == 3 and color.shape[2] == 3:
        return "bgr8"
    raise RecordingError(
        f"a recorded colour image is 8-bit gray or BGR, or 16-bit gray; got {color.dtype} "
        f"with shape {color.shape}"
    )


def intrinsics_json(intrinsics: Intrinsics | None) -> dict[str, Any] | None:
    """Intrinsics as the configuration writes them (``distortion``, not the wire's ``dist``)."""
    if intrinsics is None:
        return None
    return {
        "width": intrinsics.width,
        "height": intrinsics.height,
        "fx": intrinsics.fx,
        "fy": intrinsics.fy,
        "cx": intrinsics.cx,
        "cy": intrinsics.cy,
        "distortion": list(intrinsics.distortion),
    }


def _public_value(value: Any) -> Any:
    if value is None or isinstance(value, bool | int | float):
        return value
    if isinstance(value, Path):
        return public_path(value)
    if isinstance(value, Intrinsics):
        return intrinsics_json(value)
    if isinstance(value, CameraMount):
        return {value.key: {"xyz": list(value.xyz), "rpy": list(value.rpy)}}
    if isinstance(value, str):
        return _redact(value) if "://" in value else value
    if isinstance(value, tuple | list):
        return [_public_value(item) for item in value]
    return str(value)


def public_settings(settings: Any) -> dict[str, Any]:
    """A camera's settings (one of the settings dataclasses) as a recording's manifest shows
    them: the configuration's keys, paths as configured (an absolute one by its last
    component, as :func:`~vision_server.cameras.base.public_path` shows it to clients), a
    stream URL without its password, unset keys left out."""
    if not dataclasses.is_dataclass(settings) or isinstance(settings, type):
        raise TypeError(f"expected a camera's settings, got {settings!r}")
    out: dict[str, Any] = {}
    for item in dataclasses.fields(settings):
        value = getattr(settings, item.name)
        if value is not None:
            out[item.name] = _public_value(value)
    return out


def _encode_png(image: NDArray[Any]) -> bytes:
    ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:  # pragma: no cover - OpenCV encodes every layout color_format accepts
        raise RecordingError(f"OpenCV could not encode a {image.dtype} {image.shape} PNG")
    return bytes(data)


class RecordingWriter:
    """Writes a recording into ``path`` (created; it must not exist or be an empty directory).

    Bounds (None: no bound): ``max_frames``, ``max_bytes`` (the frame files' total, the
    manifest not counted) and ``max_duration_s`` (from the writer's creation, on ``clock``'s
    monotonic time). :meth:`add` returns False, writing nothing, once one is reached or when
    the frame would overrun ``max_bytes``; :attr:`stopped_by` says which. Use it as a context
    manager, or call :meth:`close` (which marks the recording complete).
    """

    def __init__(
        self,
        path: Path | str,
        *,
        camera: str,
        source: str,
        settings: dict[str, Any] | None = None,
        intrinsics: Intrinsics | None = None,
        config_hash: str = "",
        max_frames: int | None = None,
        max_bytes: int | None = None,
        max_duration_s: float | None = None,
        sync_interval_s: float = 1.0,
        clock: Clock | None = None,
    ) -> None:
        for name, bound in (("max_frames", max_frames), ("max_bytes", max_bytes)):
            if bound is not None and (isinstance(bound, bool) or not isinstance(bound, int)):
                raise ValueError(f"{name} must be a positive integer, got {bound!r}")
            if bound is not None and bound < 1:
                raise ValueError(f"{name} must be a positive integer, got {bound!r}")
        if max_duration_s is not None and not (
            isinstance(max_duration_s, int | float) and math.isfinite(max_duration_s)
        ):
            raise ValueError(f"max_duration_s must be a finite number, got {max_duration_s!r}")
        if max_duration_s is not None and max_duration_s <= 0:
            raise ValueError(f"max_duration_s must be > 0, got {max_duration_s!r}")
        self.path = Path(path)
        if self.path.exists() and (not self.path.is_dir() or any(self.path.iterdir())):
            raise RecordingError(
                f"{self.path} already exists and is not an empty directory: a recording is "
                "written into a new directory"
            )
        try:
            self.path.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"cannot create {self.path}: {exc.strerror or exc}") from exc
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self.max_duration_s = max_duration_s
        self.sync_interval_s = sync_interval_s
        self._clock: Clock = clock or SYSTEM_CLOCK
        self._start = self._clock.monotonic()
        started = self._clock.time()
        self._header: dict[str, Any] = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "camera": camera,
            "source": source,
            "settings": settings or {},
            "intrinsics": intrinsics_json(intrinsics),
            "config_hash": config_hash,
            "started": datetime.fromtimestamp(started, UTC).isoformat(timespec="milliseconds"),
            "started_s": started,
        }
        self._frames: list[RecordedFrame] = []
        self._bytes = 0
        self._stopped_by: StopReason | None = None
        self._closed = False
        self._synced_at: float | None = None
        self._unsynced: list[Path] = []  # frame files the next manifest lists, not yet on disk
        self._write_manifest()

    # -- state -------------------------------------------------------------------------

    @property
    def frames(self) -> int:
        return len(self._frames)

    @property
    def bytes(self) -> int:
        """The frame files' bytes so far."""
        return self._bytes

    @property
    def elapsed_s(self) -> float:
        return self._clock.monotonic() - self._start

    @property
    def stopped_by(self) -> StopReason | None:
        """Why the recording takes no more frames: a bound, "closed", or None."""
        return self._stopped_by

    @property
    def stopped(self) -> bool:
        """True once a bound was reached or the writer closed; checks the duration too."""
        self._check_duration()
        return self._stopped_by is not None

    def _check_duration(self) -> None:
        if (
            self._stopped_by is None
            and self.max_duration_s is not None
            and self.elapsed_s >= self.max_duration_s
        ):
            self._stopped_by = "duration"

    # -- writing -----------------------------------------------------------------------

    def add(
        self,
        color: NDArray[Any],
        depth: NDArray[Any] | None = None,
        *,
        timestamp_s: float,
        source: str | None = None,
    ) -> bool:
        """Store one frame; False (nothing written) once the recording is stopped or when
        the frame would overrun ``max_bytes`` (which then stops it). Raises
        ``RecordingError`` for an image a recording cannot hold or a file it cannot write."""
        if self.stopped:
            return False
        layout = color_format(color)
        if depth is not None and (
            depth.dtype != np.uint16 or depth.ndim != 2 or depth.shape != color.shape[:2]
        ):
            raise RecordingError(
                f"a depth image is uint16 (mm) of the colour image's size {color.shape[:2]}, "
                f"got {depth.dtype} with shape {depth.shape}"
            )
        if not math.isfinite(timestamp_s):
            raise RecordingError(f"a frame's timestamp must be finite, got {timestamp_s!r}")
        height, width = color.shape[:2]
        if width > MAX_SIDE or height > MAX_SIDE:
            raise RecordingError(f"a {width}x{height} image is beyond {MAX_SIDE} pixels a side")
        if width * height > max_pixels():
            raise RecordingError(
                f"a {width}x{height} image has more than {max_pixels()} pixels: it could not "
                "be replayed"
            )
        color_png = _encode_png(color)
        depth_png = None if depth is None else _encode_png(depth)
        size = len(color_png) + (0 if depth_png is None else len(depth_png))
        if self.max_bytes is not None and self._bytes + size > self.max_bytes:
            self._stopped_by = "bytes"
            return False
        index = len(self._frames)
        stem = f"frame_{index:06d}"
        color_name = f"{stem}.png"
        depth_name = None if depth_png is None else f"{stem}.depth.png"
        try:
            (self.path / color_name).write_bytes(color_png)
            self._unsynced.append(self.path / color_name)
            if depth_name is not None and depth_png is not None:
                (self.path / depth_name).write_bytes(depth_png)
                self._unsynced.append(self.path / depth_name)
        except OSError as exc:
            raise RecordingError(
                f"cannot write {self.path / stem}*.png: {exc.strerror or exc}"
            ) from exc
        self._frames.append(
            RecordedFrame(
                index=index,
                color=color_name,
                color_format=layout,
                width=int(width),
                height=int(height),
                depth=depth_name,
                timestamp_s=float(timestamp_s),
                wall_time_s=self._clock.time(),
                bytes=size,
                source=source,
            )
        )
        self._bytes += size
        if len(self._frames) >= min(self.max_frames or MAX_FRAMES, MAX_FRAMES):
            self._stopped_by = "frames"
        now = self._clock.monotonic()
        if self._synced_at is None or now - self._synced_at >= self.sync_interval_s:
            self._write_manifest()
        return True

    def close(self) -> None:
        """Write the final manifest (complete). Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._stopped_by is None:
            self._stopped_by = "closed"
        self._write_manifest(complete=True)

    def _write_manifest(self, *, complete: bool = False) -> None:
        manifest = {
            **self._header,
            "complete": complete,
            "stopped_by": self._stopped_by if complete else None,
            "frames": [frame.to_json() for frame in self._frames],
        }
        target = self.path / MANIFEST
        temporary = self.path / f".{MANIFEST}.tmp"
        try:
            # The frames it lists reach the disk before the manifest that lists them.
            for path in self._unsynced:
                _fsync(path)
            self._unsynced.clear()
            with temporary.open("w", encoding="utf-8") as file:
                json.dump(manifest, file, separators=(",", ":"))
                file.flush()
                os.fsync(file.fileno())
            os.replace(temporary, target)
            _fsync(self.path)  # the rename itself
        except OSError as exc:
            raise RecordingError(f"cannot write {target}: {exc.strerror or exc}") from exc
        if self._frames:
            self._synced_at = self._clock.monotonic()

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def _fsync(path: Path) -> None:
    """Flush a written file's (or a directory's entries') data to the disk."""
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


# ----------------------------------------------------------------------------- reading


def _field(entry: dict[str, Any], key: str, kind: type | tuple[type, ...], where: str) -> Any:
    value = entry.get(key)
    if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
        raise RecordingError(f"{where}: {key} must be {_kind_name(kind)}, got {value!r}")
    if not isinstance(value, kind):
        raise RecordingError(f"{where}: {key} must be {_kind_name(kind)}, got {value!r}")
    return value


def _kind_name(kind: type | tuple[type, ...]) -> str:
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if set(kinds) == {int, float}:
        return "a number"
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false"}
    names[type(None)] = "null"
    return " or ".join(names.get(k, k.__name__) for k in kinds)


def _number(entry: dict[str, Any], key: str, where: str) -> float:
    value = _field(entry, key, (int, float), where)
    if not math.isfinite(value):
        raise RecordingError(f"{where}: {key} must be a finite number, got {value!r}")
    return float(value)


def _file_name(value: Any, key: str, where: str) -> str:
    if not isinstance(value, str) or not _FILE_NAME.fullmatch(value) or ".." in value:
        raise RecordingError(
            f"{where}: {key} must be a PNG file name in the recording's directory, got {value!r}"
        )
    return value


def _frame_entry(entry: Any, position: int, manifest: Path) -> RecordedFrame:
    where = f"{manifest}: frames[{position}]"
    if not isinstance(entry, dict):
        raise RecordingError(f"{where}: expected an object, got {type(entry).__name__}")
    index = _field(entry, "index", int, where)
    if index != position:
        raise RecordingError(f"{where}: index is {index}, expected {position} (frames in order)")
    layout = entry.get("color_format")
    if layout not in COLOR_FORMATS:
        raise RecordingError(
            f"{where}: color_format must be one of {', '.join(COLOR_FORMATS)}, got {layout!r}"
        )
    width = _field(entry, "width", int, where)
    height = _field(entry, "height", int, where)
    if not (0 < width <= MAX_SIDE and 0 < height <= MAX_SIDE):
        raise RecordingError(
            f"{where}: a {width}x{height} image is not 1..{MAX_SIDE} pixels a side"
        )
    limit = max_pixels()
    if width * height > limit:
        raise RecordingError(
            f"{where}: frame {index} is {width}x{height}, more than {limit} pixels (the "
            "server's image limit: it could not be decoded)"
        )
    depth = entry.get("depth")
    source = entry.get("source")
    if source is not None and not isinstance(source, str):
        raise RecordingError(f"{where}: source must be a string or null, got {source!r}")
    size = _field(entry, "bytes", int, where)
    if size < 0:
        raise RecordingError(f"{where}: bytes must be >= 0, got {size}")
    return RecordedFrame(
        index=index,
        color=_file_name(entry.get("color"), "color", where),
        color_format=layout,
        width=width,
        height=height,
        depth=None if depth is None else _file_name(depth, "depth", where),
        timestamp_s=_number(entry, "timestamp_s", where),
        wall_time_s=_number(entry, "wall_time_s", where),
        bytes=size,
        source=source,
    )


def _file_kind(mode: int) -> str:
    """What a file that is not a regular file is, for a message."""
    for test, name in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return "not a regular file"


def _read_bounded(path: Path, limit: int, shown: Path, what: str) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` of them.

    The file is opened without blocking (a FIFO must not stall the open) and checked on its
    descriptor: anything but a regular file (a device, a FIFO, a directory, a socket) is
    refused, and so is a file of more than ``limit`` bytes, whatever its size said (at most
    ``limit + 1`` bytes are read). ``RecordingError`` names ``shown`` and the cause;
    ``FileNotFoundError`` is left to the caller.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
    descriptor = os.open(path, flags)
    try:
        info = os.fstat(descriptor)
        if not stat.S_ISREG(info.st_mode):
            raise RecordingError(
                f"refused {shown}: it is {_file_kind(info.st_mode)}, not a regular file ({what})"
            )
        if info.st_size > limit:
            raise RecordingError(
                f"{shown} has {info.st_size} bytes, more than {what} can have ({limit})"
            )
        chunks: list[bytes] = []
        remaining = limit + 1
        while remaining > 0:
            chunk = os.read(descriptor, min(remaining, 1 << 20))
            if not chunk:
                break
            chunks.append(chunk)
            remaining -= len(chunk)
    finally:
        os.close(descriptor)
    data = b"".join(chunks)
    if len(data) > limit:
        raise RecordingError(f"{shown} has more than {what} can have ({limit} bytes)")
    return data


def _png_header(data: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, bit depth, colour type) from a PNG's IHDR, or None if it is none."""
    if len(data) < 33 or not data.startswith(_PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    width, height, bits, kind = struct.unpack(">IIBB", data[16:26])
    return width, height, bits, kind


class RecordingReader:
    """A recording opened for reading: the manifest now, the frames when :meth:`read` asks.

    Raises :class:`RecordingError` naming the cause for a recording it cannot read.
    Attributes: ``path``, ``camera``, ``source``, ``settings``, ``intrinsics``
    (:class:`Intrinsics` or None), ``config_hash``, ``started``, ``started_s``, ``complete``,
    ``stopped_by``, ``entries`` (the :class:`RecordedFrame` of each frame).
    """

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        manifest = self.path / MANIFEST
        if not self.path.is_dir():
            what = "is not a directory" if self.path.exists() else "does not exist"
            raise RecordingError(f"recording {self.path} {what}")
        root = self.path.resolve()
        resolved = manifest.resolve()
        if not resolved.is_relative_to(root):
            raise RecordingError(f"refused {manifest}: it resolves outside the recording {root}")
        try:
            raw = _read_bounded(resolved, MAX_MANIFEST_BYTES, manifest, "a recording's manifest")
        except FileNotFoundError:
            raise RecordingError(
                f"{self.path} is not a recording: it has no {MANIFEST} "
                "(vision-server record writes one)"
            ) from None
        except OSError as exc:
            raise RecordingError(f"cannot read {manifest}: {exc.strerror or exc}") from exc
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as exc:
            raise RecordingError(f"{manifest} is not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise RecordingError(f"{manifest}: expected a JSON object")
        if data.get("format") != FORMAT:
            raise RecordingError(
                f"{manifest}: format is {data.get('format')!r}, expected {FORMAT!r}"
            )
        version = data.get("version")
        if version != FORMAT_VERSION or isinstance(version, bool):
            raise RecordingError(
                f"{manifest}: version {version!r}; this server reads version {FORMAT_VERSION}"
            )
        where = str(manifest)
        self.camera: str = _field(data, "camera", str, where)
        self.source: str = _field(data, "source", str, where)
        settings = data.get("settings", {})
        if not isinstance(settings, dict):
            raise RecordingError(f"{where}: settings must be an object")
        self.settings: dict[str, Any] = settings
        self.config_hash: str = _field(data, "config_hash", str, where)
        self.started: str = _field(data, "started", str, where)
        self.started_s = _number(data, "started_s", where)
        self.complete: bool = _field(data, "complete", bool, where)
        stopped_by = data.get("stopped_by")
        if stopped_by not in (None, "frames", "bytes", "duration", "closed"):
            raise RecordingError(f"{where}: stopped_by {stopped_by!r} is not known")
        self.stopped_by: str | None = stopped_by
        self.intrinsics = self._intrinsics(data.get("intrinsics"), where)
        frames = data.get("frames")
        if not isinstance(frames, list):
            raise RecordingError(f"{where}: frames must be a list")
        if len(frames) > MAX_FRAMES:
            raise RecordingError(
                f"{where}: {len(frames)} frames, more than a recording holds ({MAX_FRAMES})"
            )
        self.entries: tuple[RecordedFrame, ...] = tuple(
            _frame_entry(entry, i, manifest) for i, entry in enumerate(frames)
        )
        k = self.intrinsics
        for entry in self.entries:
            if k is not None and (entry.width, entry.height) != (k.width, k.height):
                raise RecordingError(
                    f"{where}: frame {entry.index} is {entry.width}x{entry.height} but the "
                    f"intrinsics are for {k.width}x{k.height}"
                )

    @staticmethod
    def _intrinsics(value: Any, where: str) -> Intrinsics | None:
        if value is None:
            return None
        keys = {"width", "height", "fx", "fy", "cx", "cy", "distortion"}
        if not isinstance(value, dict) or not set(value) <= keys:
            raise RecordingError(f"{where}: intrinsics must be an object with keys {keys}")
        try:
            distortion = value.get("distortion", [0.0] * 5)
            if isinstance(distortion, list):
                distortion = tuple(distortion)
            return Intrinsics(**{**value, "distortion": distortion})
        except (TypeError, ValueError) as exc:
            raise RecordingError(f"{where}: intrinsics: {exc}") from None

    def __len__(self) -> int:
        return len(self.entries)

    @property
    def has_depth(self) -> bool:
        """True when the frames carry depth (the first one says for all)."""
        return bool(self.entries) and self.entries[0].depth is not None

    @property
    def bytes(self) -> int:
        return sum(entry.bytes for entry in self.entries)

    @property
    def duration_s(self) -> float:
        """From the first frame's timestamp to the last's (0 for fewer than two)."""
        if len(self.entries) < 2:
            return 0.0
        return self.entries[-1].timestamp_s - self.entries[0].timestamp_s

    def _read_file(self, name: str, layout: str, entry: RecordedFrame) -> NDArray[Any]:
        path = self.path / name
        root = self.path.resolve()
        resolved = path.resolve()
        if not resolved.is_relative_to(root):
            raise RecordingError(f"refused {path}: it resolves outside the recording {root}")
        channels, depth_bytes = _CHANNELS_BYTES[layout]
        raw = entry.width * entry.height * channels * depth_bytes
        # A PNG holds at most its raw pixels, one filter byte a row and deflate's framing.
        limit = raw + raw // 64 + entry.height + 65_536
        try:
            data = _read_bounded(
                resolved,
                limit,
                path,
                f"a {entry.width}x{entry.height} {layout} PNG",
            )
        except FileNotFoundError:
            raise RecordingError(
                f"{path} is missing (frame {entry.index} of recording {self.path})"
            ) from None
        except OSError as exc:
            raise RecordingError(f"cannot read {path}: {exc.strerror or exc}") from exc
        header = _png_header(data)
        if header is None:
            raise RecordingError(f"{path} is not a PNG file (frame {entry.index})")
        want = (entry.width, entry.height, *_PNG_LAYOUT[layout])
        if header != want:
            raise RecordingError(
                f"{path}: the PNG is {header[0]}x{header[1]}, {header[2]}-bit, colour type "
                f"{header[3]}; the manifest says {entry.width}x{entry.height} {layout}"
            )
        try:
            image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
        except (cv2.error, MemoryError) as exc:
            reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
            raise RecordingError(
                f"{path} cannot be decoded (frame {entry.index}): {reason}"
            ) from None
        if image is None:
            raise RecordingError(f"{path} cannot be decoded: a corrupt PNG (frame {entry.index})")
        return np.asarray(image)

    def read(self, index: int) -> RecordingFrame:
        """Frame ``index`` (0-based), its files read and checked now."""
        if isinstance(index, bool) or not isinstance(index, int):
            raise RecordingError(f"a frame index is an integer, got {index!r}")
        if not 0 <= index < len(self.entries):
            raise RecordingError(
                f"recording {self.path} has {len(self.entries)} frames (0..{len(self) - 1}), "
                f"no frame {index}"
            )
        entry = self.entries[index]
        color = self._read_file(entry.color, entry.color_format, entry)
        depth = None
        if entry.depth is not None:
            depth = np.asarray(self._read_file(entry.depth, "depth", entry), dtype=np.uint16)
        return RecordingFrame(entry, color, depth)

    def __iter__(self) -> Iterator[RecordingFrame]:
        """The frames in order, one read at a time."""
        for index in range(len(self.entries)):
            yield self.read(index)

    def summary(self) -> dict[str, Any]:
        """JSON-able: path, camera, source, frames, bytes, duration, complete, stopped_by."""
        return {
            "path": str(self.path),
            "camera": self.camera,
            "source": self.source,
            "frames": len(self),
            "bytes": self.bytes,
            "duration_s": round(self.duration_s, 6),
            "complete": self.complete,
            "stopped_by": self.stopped_by,
            "config_hash": self.config_hash,
        }


# ----------------------------------------------------------------------------- the camera


class RecordingCamera(Camera):
    """The ``recording`` source: a recording replayed as a camera, one frame per grab.

    Each grab returns the next recorded frame with its colour (16-bit gray scaled to 8 bits,
    as the inspections take it), its depth and its recorded timestamp; the frame's ``index``
    is the camera's own counter (it keeps rising when a looping recording starts again) and
    its ``source`` the colour file's name. ``intrinsics``: the configuration's, else the
    recording's. After the last frame: again from the first with ``loop``, else
    CAMERA_UNAVAILABLE "recording ... ended after N frames". A recording that cannot be read
    (the manifest, or a frame's file) gives CAMERA_UNAVAILABLE naming the cause; the
    manifest is read again at the next grab once it failed. Messages name the recording as
    the configuration wrote it.
    """

    source = "recording"

    @property
    def sequence(self) -> bool:
        # Each grab takes the next frame: a grab only to look would skip one for the cell.
        return True

    def __init__(
        self,
        name: str,
        settings: RecordingCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        root = settings.path.expanduser()
        if not root.is_absolute() and base_dir is not None:
            root = base_dir / root
        self.root = root
        self.settings = settings
        reader: RecordingReader | None = None
        self._error: str | None = None
        try:
            reader = RecordingReader(root)
        except RecordingError as exc:
            self._error = str(exc)
        intrinsics = settings.intrinsics or (None if reader is None else reader.intrinsics)
        super().__init__(
            name,
            intrinsics=intrinsics,
            has_depth=reader is not None and reader.has_depth,
            clock=clock,
        )
        self.hide_path(root, public_path(settings.path))
        if self._error is not None:
            self._error = self.public_text(self._error)
        self._reader = reader
        self._lock = threading.Lock()
        self._position = 0
        self._next_index = 0
        self._frames = 0
        self._loops = 0

    @property
    def recording(self) -> RecordingReader:
        """The recording (read now if it could not be read before); CameraUnavailable when it
        cannot be read."""
        if self._reader is None:
            try:
                self._reader = RecordingReader(self.root)
            except RecordingError as exc:
                raise self.unavailable(str(exc)) from None
        return self._reader

    def frame_at(self, index: int) -> CameraFrame:
        """Frame ``index`` of the recording, without moving the camera's position (what the
        console's try reads). ``RecordingError`` for an index the recording does not have;
        CameraUnavailable for a recording or frame file that cannot be read."""
        self._check_open()
        reader = self.recording
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(reader):
            raise RecordingError(
                f"camera {self.name!r}: the recording has {len(reader)} frames "
                f"(0..{len(reader) - 1}), no frame {index!r}"
            )
        return self._camera_frame(reader, index, index)

    def _camera_frame(self, reader: RecordingReader, position: int, index: int) -> CameraFrame:
        try:
            recorded = reader.read(position)
        except RecordingError as exc:
            raise self.unavailable(str(exc)) from None
        color = recorded.color8()
        k = self.intrinsics
        if k is not None and (color.shape[1], color.shape[0]) != (k.width, k.height):
            raise self.unavailable(
                f"{reader.path / recorded.entry.color}: the image is {color.shape[1]}x"
                f"{color.shape[0]} but the intrinsics are for {k.width}x{k.height}"
            )
        return CameraFrame(
            color, recorded.depth, recorded.entry.timestamp_s, index, recorded.entry.color
        )

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        # Every grab reads the next frame with a new index: always fresh and newer.
        self._check_open()
        with self._lock:
            try:
                reader = self.recording
                if not len(reader):
                    raise self.unavailable(f"recording {self.root} has no frames")
                if self._position >= len(reader):
                    if not self.settings.loop:
                        raise self.unavailable(
                            f"recording {self.root} ended after {len(reader)} frames (loop: false)"
                        )
                    self._position = 0
                    self._loops += 1
                frame = self._camera_frame(reader, self._position, self._next_index)
            except CameraUnavailable as exc:
                self._error = exc.message
                raise
            self._position += 1
            self._next_index += 1
            self._frames += 1
            return frame

    def status(self) -> dict[str, Any]:
        with self._lock:
            total = None if self._reader is None else len(self._reader)
            ended = not self.settings.loop and total is not None and self._position >= total
            return {
                "name": self.name,
                "source": self.source,
                "recording": public_path(self.settings.path),
                "state": "closed" if self.closed else ("ended" if ended else "ready"),
                "connected": not self.closed and not ended and self._reader is not None,
                "frames": self._frames,
                "last_error": self._error,
                "reconnects": 0,
                "recorded_frames": total,
                "position": self._position,
                "loops": self._loops,
            }
