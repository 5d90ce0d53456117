"""What every camera source offers: :class:`CameraFrame` and the :class:`Camera` base class.

Threads: ``grab``/``grab_many``/``status`` may be called from several worker threads at once;
``open`` from the thread that owns the camera (the server's configuration code), ``close`` from
any one thread (the configuration code closes a replaced camera in a thread of its own once the
last request using it is done).

Messages to clients: a :class:`protocol.CameraUnavailable` goes to the client, so its text names
the camera and paths only as the configuration wrote them (relative) or by their file name; the
absolute paths on the server go to the server's log (see :meth:`Camera.unavailable`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, ClassVar

import cv2
import numpy as np
from numpy.typing import NDArray

from protocol import CameraUnavailable, InvalidArgument

from .clock import SYSTEM_CLOCK, Clock
from .settings import Intrinsics

__all__ = ["Camera", "CameraFrame", "color_image", "path_forms", "public_path", "replace_paths"]

log = logging.getLogger("vision_server.cameras")


@dataclass(frozen=True)
class CameraFrame:
    """One capture.

    ``color``: (H, W) gray or (H, W, 3) BGR, uint8. ``depth``: (H, W) uint16 millimetres
    (0 = no depth) registered to ``color``, or None. ``timestamp``: seconds since the epoch
    on the camera's clock (``time.time()`` unless a test gives another) when the frame was
    captured (read from the device, file or renderer). ``index``: the camera's frame counter;
    it only increases, also across reconnects, so frames with different indices are different
    captures. Both arrays are read-only because one frame may be handed to several
    requests at once: copy before drawing on them. ``source``: where the frame was
    read from, for people (a folder camera's file, relative to its folder), or None.
    """

    color: NDArray[np.uint8]
    depth: NDArray[np.uint16] | None
    timestamp: float
    index: int
    source: str | None = None

    def __post_init__(self) -> None:
        if self.color.dtype != np.uint8 or not (
            self.color.ndim == 2 or (self.color.ndim == 3 and self.color.shape[2] == 3)
        ):
            raise ValueError(
                f"color must be (H, W) or (H, W, 3) uint8, got {self.color.shape} "
                f"{self.color.dtype}"
            )
        if self.depth is not None and (
            self.depth.dtype != np.uint16 or self.depth.shape != self.color.shape[:2]
        ):
            raise ValueError(
                f"depth must be (H, W) uint16 of the colour image's size {self.color.shape[:2]}, "
                f"got {self.depth.shape} {self.depth.dtype}"
            )
        self.color.flags.writeable = False
        if self.depth is not None:
            self.depth.flags.writeable = False

    @property
    def width(self) -> int:
        return int(self.color.shape[1])

    @property
    def height(self) -> int:
        return int(self.color.shape[0])


def color_image(image: NDArray[Any]) -> NDArray[np.uint8]:
    """Bring a decoded image to the colour convention: uint8, (H, W) gray or (H, W, 3) BGR.

    (H, W, 1) becomes (H, W); BGRA becomes BGR. Raises ``ValueError`` (with the reason) for
    anything else, for example 16-bit images.
    """
    if image.dtype != np.uint8:
        raise ValueError(f"colour images must be 8-bit, this one is {image.dtype}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3):
        return np.ascontiguousarray(image)
    raise ValueError(f"unsupported image shape {image.shape}")


def path_forms(path: Path | str) -> list[str]:
    """The spellings of ``path`` a message may contain: as given and resolved."""
    forms = [str(path)]
    with contextlib.suppress(OSError, RuntimeError):  # a symlink loop: keep the given form
        forms.append(str(Path(path).resolve()))
    return forms


def replace_paths(text: str, shown: Mapping[str, str]) -> str:
    """``text`` with each key of ``shown`` replaced by its value, longest key first (so that
    a file inside a replaced folder keeps its name relative to the folder)."""
    for private in sorted(shown, key=len, reverse=True):
        text = text.replace(private, shown[private])
    return text


def public_path(configured: Path | str) -> str:
    """How a path from the configuration is shown to clients: as written when it is relative
    (to the configuration file), by its last component when it is absolute."""
    text = str(configured)
    path = Path(text).expanduser()
    if not path.is_absolute():
        return text
    return path.name or text


class Camera(ABC):
    """A named camera of the server.

    ``open()`` starts the source (threads, devices) and never raises because a device is
    absent: unavailability is reported by ``grab`` (``protocol.CameraUnavailable``, whose
    message names the camera and the cause) and by ``status()``. ``close()`` stops and joins
    everything; it is idempotent. A camera is also a context manager (open ... close).
    """

    source: ClassVar[str] = ""
    """The source kind: ``request``, ``opencv``, ``folder``, ``sim``, ``realsense`` or
    ``genicam``."""

    def __init__(
        self,
        name: str,
        *,
        intrinsics: Intrinsics | None,
        has_depth: bool,
        clock: Clock | None = None,
    ) -> None:
        self._name = name
        self._intrinsics = intrinsics
        self._has_depth = has_depth
        self._clock: Clock = clock or SYSTEM_CLOCK
        self._closed = threading.Event()
        self._private_paths: dict[str, str] = {}
        self._logged_cause: str | None = None

    @property
    def name(self) -> str:
        return self._name

    @property
    def intrinsics(self) -> Intrinsics | None:
        return self._intrinsics

    @property
    def has_depth(self) -> bool:
        """True when frames carry a registered depth image."""
        return self._has_depth

    @property
    def triggered(self) -> bool:
        """True when a grab fires a trigger or takes a frame a trigger line started: a frame read
        only to be looked at (the console's live view) would then be a frame taken from the
        cell's work. Such a camera's view shows the last frame an inspection took."""
        return False

    @property
    def sequence(self) -> bool:
        """True when every grab takes the next frame of a fixed sequence (a folder replay): a
        frame read only to be looked at would be skipped by the cell's next inspection. Such a
        camera's view also shows the last frame an inspection took."""
        return False

    @property
    def view_takes_frames(self) -> bool:
        """Whether a viewer (the console) may grab frames of its own: not from a triggered
        camera nor from a sequence, whose frames belong to the cell's inspections."""
        return not (self.triggered or self.sequence)

    def descriptor(self) -> dict[str, Any]:
        """JSON-able description: name, source, depth, intrinsics (when known)."""
        desc: dict[str, Any] = {"name": self.name, "source": self.source, "depth": self.has_depth}
        if self.intrinsics is not None:
            desc["intrinsics"] = self.intrinsics.to_dict()
        return desc

    def open(self) -> None:  # noqa: B027 - sources without threads have nothing to start
        """Start the source. Never raises because the device is absent."""

    @abstractmethod
    def grab(self, *, timeout_s: float, newer_than: int | None = None) -> CameraFrame:
        """Block until a fresh frame is available and return it.

        Fresh means: captured after this call started (live sources), or with an index greater
        than ``newer_than`` when given. Raises ``CameraUnavailable`` when the source is down,
        or when no fresh frame arrives within ``timeout_s`` seconds.
        """

    def grab_many(self, n: int, *, timeout_s: float) -> list[CameraFrame]:
        """``n`` distinct successive frames (for depth averaging); ``timeout_s`` covers all."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise InvalidArgument(f"camera {self.name!r}: frame count must be >= 1, got {n!r}")
        deadline = self._clock.monotonic() + timeout_s
        frames = [self.grab(timeout_s=timeout_s)]
        while len(frames) < n:
            remaining = deadline - self._clock.monotonic()
            try:
                frames.append(self.grab(timeout_s=max(remaining, 0.0), newer_than=frames[-1].index))
            except CameraUnavailable as exc:
                raise self.unavailable(
                    f"got {len(frames)} of {n} frames within {timeout_s:.3g} s: {exc.message}"
                ) from exc
        return frames

    @abstractmethod
    def status(self) -> dict[str, Any]:
        """JSON-able health: at least ``connected``, ``frames``, ``last_error``,
        ``reconnects``."""

    def close(self) -> None:
        """Stop the source and join its threads. Idempotent."""
        self._closed.set()

    @property
    def closed(self) -> bool:
        return self._closed.is_set()

    def hide_path(self, path: Path | str, shown_as: str) -> None:
        """Show ``path`` (an absolute path on the server) as ``shown_as`` in client messages.

        Its resolved form (symlinks followed) is hidden too. Longer paths are replaced first,
        so that a file inside a hidden folder keeps its name relative to the folder.
        """
        for private in path_forms(path):
            self._private_paths.setdefault(private, shown_as)

    def public_text(self, text: str) -> str:
        """``text`` with the camera's hidden paths replaced by how clients see them."""
        return replace_paths(text, self._private_paths)

    def unavailable(self, cause: str) -> CameraUnavailable:
        """The error for this camera giving no frame because of ``cause``.

        ``cause`` may name absolute paths: the client gets them as configured (see
        :meth:`hide_path`); the full cause is logged once per distinct cause.
        """
        public = self.public_text(cause)
        if public != cause and cause != self._logged_cause:
            self._logged_cause = cause
            log.warning("camera %r (%s): %s", self.name, self.source, cause)
        return CameraUnavailable(
            f"camera {self.name!r} ({self.source}): {public}",
            details={"camera": self.name, "source": self.source},
        )

    def _check_open(self) -> None:
        if self.closed:
            raise self.unavailable("the camera is closed")

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name!r}>"
