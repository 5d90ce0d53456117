"""Cameras of the vision server: a name -> a source of frames.

Sources (``source:`` in the configuration): ``request`` (images arrive with the request),
``opencv`` (device, stream or video file through ``cv2.VideoCapture``, latest-frame semantics,
automatic reconnect), ``folder`` (replay a directory), ``sim`` (the simulated cell),
``realsense`` (Intel RealSense RGB-D through pyrealsense2, an optional extra) and ``genicam``
(GigE Vision / USB3 Vision through harvesters, an optional extra). Any source
may deliver a depth frame (uint16 mm) registered to its colour frame.

Public API:

- Settings (frozen, validated): :class:`Intrinsics`, :class:`RequestCameraSettings`,
  :class:`OpenCVCameraSettings`, :class:`FolderCameraSettings`, :class:`SimCameraSettings`,
  :class:`RealSenseCameraSettings`, :class:`GenICamCameraSettings`,
  ``CameraSettings`` (their union), ``SOURCE_NAMES`` (source name -> settings class).
- :class:`CameraFrame` (``color``, ``depth``, ``timestamp``, ``index``) and :class:`Camera`
  (``name``, ``source``, ``has_depth``, ``intrinsics``, ``open()``,
  ``grab(*, timeout_s, newer_than=None)``, ``grab_many(n, *, timeout_s)``, ``status()``,
  ``close()``, ``descriptor()``).
- :func:`make_camera` ``(name, settings, *, base_dir, clock=None) -> Camera``.
- :class:`RealSenseRecorder`: writes a RealSense recording (the SDK's own file) that the
  ``realsense`` source plays with ``playback:``.
- Time: :class:`Clock` (what a camera reads and waits on), ``SYSTEM_CLOCK`` (the default) and
  :class:`ManualClock` (a clock a test advances by hand).
- The implementations: :class:`RequestCamera`, :class:`OpenCVCamera`, :class:`FolderCamera`,
  :class:`SimCamera`, :class:`RealSenseCamera`, :class:`GenICamCamera` (the vendor SDK is
  imported when the camera first connects, so neither extra is needed to load this package).
"""

from .base import Camera, CameraFrame
from .clock import SYSTEM_CLOCK, Clock, ManualClock
from .factory import make_camera
from .folder import FolderCamera
from .genicam import GenICamCamera
from .mount import MOUNT_KEYS, CameraMount
from .opencv import OpenCVCamera
from .realsense import RealSenseCamera
from .realsense_recording import RealSenseRecorder
from .request import RequestCamera
from .settings import (
    SOURCE_NAMES,
    CameraSettings,
    FolderCameraSettings,
    GenICamCameraSettings,
    Intrinsics,
    OpenCVCameraSettings,
    RealSenseCameraSettings,
    RequestCameraSettings,
    SimCameraSettings,
)
from .sim import SimCamera

__all__ = [
    "Camera",
    "CameraFrame",
    "CameraMount",
    "CameraSettings",
    "Clock",
    "FolderCamera",
    "FolderCameraSettings",
    "GenICamCamera",
    "GenICamCameraSettings",
    "Intrinsics",
    "MOUNT_KEYS",
    "ManualClock",
    "OpenCVCamera",
    "OpenCVCameraSettings",
    "RealSenseCamera",
    "RealSenseCameraSettings",
    "RealSenseRecorder",
    "RequestCamera",
    "RequestCameraSettings",
    "SOURCE_NAMES",
    "SYSTEM_CLOCK",
    "SimCamera",
    "SimCameraSettings",
    "make_camera",
]
