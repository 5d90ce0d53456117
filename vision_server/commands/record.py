"""``vision-server record CAMERA``: record what a configured camera sees, for replay offline.

The camera is opened from the configuration (``--config``) as the server opens it, outside any
server, and grabbed until a bound is reached: ``--frames N``, ``--max-bytes SIZE`` (the frame
files), ``--duration S``; without any, 100 frames. ``--interval S`` waits between grabs (from
the start of one grab to the start of the next). The result is a recording directory (the
format of :mod:`vision_server.cameras.recording`, docs/recording.md) that the ``recording``
camera source, ``vision-server run --recording`` and ``vision-server test-inspections
--from-recording`` replay.

For a RealSense camera the SDK's own format (a rosbag2 ``.db3`` file, which the RealSense
Viewer plays and ``source: realsense`` with ``playback:`` replays) is written instead with
``--format realsense`` (any camera), or by default when ``--out`` ends in ``.db3``, through
:class:`vision_server.cameras.RealSenseRecorder` (pyrealsense2's ``software_device`` and
``recorder``).

Exit codes: 0 recorded up to a bound; 1 the camera failed (what was recorded before is kept and
replays); 2 usage or configuration error (nothing recorded); 130 interrupted by Ctrl-C, 143
stopped by SIGTERM (``timeout``, ``systemctl stop``): what was recorded is kept, its manifest
complete. A recording that ends with no frame (exit 1, 130 or 143) is removed, with the
directory when the command created it, so that the same ``--out`` can be used again.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from protocol import CameraUnavailable, CellvisionError
from protocol.cli import CONFIG_ENV, ErrorKind, ExitCode, json_error

from ..cameras import (
    RECORDING_MANIFEST,
    Camera,
    CameraFrame,
    RealSenseCameraSettings,
    RealSenseRecorder,
    RecordingError,
    RecordingWriter,
    RequestCameraSettings,
    make_camera,
    public_settings,
)
from ..config import ConfigError, load_config

__all__ = ["DEFAULT_FRAMES", "add_parser", "parse_size", "record"]

PROG = "vision-server record"
DEFAULT_FRAMES = 100
"""The bound when none is given: a recording never grows without one."""
REALSENSE_SUFFIXES = (".db3",)
TERMINATED = 128 + int(signal.SIGTERM)
"""The exit code when SIGTERM stopped the recording (143, as a shell reports a SIGTERM)."""
_SIZE = re.compile(r"(\d+(?:\.\d+)?)\s*([kmgt]?)(i?b?)", re.IGNORECASE)
_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(text: str) -> int:
    """``--max-bytes``: bytes, or with a binary unit: ``500k``, ``200M``, ``1.5GiB``."""
    match = _SIZE.fullmatch(text.strip())
    if match is None:
        raise argparse.ArgumentTypeError(
            f"expected a size such as 5000000, 200M or 1G, got {text!r}"
        )
    size = int(float(match.group(1)) * _UNITS[match.group(2).lower()])
    if size < 1:
        raise argparse.ArgumentTypeError(f"a size must be at least 1 byte, got {text!r}")
    return size


def _positive(kind: type[int] | type[float]) -> Any:
    def convert(text: str) -> int | float:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
        if not math.isfinite(value) or value <= 0:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
        return value

    return convert


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}") from None
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def add_parser(sub: Any, parents: list[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "record",
        parents=parents,
        help="record a configured camera's frames (for replay: source recording, run, golden)",
        description="Record what a configured camera sees (opened from --config as the "
        "server opens it, outside any server) until a bound: --frames, --max-bytes or "
        f"--duration; without any, {DEFAULT_FRAMES} frames. The recording (docs/recording.md) "
        "replays as a camera (source: recording), through vision-server run --recording and "
        "as golden cases (test-inspections --from-recording). Exit codes: 0 recorded up to a "
        "bound; 1 the camera failed (what was recorded is kept); 2 usage or configuration "
        "error; 130 Ctrl-C, 143 SIGTERM (what was recorded is kept, complete; a recording of "
        "no frame is removed).",
    )
    p.add_argument("camera", help="the camera's name in the configuration")
    p.add_argument(
        "--out",
        required=True,
        metavar="PATH",
        help="the recording: a new (or empty) directory; a .db3 file with --format realsense",
    )
    p.add_argument(
        "--frames",
        type=_positive(int),
        metavar="N",
        help=f"stop after N frames (the default bound, {DEFAULT_FRAMES}, when none is given)",
    )
    p.add_argument(
        "--max-bytes",
        type=parse_size,
        metavar="SIZE",
        help="stop before the frame files pass SIZE (bytes, or 500k, 200M, 2G)",
    )
    p.add_argument("--duration", type=_positive(float), metavar="S", help="stop after S seconds")
    p.add_argument(
        "--interval",
        type=_non_negative,
        default=0.0,
        metavar="S",
        help="seconds from one grab to the next (default 0: as fast as the camera gives)",
    )
    p.add_argument(
        "--timeout",
        type=_positive(float),
        default=10.0,
        metavar="S",
        help="how long one grab may wait for a frame (default 10 s)",
    )
    p.add_argument(
        "--format",
        choices=("auto", "cellvision", "realsense"),
        default="auto",
        help="cellvision: the recording directory (docs/recording.md); realsense: the "
        "RealSense SDK's file (the Viewer plays it); auto (default): realsense for a realsense "
        "camera whose --out ends in .db3, else cellvision",
    )
    p.set_defaults(func=record)


# ----------------------------------------------------------------------------- where frames go


class _Sink(Protocol):
    @property
    def frames(self) -> int: ...

    @property
    def bytes(self) -> int: ...

    @property
    def path(self) -> Path: ...

    def add(self, frame: CameraFrame) -> bool: ...

    def stopped_by(self) -> str | None: ...

    def close(self) -> None: ...

    def discard(self) -> bool: ...


class _RecordingSink:
    """The cellvision recording directory (:class:`RecordingWriter` keeps the bounds);
    ``created``: the writer made the directory (it did not exist before)."""

    def __init__(self, writer: RecordingWriter, *, created: bool) -> None:
        self.writer = writer
        self.path = writer.path
        self.created = created

    @property
    def frames(self) -> int:
        return self.writer.frames

    @property
    def bytes(self) -> int:
        return self.writer.bytes

    def add(self, frame: CameraFrame) -> bool:
        return self.writer.add(
            frame.color, frame.depth, timestamp_s=frame.timestamp, source=frame.source
        )

    def stopped_by(self) -> str | None:
        return self.writer.stopped_by if self.writer.stopped else None

    def close(self) -> None:
        self.writer.close()

    def discard(self) -> bool:
        """Remove a closed recording of no frame: its manifest, and its directory when it was
        created for it (an empty directory that was given stays, empty). True if removed."""
        if self.writer.frames:
            return False
        for name in (RECORDING_MANIFEST, f".{RECORDING_MANIFEST}.tmp"):
            with contextlib.suppress(FileNotFoundError):
                (self.path / name).unlink()
        if self.created:
            with contextlib.suppress(OSError):  # something else put a file there: keep it
                self.path.rmdir()
        return True


@dataclass
class _Bounds:
    frames: int | None
    bytes: int | None
    duration_s: float | None


class _RealSenseSink:
    """The RealSense SDK's own file, through ``vision_server.cameras.RealSenseRecorder``
    (created at the first frame, when the camera's size and intrinsics are known). The bytes
    bound is checked against the file's size after each frame (the SDK writes as it goes)."""

    def __init__(self, path: Path, camera: Camera, settings: Any, bounds: _Bounds) -> None:
        self.path = path
        self.camera = camera
        self.fps = settings.fps if isinstance(settings, RealSenseCameraSettings) else 30
        self.bounds = bounds
        self.frames = 0
        self.bytes = 0
        self._recorder: Any = None
        self._start = time.monotonic()
        self._stopped: str | None = None

    def add(self, frame: CameraFrame) -> bool:
        if self.stopped_by() is not None:
            return False
        color: Any = frame.color
        if frame.color.ndim == 2:
            color = cv2.cvtColor(frame.color, cv2.COLOR_GRAY2BGR)
        if self._recorder is None:
            intrinsics = self.camera.intrinsics
            if intrinsics is None:
                raise RecordingError(
                    f"camera {self.camera.name!r} reports no intrinsics: the RealSense format "
                    "needs them (give intrinsics in the configuration)"
                )
            try:
                # The camera's depth is registered to its colour already: one set of
                # intrinsics, in mm.
                self._recorder = RealSenseRecorder(
                    self.path,
                    width=frame.width,
                    height=frame.height,
                    fps=self.fps,
                    intrinsics=intrinsics,
                    depth_intrinsics=None,
                    depth_scale_m=0.001,
                    depth=frame.depth is not None,
                )
            except (ImportError, ValueError) as exc:
                raise RecordingError(f"the RealSense recording cannot be written: {exc}") from exc
        try:
            self._recorder.add(np.ascontiguousarray(color), frame.depth, frame.timestamp)
        except ValueError as exc:
            raise RecordingError(f"a frame the RealSense recording cannot hold: {exc}") from exc
        self.frames += 1
        with contextlib.suppress(OSError):  # the SDK may create the file later
            self.bytes = self.path.stat().st_size
        if self.bounds.frames is not None and self.frames >= self.bounds.frames:
            self._stopped = "frames"
        elif self.bounds.bytes is not None and self.bytes >= self.bounds.bytes:
            self._stopped = "bytes"
        return True

    def stopped_by(self) -> str | None:
        bound = self.bounds.duration_s
        if self._stopped is None and bound is not None and time.monotonic() - self._start >= bound:
            self._stopped = "duration"
        return self._stopped

    def close(self) -> None:
        if self._recorder is not None:
            self._recorder.close()
            self._recorder = None
            with_size = self.path.stat().st_size if self.path.exists() else self.bytes
            self.bytes = with_size
        if self._stopped is None:
            self._stopped = "closed"

    def discard(self) -> bool:
        # The SDK's file is created with the first frame: with none, there is nothing.
        return not self.frames


# ----------------------------------------------------------------------------- the command


def _fail(args: argparse.Namespace, kind: ErrorKind, message: str, code: str | None = None) -> None:
    if getattr(args, "json", False):
        print(json.dumps(json_error(kind, message, code)), flush=True)
    else:
        label = f"{code}: " if code else ""
        print(f"{PROG}: {label}{message}", file=sys.stderr, flush=True)


def _usage(args: argparse.Namespace, message: str) -> int:
    _fail(args, ErrorKind.USAGE, message)
    return int(ExitCode.USAGE)


def record(args: argparse.Namespace) -> int:
    """Record ``args.camera``; the exit code (see the module)."""
    config_path = getattr(args, "config", None) or os.environ.get(CONFIG_ENV) or None
    if not config_path:
        return _usage(args, f"give --config FILE (or ${CONFIG_ENV})")
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        return _usage(args, f"invalid configuration: {exc}")
    name = args.camera
    settings = config.cameras.get(name)
    if settings is None:
        names = ", ".join(sorted(config.cameras)) or "none"
        return _usage(args, f"no camera named {name!r} in {config_path} (its cameras: {names})")
    if isinstance(settings, RequestCameraSettings):
        return _usage(
            args,
            f"camera {name!r} gets its images with each request: the server cannot grab it "
            "(record on the robot's side, or save the images it sends)",
        )
    out = Path(args.out)
    given = _Bounds(args.frames, args.max_bytes, args.duration)
    if given.frames is None and given.bytes is None and given.duration_s is None:
        given.frames = DEFAULT_FRAMES
    fmt = args.format
    if fmt == "auto":
        bag = out.suffix.lower() in REALSENSE_SUFFIXES
        realsense = isinstance(settings, RealSenseCameraSettings) and bag
        fmt = "realsense" if realsense else "cellvision"
    try:
        camera = make_camera(name, settings, base_dir=config.base_dir)
    except ValueError as exc:
        return _usage(args, f"camera {name!r}: {exc}")
    sink: _Sink | None = None
    try:
        camera.open()
        if fmt == "realsense" and camera.intrinsics is None and not camera.status()["last_error"]:
            camera.close()
            return _usage(
                args,
                f"camera {name!r} has no intrinsics: the RealSense format needs them (give "
                "intrinsics in the configuration)",
            )
        if fmt == "realsense":
            if out.suffix.lower() not in REALSENSE_SUFFIXES:
                camera.close()
                return _usage(
                    args,
                    f"{out}: a RealSense recording is a *.db3 file (pyrealsense2 2.59 writes "
                    "rosbag2 and refuses other names)",
                )
            if out.exists():
                return _usage(args, f"{out} already exists: the RealSense file is written anew")
            sink = _RealSenseSink(out, camera, settings, given)
        else:
            created = not out.exists()
            sink = _RecordingSink(
                RecordingWriter(
                    out,
                    camera=name,
                    source=camera.source,
                    settings=public_settings(settings),
                    intrinsics=camera.intrinsics,
                    config_hash=config.config_hash,
                    max_frames=given.frames,
                    max_bytes=given.bytes,
                    max_duration_s=given.duration_s,
                ),
                created=created,
            )
    except RecordingError as exc:
        camera.close()
        return _usage(args, str(exc))
    return _record_frames(args, camera, sink, fmt)


class _Terminated(BaseException):
    """SIGTERM arrived: stop as for Ctrl-C (a BaseException, as KeyboardInterrupt is, so that
    no camera's ``except Exception`` takes it for a failure)."""


class _SigtermStops:
    """While recording, SIGTERM (``timeout``, ``systemctl stop``) raises :class:`_Terminated`
    in the main thread, once; from :meth:`closing` on (the recording being closed, or a first
    SIGTERM taken) it is ignored, so that the manifest is written whole. The previous handler
    is restored at exit. Outside the main thread (no signals there) it does nothing."""

    def __init__(self) -> None:
        self._closing = False
        self._previous: Any = None
        self._installed = False

    def __enter__(self) -> _SigtermStops:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGTERM, self._stop)
            self._installed = True
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._installed:
            signal.signal(signal.SIGTERM, self._previous)

    def closing(self) -> None:
        self._closing = True

    def _stop(self, signum: int, frame: object) -> None:
        if not self._closing:
            self._closing = True
            raise _Terminated


