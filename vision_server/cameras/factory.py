"""``make_camera``: build the camera object for a name and its settings."""

from __future__ import annotations

from pathlib import Path

from .aravis import AravisCamera
from .base import Camera
from .clock import Clock
from .folder import FolderCamera
from .genicam import GenICamCamera
from .opencv import OpenCVCamera
from .realsense import RealSenseCamera
from .recording import RecordingCamera
from .request import RequestCamera
from .settings import (
    AravisCameraSettings,
    CameraSettings,
    FolderCameraSettings,
    GenICamCameraSettings,
    OpenCVCameraSettings,
    RealSenseCameraSettings,
    RecordingCameraSettings,
    RequestCameraSettings,
    SimCameraSettings,
)
from .sim import SimCamera

__all__ = ["make_camera"]


def make_camera(
    name: str, settings: CameraSettings, *, base_dir: Path, clock: Clock | None = None
) -> Camera:
    """The camera ``name`` for ``settings``, not yet opened (call ``open()``).

    ``clock``: the time the camera reads and waits on (the system's unless given, see
    :mod:`vision_server.cameras.clock`).

    Relative paths in the settings (a video file, a folder, a scene, a world-state file, a
    recording)
    resolve against ``base_dir``, the configuration file's directory. Raises ``ValueError`` for
    a configuration error found without touching hardware (an unreadable scene, a camera the
    scene lacks); an absent device or folder is reported later, by ``grab``.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"camera name must be a non-empty string, got {name!r}")
    if isinstance(settings, RequestCameraSettings):
        return RequestCamera(name, settings, clock=clock)
    if isinstance(settings, OpenCVCameraSettings):
        return OpenCVCamera(name, settings, base_dir=base_dir, clock=clock)
    if isinstance(settings, FolderCameraSettings):
        return FolderCamera(name, settings, base_dir=base_dir, clock=clock)
    if isinstance(settings, SimCameraSettings):
        return SimCamera(name, settings, base_dir=base_dir, clock=clock)
    if isinstance(settings, RealSenseCameraSettings):
        return RealSenseCamera(name, settings, base_dir=base_dir, clock=clock)
    if isinstance(settings, GenICamCameraSettings):
        return GenICamCamera(name, settings, base_dir=base_dir, clock=clock)
    if isinstance(settings, AravisCameraSettings):
        return AravisCamera(name, settings, clock=clock)
    if isinstance(settings, RecordingCameraSettings):
        return RecordingCamera(name, settings, base_dir=base_dir, clock=clock)
    raise TypeError(f"camera {name!r}: unknown settings type {type(settings).__name__}")
