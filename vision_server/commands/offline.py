"""Inspections offline, on image files: the service that ``vision-server run`` and the golden
cases (:mod:`vision_server.commands.golden`) call directly, without a listener.

:func:`offline_service` serves one configured inspection with one worker; its camera is replaced
by one whose images come with the request, with the same intrinsics, so that everything after
the images (checks, the inspection, the overlay) is what a served request goes through.
:func:`file_request` reads image files into a request: PNG and JPEG files go to the service's
worker undecoded (their headers are checked against the pixel limit first), other formats are
decoded by :func:`protocol.image_files.payload_from_file`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from protocol import ImagePayload, ImageRole
from protocol.image_files import payload_from_file

from ..cameras import (
    Intrinsics,
    RecordingCameraSettings,
    RecordingError,
    RecordingReader,
    RequestCamera,
    RequestCameraSettings,
)
from ..config import ServiceSettings
from ..frontends import payload_loader
from ..inspections import Inspection
from ..service import Catalog, InspectionService, InspectRequest


def offline_service(
    inspection: Inspection,
    settings: Any,
    base_dir: Path,
    *,
    config_hash: str = "",
    max_image_pixels: int | None = None,
    intrinsics: Intrinsics | None = None,
) -> InspectionService:
    """A one-worker service for ``inspection`` alone, its camera (configured with
    ``settings``) replaced by a request camera with the same intrinsics. ``max_image_pixels``:
    the configuration's limit (default: the server's default). ``intrinsics``: those the
    images were taken with (a recording's), used when the settings give none; a recording
    camera's settings without intrinsics take its recording's."""
    known = getattr(settings, "intrinsics", None) or intrinsics
    if known is None and isinstance(settings, RecordingCameraSettings):
        known = _recording_intrinsics(settings, base_dir)
    camera = RequestCamera(
        inspection.camera,
        RequestCameraSettings(known, depth=inspection.uses_depth),
    )
    if camera.intrinsics is None and inspection.uses_depth:
        camera = _with_scene_intrinsics(inspection.camera, settings, base_dir) or camera
    catalog = Catalog.build([camera], [inspection], config_hash=config_hash)
    served = ServiceSettings(workers=1, queue_depth=0)
    if max_image_pixels is not None:
        served = ServiceSettings(workers=1, queue_depth=0, max_image_pixels=max_image_pixels)
    return InspectionService(catalog, served)


def _recording_intrinsics(settings: RecordingCameraSettings, base_dir: Path) -> Intrinsics | None:
    """The intrinsics a recording camera's recording holds (None when it cannot be read: the
    images are then inspected without, as for a camera that declares none)."""
    path = settings.path.expanduser()
    try:
        return RecordingReader(path if path.is_absolute() else base_dir / path).intrinsics
    except RecordingError:
        return None


def _with_scene_intrinsics(name: str, settings: Any, base_dir: Path) -> RequestCamera | None:
    """For a sim camera without configured intrinsics, the scene camera's own."""
    from ..cameras import SimCameraSettings, make_camera

    if not isinstance(settings, SimCameraSettings):
        return None
    sim = make_camera(name, settings, base_dir=base_dir)
    try:
        return RequestCamera(name, RequestCameraSettings(sim.intrinsics, depth=True))
    finally:
        sim.close()


def image_payload(path: Path, role: ImageRole) -> ImagePayload:
    """The payload for an image file of any format OpenCV reads (see
    :mod:`protocol.image_files`); ValueError naming the file when it cannot be read."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read {path}: {exc.strerror or exc}") from None
    return payload_from_file(data, name=str(path), role=role)


def file_request(
    inspection: str,
    color: ImagePayload,
    depth: Sequence[ImagePayload] = (),
    *,
    overlay: str | None = None,
    peer: str = "offline",
    request_id: int = 0,
) -> InspectRequest:
    """The request for one colour image file (and its depth frames), read by
    :func:`image_payload`; the service decodes them in its worker."""
    return InspectRequest(
        inspection,
        payload_loader((color, *depth)),
        overlay=overlay,
        peer=peer,
        request_id=request_id,
    )


__all__ = ["file_request", "image_payload", "offline_service"]