def _record_frames(args: argparse.Namespace, camera: Camera, sink: _Sink, fmt: str) -> int:
    with _SigtermStops() as sigterm:
        return _record_until_stopped(args, camera, sink, fmt, sigterm)


def _record_until_stopped(
    args: argparse.Namespace, camera: Camera, sink: _Sink, fmt: str, sigterm: _SigtermStops
) -> int:
    started = time.monotonic()
    failure: str | None = None
    ended = False
    code = int(ExitCode.OK)
    last: int | None = None
    try:
        while sink.stopped_by() is None:
            if args.interval and sink.frames:
                wait = started + sink.frames * args.interval - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                if sink.stopped_by() is not None:
                    break
            frame = camera.grab(timeout_s=args.timeout, newer_than=last)
            last = frame.index
            if not sink.add(frame):
                break
    except CameraUnavailable as exc:
        # A replayed source (a recording, a playback, a folder played once) that ran out
        # after giving frames is a complete recording of it, not a failure.
        ended = sink.frames > 0 and camera.status().get("state") == "ended"
        if not ended:
            failure = exc.message
            code = ExitCode.FAILED
    except CellvisionError as exc:  # a camera that refuses grabs (InvalidArgument)
        failure = exc.message
        code = ExitCode.FAILED
    except RecordingError as exc:  # the disk is full, a frame the format cannot hold
        failure = str(exc)
        code = ExitCode.FAILED
    except KeyboardInterrupt:
        failure = "interrupted"
        code = ExitCode.INTERRUPTED
    except _Terminated:
        failure = "terminated by SIGTERM"
        code = TERMINATED
    finally:
        sigterm.closing()
        try:
            sink.close()
        finally:
            camera.close()
    removed = code != ExitCode.OK and sink.discard()
    elapsed = time.monotonic() - started
    summary = {
        "camera": camera.name,
        "source": camera.source,
        "format": fmt,
        "path": str(sink.path),
        "frames": sink.frames,
        "bytes": sink.bytes,
        "duration_s": round(elapsed, 3),
        "stopped_by": failure
        if failure is not None
        else "source ended"
        if ended
        else sink.stopped_by(),
        "ok": code == ExitCode.OK,
        "removed": removed,
    }
    if failure is not None and code == ExitCode.FAILED:
        # A camera's own messages name it already ("camera 'c' (aravis): ...").
        named = failure.startswith(f"camera {camera.name!r}")
        message = failure if named else f"camera {camera.name!r}: {failure}"
        _fail(args, ErrorKind.DEVICE, message, "CAMERA_UNAVAILABLE")
    if getattr(args, "json", False):
        print(json.dumps(summary), flush=True)
    else:
        what = "recorded" if code == ExitCode.OK else f"stopped ({failure}) after recording"
        print(
            f"{what} {sink.frames} frame{'s' if sink.frames != 1 else ''} of camera "
            f"{camera.name!r} ({camera.source}), {sink.bytes} bytes in {elapsed:.1f} s, "
            f"into {sink.path}"
            + (
                "; the source ended"
                if ended
                else f"; stopped by the {summary['stopped_by']} bound"
                if code == ExitCode.OK
                else ""
            )
            + (" (removed: nothing was recorded)" if removed else ""),
            flush=True,
        )
    return int(code)
