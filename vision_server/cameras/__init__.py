"""Cameras of the vision server: a name -> a source of frames.

Sources (``source:`` in the configuration): ``request`` (images arrive with the request),
``opencv`` (device, stream or video file through ``cv2.VideoCapture``, latest-frame semantics,
automatic reconnect), ``folder`` (replay a directory), ``sim`` (the simulated cell),
``realsense`` (Intel RealSense RGB-D through pyrealsense2, an optional extra), ``aravis``
(GigE Vision / USB3 Vision through Aravis, an optional extra), ``genicam`` (GenICam through a
vendor's GenTL producer and harvesters, an optional extra) and ``recording`` (replay a
recording that ``vision-server record`` made of any camera, frame by frame, with its depth,
timestamps and intrinsics). Any source may deliver a depth frame (uint16 mm) registered to its
colour frame.

Public API:

- Settings (frozen, validated): :class:`Intrinsics`, :class:`RequestCameraSettings`,
  :class:`OpenCVCameraSettings`, :class:`FolderCameraSettings`, :class:`SimCameraSettings`,
  :class:`RealSenseCameraSettings`, :class:`GenICamCameraSettings`, :class:`AravisCameraSettings`,
  :class:`RecordingCameraSettings`, ``CameraSettings`` (their union), ``SOURCE_NAMES``
  (source name -> settings class).
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
  :class:`SimCamera`, :class:`RealSenseCamera`, :class:`GenICamCamera`, :class:`AravisCamera`
  (the SDK is imported when the camera first connects, so no extra is needed to load this
  package), :class:`RecordingCamera` (whose :meth:`~RecordingCamera.frame_at` reads any frame
  without moving the camera's position).
- Recordings (:mod:`.recording`, the format in docs/recording.md): :class:`RecordingWriter`
  (bounded by frames, bytes or seconds; interrupted, it still replays what it wrote),
  :class:`RecordingReader` (frames read one at a time), :class:`RecordingFrame`,
  :class:`RecordedFrame`, :class:`RecordingError` (a ``ValueError`` naming the cause),
  :func:`public_settings` (a camera's settings as a manifest shows them),
  ``RECORDING_MANIFEST`` (``recording.json``).
"""

from .aravis import AravisCamera
from .base import Camera, CameraFrame
from .clock import SYSTEM_CLOCK, Clock, ManualClock
from .factory import make_camera
from .folder import FolderCamera
from .genicam import GenICamCamera
from .mount import MOUNT_KEYS, CameraMount
from .opencv import OpenCVCamera
from .realsense import RealSenseCamera
from .realsense_recording import RealSenseRecorder
from .recording import MANIFEST as RECORDING_MANIFEST
from .recording import (
    RecordedFrame,
    RecordingCamera,
    RecordingError,
    RecordingFrame,
    RecordingReader,
    RecordingWriter,
    public_settings,
)
from .request import RequestCamera
from .settings import (
    SOURCE_NAMES,
    AravisCameraSettings,
    CameraSettings,
    FolderCameraSettings,
    GenICamCameraSettings,
    Intrinsics,
    OpenCVCameraSettings,
    RealSenseCameraSettings,
    RecordingCameraSettings,
    RequestCameraSettings,
    SimCameraSettings,
)
from .sim import SimCamera

__all__ = [
    "AravisCamera",
    "AravisCameraSettings",
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
    "RECORDING_MANIFEST",
    "RecordedFrame",
    "RecordingCamera",
    "RecordingCameraSettings",
    "RecordingError",
    "RecordingFrame",
    "RecordingReader",
    "RecordingWriter",
    "RequestCamera",
    "RequestCameraSettings",
    "SOURCE_NAMES",
    "SYSTEM_CLOCK",
    "SimCamera",
    "SimCameraSettings",
    "make_camera",
    "public_settings",
]
