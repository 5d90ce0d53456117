"""The ``folder`` source: images from a directory, for replay.

Each grab reads the next file (natural sort order: ``img2`` before ``img10``), so successive
grabs are always distinct frames. ``cycle`` starts again after the last file and re-scans the
directory at that moment (files added or removed are seen); ``once`` raises
``CameraUnavailable`` after the last one. A missing or empty directory is reported on grab and
scanned again at the next grab.

Confinement: a file is read only if its resolved path (symlinks followed) lies inside the
resolved directory; a symlink that points outside is refused with ``CameraUnavailable`` naming
it. The glob patterns cannot be absolute or contain ``..`` (checked in the settings).

Messages to clients name the folder as configured (relative to the configuration file, or by
its last component when absolute) and files relative to it; the log gets the full paths.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .base import Camera, CameraFrame, color_image, public_path
from .clock import Clock
from .settings import FolderCameraSettings

__all__ = ["FolderCamera", "natural_key"]

_READ_FLAGS = {
    "gray": cv2.IMREAD_GRAYSCALE,
    "bgr": cv2.IMREAD_COLOR,
    "unchanged": cv2.IMREAD_UNCHANGED,
}
_DIGITS = re.compile(r"(\d+)")


def natural_key(text: str) -> tuple[tuple[int, int | str], ...]:
    """Sort key that orders embedded numbers by value: ``img2`` < ``img10``."""
    return tuple(
        (0, int(part)) if part.isdigit() else (1, part) for part in _DIGITS.split(text) if part
    )


class FolderCamera(Camera):
    """Replays the images of a directory. See the module for order and confinement."""

    source = "folder"

    @property
    def sequence(self) -> bool:
        # Each grab reads the next file: a grab to look at one would skip it for the cell.
        return True

    def __init__(
        self,
        name: str,
        settings: FolderCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        super().__init__(
            name,
            intrinsics=settings.intrinsics,
            has_depth=settings.depth_glob is not None,
            clock=clock,
        )
        self.settings = settings
        root = settings.path.expanduser()
        if not root.is_absolute() and base_dir is not None:
            root = base_dir / root
        self.root = root
        self.hide_path(root, public_path(settings.path))
        self._lock = threading.Lock()
        self._files: list[Path] = []
        self._depth_files: list[Path | None] = []
        self._position = 0
        self._next_index = 0
        self._frames = 0
        self._error: str | None = None

    # -- scanning --------------------------------------------------------------------------

    def _resolved_root(self) -> Path:
        root = self.root.resolve()
        if not root.is_dir():
            raise self.unavailable(f"folder {self.root} does not exist or is not a directory")
        return root

    def _matching(self, root: Path, pattern: str) -> list[Path]:
        files = [path for path in root.glob(pattern) if path.is_file() or path.is_symlink()]
        return sorted(files, key=lambda path: natural_key(path.relative_to(root).as_posix()))

    def _scan(self) -> None:
        """List the images (and their depth partners); caller holds the lock."""
        root = self._resolved_root()
        s = self.settings
        colour = self._matching(root, s.glob)
        depth: list[Path | None] = [None] * len(colour)
        if s.depth_glob is not None:
            depth_files = self._matching(root, s.depth_glob)
            taken = set(depth_files)
            colour = [path for path in colour if path not in taken]
            by_stem = {path.stem: path for path in depth_files}
            if len(by_stem) == len(depth_files) and all(p.stem in by_stem for p in colour):
                depth = [by_stem[path.stem] for path in colour]
            elif len(depth_files) == len(colour):
                depth = list(depth_files)
            else:
                raise self.unavailable(
                    f"folder {self.root}: {len(colour)} images match {s.glob!r} but "
                    f"{len(depth_files)} depth images match {s.depth_glob!r}, and their file "
                    f"stems do not pair them"
                )
        self._files = colour
        self._depth_files = depth
        self._position = 0

    # -- reading ---------------------------------------------------------------------------

    def _confined(self, path: Path) -> Path:
        root = self.root.resolve()
        resolved = path.resolve()
        if not resolved.is_relative_to(root):
            raise self.unavailable(f"refused {path}: it resolves outside the folder {root}")
        return resolved

    def _decode(self, path: Path, flags: int) -> NDArray[Any]:
        resolved = self._confined(path)
        try:
            data = np.frombuffer(resolved.read_bytes(), dtype=np.uint8)
        except OSError as exc:
            raise self.unavailable(f"cannot read {path}: {exc.strerror or exc}") from exc
        image = cv2.imdecode(data, flags) if data.size else None
        if image is None:
            raise self.unavailable(f"cannot decode {path}: not a readable image")
        return image

    def _read(self, path: Path, depth_path: Path | None) -> tuple[NDArray[np.uint8], Any]:
        try:
            color = color_image(self._decode(path, _READ_FLAGS[self.settings.color]))
        except ValueError as exc:
            raise self.unavailable(f"{path}: {exc}") from exc
        k = self.intrinsics
        if k is not None and (color.shape[1], color.shape[0]) != (k.width, k.height):
            raise self.unavailable(
                f"{path}: the image is {color.shape[1]}x{color.shape[0]} but the intrinsics "
                f"are for {k.width}x{k.height}"
            )
        if depth_path is None:
            return color, None
        depth = self._decode(depth_path, cv2.IMREAD_UNCHANGED)
        if depth.dtype != np.uint16 or depth.ndim != 2:
            raise self.unavailable(
                f"{depth_path}: a depth image must be single-channel uint16 (mm), got "
                f"{depth.dtype} with shape {depth.shape}"
            )
        if depth.shape != color.shape[:2]:
            raise self.unavailable(
                f"{depth_path}: depth size {depth.shape[1]}x{depth.shape[0]} differs from the "
                f"colour image {path.name} ({color.shape[1]}x{color.shape[0]})"
            )
        return color, depth

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        # Every grab reads a new file with a new index, so it is always fresh and newer.
        self._check_open()
        with self._lock:
            try:
                return self._next_frame()
            except Exception as exc:
                self._error = getattr(exc, "message", str(exc))
                raise

    def _next_frame(self) -> CameraFrame:
        s = self.settings
        exhausted = self._position >= len(self._files)
        if not self._files or (exhausted and s.mode == "cycle"):
            self._scan()
        if not self._files:
            raise self.unavailable(f"folder {self.root} has no files matching {s.glob!r}")
        if self._position >= len(self._files):
            raise self.unavailable(
                f"folder {self.root} exhausted after {len(self._files)} images (mode: once)"
            )
        path = self._files[self._position]
        depth_path = self._depth_files[self._position]
        self._position += 1
        color, depth = self._read(path, depth_path)
        root = self.root.resolve()  # which file, for the result (relative: no host paths)
        source = path.relative_to(root).as_posix() if path.is_relative_to(root) else path.name
        frame = CameraFrame(color, depth, self._clock.time(), self._next_index, source)
        self._next_index += 1
        self._frames += 1
        return frame

    def status(self) -> dict[str, Any]:
        with self._lock:
            exhausted = self.settings.mode == "once" and self._position >= len(self._files) > 0
            connected = not self.closed and not exhausted and self.root.is_dir()
            return {
                "name": self.name,
                "source": self.source,
                "folder": str(self.root),
                "state": "closed" if self.closed else ("ended" if exhausted else "ready"),
                "connected": connected,
                "frames": self._frames,
                "last_error": self._error,
                "reconnects": 0,
                "images": len(self._files),
                "position": self._position,
            }
