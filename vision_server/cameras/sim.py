"""The ``sim`` source: frames rendered by the simulated cell.

The camera owns a :class:`simulation.SimCell` built from the scene; with a world-state file it
follows what another process (the robot client) did: each render first adopts a newer world
from that file. A grab renders a new frame (new sensor noise, index + 1), so successive grabs
are distinct frames. ``SimCell`` is not thread-safe: renders are serialised by a lock.
"""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

from simulation import SimCell

from .base import Camera, CameraFrame, color_image, log, path_forms, public_path, replace_paths
from .clock import Clock
from .settings import Intrinsics, SimCameraSettings

__all__ = ["SimCamera"]


def _resolve(path: Path, base_dir: Path | None) -> Path:
    path = path.expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    return path


class SimCamera(Camera):
    """A camera of the simulated cell.

    Building it loads the scene: a missing or invalid scene, or a camera the scene does not
    have, raises ``ValueError`` at once (it is a configuration error, not an absent device).
    """

    source = "sim"

    def __init__(
        self,
        name: str,
        settings: SimCameraSettings,
        *,
        base_dir: Path | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.settings = settings
        self.scene_path = _resolve(settings.scene, base_dir)
        self.state_path = (
            None if settings.state_file is None else _resolve(settings.state_file, base_dir)
        )
        # Configuration errors reach a RELOAD's client too: paths as configured, full in the log.
        shown = dict.fromkeys(path_forms(self.scene_path), public_path(settings.scene))
        if self.state_path is not None and settings.state_file is not None:
            shown.update(
                dict.fromkeys(path_forms(self.state_path), public_path(settings.state_file))
            )

        def config_error(message: str) -> ValueError:
            public = replace_paths(message, shown)
            if public != message:
                log.warning("camera %r: %s", name, message)
            return ValueError(public)

        try:
            cell = SimCell.from_yaml(
                self.scene_path, seed=settings.seed, state_path=self.state_path
            )
        except (OSError, ValueError) as exc:
            raise config_error(
                f"camera {name!r}: cannot load scene {self.scene_path}: {exc}"
            ) from exc
        try:
            spec = cell.scene.camera(settings.camera)
        except KeyError as exc:
            raise config_error(
                f"camera {name!r}: {exc.args[0]} in scene {self.scene_path}"
            ) from exc
        intrinsics = settings.intrinsics or Intrinsics.from_geometry(spec.intrinsics)
        size = (spec.intrinsics.width, spec.intrinsics.height)
        if (intrinsics.width, intrinsics.height) != size:
            raise ValueError(
                f"camera {name!r}: intrinsics are for {intrinsics.width}x{intrinsics.height} "
                f"but the scene camera {settings.camera!r} renders {size[0]}x{size[1]}"
            )
        super().__init__(name, intrinsics=intrinsics, has_depth=spec.depth is not None, clock=clock)
        for private, public in shown.items():
            self.hide_path(private, public)
        self._cell = cell
        self._lock = threading.Lock()
        self._next_index = 0
        self._error: str | None = None

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        # Each grab renders a new frame with a new index: always fresh and newer.
        self._check_open()
        with self._lock:
            try:
                frame = self._cell.render(self.settings.camera)
                color = color_image(frame.color)
            except Exception as exc:  # the world-state file or the renderer failed
                error = self.unavailable(f"rendering {self.settings.camera!r} failed: {exc}")
                self._error = error.message
                raise error from exc
            result = CameraFrame(color, frame.depth, self._clock.time(), self._next_index)
            self._next_index += 1
            return result

    def status(self) -> dict[str, Any]:
        with self._lock:
            return {
                "name": self.name,
                "source": self.source,
                "scene": str(self.scene_path),
                "camera": self.settings.camera,
                "state": "closed" if self.closed else "ready",
                "connected": not self.closed,
                "frames": self._next_index,
                "last_error": self._error,
                "reconnects": 0,
            }
