"""The ``request`` source: the images come with each request (the camera on the robot's tool)."""

from __future__ import annotations

from typing import Any

from protocol import InvalidArgument

from .base import Camera, CameraFrame
from .clock import Clock
from .settings import RequestCameraSettings

__all__ = ["RequestCamera"]


class RequestCamera(Camera):
    """A camera the server never reads: ``grab`` raises ``InvalidArgument``."""

    source = "request"

    def __init__(
        self, name: str, settings: RequestCameraSettings, *, clock: Clock | None = None
    ) -> None:
        super().__init__(
            name, intrinsics=settings.intrinsics, has_depth=settings.depth, clock=clock
        )
        self.settings = settings

    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        raise InvalidArgument(
            f"camera {self.name!r} gets its images from the request: the server cannot "
            f"capture from it",
            details={"camera": self.name, "source": self.source},
        )

    def grab_many(self, n: int, *, timeout_s: float) -> list[CameraFrame]:
        return [self.grab(timeout_s=timeout_s)]

    def status(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "source": self.source,
            "state": "closed" if self.closed else "request",
            "connected": not self.closed,
            "frames": 0,
            "last_error": None,
            "reconnects": 0,
        }
