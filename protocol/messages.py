"""Typed messages of protocol v1: frozen dataclasses that validate on construction.

Each message class knows its ``TYPE`` and converts to and from a :class:`~protocol.frames.Frame`.
Unknown metadata fields are ignored on receipt (forward compatibility within a major version).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar, cast

from .constants import MAX_U32, NO_REQUEST, ImageRole, MessageType
from .errors import (
    BadImage,
    BadMetadata,
    CellvisionError,
    ErrorCode,
    InvalidArgument,
    error_from_code,
)
from .frames import Blob, Frame, as_integer
from .images import ImagePayload, payload_from_descriptor

Version = tuple[int, int]
_T = TypeVar("_T")


@dataclass(frozen=True)
class DecodeContext:
    """What parsing needs besides the frame: the limits that apply to images."""

    max_image_pixels: int


# --------------------------------------------------------------------------- field helpers


def _get(
    meta: dict[str, Any],
    key: str,
    kind: type[_T] | tuple[type, ...],
    rid: int,
    *,
    default: Any = ...,
    what: str = "",
) -> Any:
    if key not in meta or meta[key] is None:
        if default is ...:
            raise BadMetadata(f"missing field {key!r}{what}", request_id=rid)
        return default
    value = meta[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if int in kinds and float not in kinds and isinstance(value, float):
        # SPEC §3.2: a number without a fractional part is an integer, also written as 3.0.
        integral = as_integer(value)
        value = value if integral is None else integral
    ok = isinstance(value, kinds) and not (isinstance(value, bool) and bool not in kinds)
    if not ok:
        names = "/".join(k.__name__ for k in kinds)
        raise BadMetadata(
            f"field {key!r}{what} must be {names}, got {type(value).__name__}", request_id=rid
        )
    return value


def _version(value: Any, rid: int, where: str) -> Version:
    if isinstance(value, list) and len(value) == 2:
        numbers = [as_integer(v) for v in value]
        if all(n is not None and 0 <= n <= 255 for n in numbers):
            return (int(numbers[0] or 0), int(numbers[1] or 0))
    raise BadMetadata(
        f"{where} must be [major, minor] with 0..255 integers, got {value!r}", request_id=rid
    )


def _as_float(value: int | float) -> float | None:
    """``value`` as a finite float, or None (a JSON integer may be too large for a float)."""
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) else None


def _deadline(meta: dict[str, Any], rid: int) -> float | None:
    value = _get(meta, "deadline_ms", (int, float), rid, default=None)
    if value is None:
        return None
    deadline = _as_float(value)
    if deadline is None or deadline <= 0:
        raise BadMetadata(f"field 'deadline_ms' must be positive, got {value}", request_id=rid)
    return deadline


def _check_id(request_id: int) -> None:
    if not 0 <= request_id <= 0xFFFFFFFF:
        raise ValueError(f"request_id must fit in a u32, got {request_id}")


def _images_to_wire(
    images: tuple[ImagePayload, ...],
) -> tuple[list[dict[str, Any]], tuple[Blob, ...]]:
    return [img.descriptor(i) for i, img in enumerate(images)], tuple(img.data for img in images)


def _images_from_wire(
    meta: dict[str, Any], blobs: tuple[Blob, ...], rid: int, ctx: DecodeContext
) -> tuple[ImagePayload, ...]:
    descs = _get(meta, "images", list, rid, default=[])
    return tuple(
        payload_from_descriptor(
            d, blobs, where=f"images[{i}]", request_id=rid, max_pixels=ctx.max_image_pixels
        )
        for i, d in enumerate(descs)
    )


# --------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Message:
    """Base of all messages. ``request_id`` is chosen by the requester and echoed in the answer."""

    TYPE: ClassVar[MessageType]
    request_id: int

    def __post_init__(self) -> None:
        _check_id(self.request_id)

    def to_frame(self, version: Version) -> Frame:
        metadata, blobs = self._encode()
        return Frame(
            type=self.TYPE,
            request_id=self.request_id,
            metadata=metadata,
            blobs=blobs,
            version=version,
        )

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        return {}, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Message:
        raise NotImplementedError


@dataclass(frozen=True)
class Hello(Message):
    """Client → server, first message: the versions the client speaks, optionally a token."""

    TYPE: ClassVar[MessageType] = MessageType.HELLO
    versions: tuple[Version, ...] = ((1, 0),)
    client: str = ""
    auth_token: str | None = None
    max_frame_bytes: int | None = None
    """The largest frame the client accepts from the server (SPEC §5.1); None = the default."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.versions:
            raise ValueError("HELLO must list at least one version")
        if self.max_frame_bytes is not None and not 24 <= self.max_frame_bytes <= MAX_U32:
            raise ValueError(f"max_frame_bytes must be in 24..2**32-1, got {self.max_frame_bytes}")

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {"versions": [list(v) for v in self.versions]}
        if self.client:
            meta["client"] = self.client
        if self.auth_token is not None:
            meta["auth_token"] = self.auth_token
        if self.max_frame_bytes is not None:
            meta["max_frame_bytes"] = self.max_frame_bytes
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Hello:
        m, rid = frame.metadata, frame.request_id
        raw = _get(m, "versions", list, rid)
        versions = tuple(_version(v, rid, f"versions[{i}]") for i, v in enumerate(raw))
        if not versions:
            raise BadMetadata("field 'versions' must list at least one version", request_id=rid)
        max_frame = _get(m, "max_frame_bytes", int, rid, default=None)
        if max_frame is not None and not 24 <= max_frame <= MAX_U32:
            raise BadMetadata(
                f"field 'max_frame_bytes' must be in 24..{MAX_U32}, got {max_frame}",
                request_id=rid,
            )
        return cls(
            rid,
            versions,
            _get(m, "client", str, rid, default=""),
            _get(m, "auth_token", str, rid, default=None),
            max_frame,
        )


@dataclass(frozen=True)
class Welcome(Message):
    """Server → client: the chosen version, who the server is, its limits and inspections.

    ``limits`` has at least ``max_frame_bytes``, ``max_image_pixels`` and ``max_in_flight``.
    ``inspections`` and ``cameras`` are lists of descriptor objects (SPEC.md §5.2).
    """

    TYPE: ClassVar[MessageType] = MessageType.WELCOME
    version: Version = (1, 0)
    server_name: str = ""
    server_version: str = ""
    limits: dict[str, int] = field(default_factory=dict)
    inspections: tuple[dict[str, Any], ...] = ()
    cameras: tuple[dict[str, Any], ...] = ()

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        return {
            "version": list(self.version),
            "server": {"name": self.server_name, "version": self.server_version},
            "limits": dict(self.limits),
            "inspections": list(self.inspections),
            "cameras": list(self.cameras),
        }, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Welcome:
        m, rid = frame.metadata, frame.request_id
        server = _get(m, "server", dict, rid, default={})
        # A null field is an absent one (SPEC §3.2), inside objects too.
        limits = {
            k: v for k, v in _get(m, "limits", dict, rid, default={}).items() if v is not None
        }
        for key, value in limits.items():
            if isinstance(value, bool) or not isinstance(value, int):
                raise BadMetadata(f"limits.{key} must be an integer", request_id=rid)
        return cls(
            rid,
            _version(_get(m, "version", list, rid), rid, "version"),
            _text(server.get("name")),
            _text(server.get("version")),
            dict(limits),
            tuple(_descriptors(m, "inspections", rid)),
            tuple(_descriptors(m, "cameras", rid)),
        )


def _text(value: Any) -> str:
    """Free text for logs: "" when absent or null (SPEC §3.2), else as a string."""
    return "" if value is None else str(value)


def _descriptors(m: dict[str, Any], key: str, rid: int) -> list[dict[str, Any]]:
    items = _get(m, key, list, rid, default=[])
    for i, item in enumerate(items):
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise BadMetadata(f"{key}[{i}] must be an object with a string 'name'", request_id=rid)
    return list(items)


@dataclass(frozen=True)
class Ping(Message):
    """Keepalive request; ``data`` is echoed in the PONG."""

    TYPE: ClassVar[MessageType] = MessageType.PING
    data: str = ""

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        return ({"data": self.data} if self.data else {}), ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Ping:
        return cls(
            frame.request_id, _get(frame.metadata, "data", str, frame.request_id, default="")
        )


@dataclass(frozen=True)
class Pong(Message):
    """The answer to PING, echoing its ``data``.

    ``health`` is the server's health report (SPEC §5.5), or None when the server sent none: an
    object with at least ``ok`` (boolean: false when the server cannot do all it promises, e.g.
    results it acknowledged were not logged) and, when the server has a result log,
    ``result_log`` with its counters.
    """

    TYPE: ClassVar[MessageType] = MessageType.PONG
    data: str = ""
    health: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.health is not None and not isinstance(self.health.get("ok"), bool):
            raise ValueError("PONG health must have a boolean 'ok'")

    @property
    def healthy(self) -> bool:
        """False only when the server reported itself unhealthy (no report counts as healthy)."""
        return self.health is None or self.health["ok"] is True

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {"data": self.data} if self.data else {}
        if self.health is not None:
            meta["health"] = dict(self.health)
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Pong:
        m, rid = frame.metadata, frame.request_id
        health = _get(m, "health", dict, rid, default=None)
        if health is not None:
            _get(health, "ok", bool, rid, what=" of 'health'")
        return cls(rid, _get(m, "data", str, rid, default=""), health)


@dataclass(frozen=True)
class Close(Message):
    """Graceful close: the sender will send no new requests (client) or nothing more (server)."""

    TYPE: ClassVar[MessageType] = MessageType.CLOSE
    request_id: int = NO_REQUEST
    reason: str = ""

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        return ({"reason": self.reason} if self.reason else {}), ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Close:
        return cls(
            frame.request_id, _get(frame.metadata, "reason", str, frame.request_id, default="")
        )


@dataclass(frozen=True)
class ListInspections(Message):
    TYPE: ClassVar[MessageType] = MessageType.LIST_INSPECTIONS

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> ListInspections:
        return cls(frame.request_id)


@dataclass(frozen=True)
class Inspections(Message):
    TYPE: ClassVar[MessageType] = MessageType.INSPECTIONS
    inspections: tuple[dict[str, Any], ...] = ()

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        return {"inspections": list(self.inspections)}, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Inspections:
        return cls(
            frame.request_id, tuple(_descriptors(frame.metadata, "inspections", frame.request_id))
        )


@dataclass(frozen=True)
class Inspect(Message):
    """Run the named inspection.

    With ``images`` the inspection runs on them (a camera on the robot's tool); without, the
    server captures from the inspection's configured camera. ``deadline_ms`` counts from the
    moment the server has received the whole frame. ``options`` are inspection-specific (SPEC §6.1).
    """

    TYPE: ClassVar[MessageType] = MessageType.INSPECT
    inspection: str = ""
    images: tuple[ImagePayload, ...] = ()
    deadline_ms: float | None = None
    overlay: bool = False
    options: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.inspection:
            raise ValueError("INSPECT needs an inspection name")
        if self.deadline_ms is not None and not (
            math.isfinite(self.deadline_ms) and self.deadline_ms > 0
        ):
            raise ValueError(f"deadline_ms must be a positive number, got {self.deadline_ms}")

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        descs, blobs = _images_to_wire(self.images)
        meta: dict[str, Any] = {"inspection": self.inspection}
        if descs:
            meta["images"] = descs
        if self.deadline_ms is not None:
            meta["deadline_ms"] = self.deadline_ms
        if self.overlay:
            meta["overlay"] = True
        if self.options:
            meta["options"] = dict(self.options)
        return meta, blobs

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Inspect:
        m, rid = frame.metadata, frame.request_id
        name = _get(m, "inspection", str, rid)
        if not name:
            raise BadMetadata("field 'inspection' must not be empty", request_id=rid)
        deadline = _deadline(m, rid)
        return cls(
            rid,
            name,
            _images_from_wire(m, frame.blobs, rid, ctx),
            deadline,
            _get(m, "overlay", bool, rid, default=False),
            dict(_get(m, "options", dict, rid, default={})),
        )


@dataclass(frozen=True)
class Result(Message):
    """The answer to INSPECT.

    ``passed`` is the verdict. ``data`` holds what the inspection measured or found (SPEC §6.2);
    ``timing`` durations in milliseconds; ``images`` an optional overlay PNG. ``stored`` says
    whether the server wrote the result to its result log before answering: None when the
    server has no result log (or did not say), False when the entry could not be written.
    ``result_id`` is the row's id in that log when the server knows it (None otherwise): what an
    OPERATOR_CALL about this result names (SPEC §6.6).
    """

    TYPE: ClassVar[MessageType] = MessageType.RESULT
    inspection: str = ""
    passed: bool = False
    data: dict[str, Any] = field(default_factory=dict)
    timing: dict[str, float] = field(default_factory=dict)
    camera: str = ""
    config_hash: str = ""
    images: tuple[ImagePayload, ...] = ()
    stored: bool | None = None
    result_id: int | None = None

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        descs, blobs = _images_to_wire(self.images)
        meta: dict[str, Any] = {
            "inspection": self.inspection,
            "verdict": "pass" if self.passed else "fail",
            "data": dict(self.data),
            "timing": dict(self.timing),
        }
        if self.camera:
            meta["camera"] = self.camera
        if self.config_hash:
            meta["config_hash"] = self.config_hash
        if descs:
            meta["images"] = descs
        if self.stored is not None:
            meta["stored"] = self.stored
        if self.result_id is not None:
            meta["result_id"] = self.result_id
        return meta, blobs

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Result:
        m, rid = frame.metadata, frame.request_id
        verdict = _get(m, "verdict", str, rid)
        if verdict not in ("pass", "fail"):
            raise BadMetadata(
                f"field 'verdict' must be 'pass' or 'fail', got {verdict!r}", request_id=rid
            )
        timing = {
            k: v for k, v in _get(m, "timing", dict, rid, default={}).items() if v is not None
        }
        for key, value in timing.items():
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise BadMetadata(f"timing.{key} must be a number of ms", request_id=rid)
        return cls(
            rid,
            _get(m, "inspection", str, rid),
            verdict == "pass",
            dict(_get(m, "data", dict, rid, default={})),
            dict(timing),
            _get(m, "camera", str, rid, default=""),
            _get(m, "config_hash", str, rid, default=""),
            _images_from_wire(m, frame.blobs, rid, ctx),
            _get(m, "stored", bool, rid, default=None),
            _result_id(m, rid),
        )


@dataclass(frozen=True)
class Capture(Message):
    """Take ``count`` frames from a server camera (colour, and depth when ``depth`` and the
    camera has it). ``encoding`` asks for a compressed colour encoding (``png``/``jpeg``)."""

    TYPE: ClassVar[MessageType] = MessageType.CAPTURE
    camera: str = ""
    count: int = 1
    depth: bool = False
    encoding: str | None = None
    deadline_ms: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if not self.camera:
            raise ValueError("CAPTURE needs a camera name")
        if self.count < 1:
            raise ValueError(f"count must be >= 1, got {self.count}")

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {"camera": self.camera, "count": self.count}
        if self.depth:
            meta["depth"] = True
        if self.encoding:
            meta["encoding"] = self.encoding
        if self.deadline_ms is not None:
            meta["deadline_ms"] = self.deadline_ms
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Capture:
        m, rid = frame.metadata, frame.request_id
        camera = _get(m, "camera", str, rid)
        count = _get(m, "count", int, rid, default=1)
        if not camera:
            raise BadMetadata("field 'camera' must not be empty", request_id=rid)
        if count < 1:
            raise BadMetadata(f"field 'count' must be >= 1, got {count}", request_id=rid)
        deadline = _deadline(m, rid)
        return cls(
            rid,
            camera,
            count,
            _get(m, "depth", bool, rid, default=False),
            _get(m, "encoding", str, rid, default=None),
            deadline,
        )


@dataclass(frozen=True)
class Frames(Message):
    """The answer to CAPTURE: the images in capture order (colour, then its depth, per frame);
    ``timestamps`` are the server's capture times in seconds since the Unix epoch."""

    TYPE: ClassVar[MessageType] = MessageType.FRAMES
    camera: str = ""
    images: tuple[ImagePayload, ...] = ()
    timestamps: tuple[float, ...] = ()
    intrinsics: dict[str, Any] | None = None

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        descs, blobs = _images_to_wire(self.images)
        meta: dict[str, Any] = {
            "camera": self.camera,
            "images": descs,
            "timestamps": list(self.timestamps),
        }
        if self.intrinsics is not None:
            meta["intrinsics"] = dict(self.intrinsics)
        return meta, blobs

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Frames:
        m, rid = frame.metadata, frame.request_id
        stamps = _get(m, "timestamps", list, rid, default=[])
        times = [
            _as_float(t) if isinstance(t, int | float) and not isinstance(t, bool) else None
            for t in stamps
        ]
        if None in times:
            raise BadMetadata("field 'timestamps' must hold finite numbers", request_id=rid)
        return cls(
            rid,
            _get(m, "camera", str, rid),
            _images_from_wire(m, frame.blobs, rid, ctx),
            tuple(t for t in times if t is not None),
            _get(m, "intrinsics", dict, rid, default=None),
        )


@dataclass(frozen=True)
class Reload(Message):
    """Administration: re-read the server's configuration file (SPEC §6.5)."""

    TYPE: ClassVar[MessageType] = MessageType.RELOAD

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Reload:
        return cls(frame.request_id)


@dataclass(frozen=True)
class Reloaded(Message):
    """The answer to RELOAD: the new configuration's hash and what it now offers; ``notes``:
    sentences for the person who asked, e.g. that changed ``server:`` settings take effect only
    after a restart (SPEC §6.5)."""

    TYPE: ClassVar[MessageType] = MessageType.RELOADED
    config_hash: str = ""
    inspections: tuple[dict[str, Any], ...] = ()
    cameras: tuple[dict[str, Any], ...] = ()
    notes: tuple[str, ...] = ()

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {
            "config_hash": self.config_hash,
            "inspections": list(self.inspections),
            "cameras": list(self.cameras),
        }
        if self.notes:  # optional: absent means none
            meta["notes"] = list(self.notes)
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Reloaded:
        m, rid = frame.metadata, frame.request_id
        notes = _get(m, "notes", list, rid, default=[])
        if not all(isinstance(note, str) for note in notes):
            raise BadMetadata("field 'notes' must be an array of strings", request_id=rid)
        return cls(
            rid,
            _get(m, "config_hash", str, rid, default=""),
            tuple(_descriptors(m, "inspections", rid)),
            tuple(_descriptors(m, "cameras", rid)),
            tuple(notes),
        )


def _result_id(meta: dict[str, Any], rid: int) -> int | None:
    """The optional ``result_id`` of RESULT and OPERATOR_CALL: a result log's row id (>= 1)."""
    value = _get(meta, "result_id", int, rid, default=None)
    if value is not None and value < 1:
        raise BadMetadata(f"field 'result_id' must be >= 1, got {value}", request_id=rid)
    return cast(int | None, value)


OPERATOR_CHOICES: tuple[str, ...] = ("retry", "continue", "abort")
"""What an operator may answer an OPERATOR_CALL (SPEC §6.6), in the order a console shows them."""


def _check_choices(choices: tuple[str, ...]) -> str | None:
    """Why ``choices`` is not a valid OPERATOR_CALL ``choices`` list, or None when it is."""
    if not choices:
        return "choices must list at least one of " + ", ".join(OPERATOR_CHOICES)
    unknown = [c for c in choices if c not in OPERATOR_CHOICES]
    if unknown:
        return f"unknown choice {unknown[0]!r}: choices are " + ", ".join(OPERATOR_CHOICES)
    if len(set(choices)) != len(choices):
        return f"choices must not repeat a choice, got {list(choices)}"
    return None


@dataclass(frozen=True)
class OperatorCall(Message):
    """Client → server (version 1.1): ask a person at the server's console to decide (SPEC §6.6).

    ``message`` says what happened; ``choices`` what the person may answer (a subset of
    :data:`OPERATOR_CHOICES`); ``inspection`` and ``skill`` name what failed, for the console;
    ``images`` show it (e.g. the failing RESULT's overlay PNG; roles ``color`` or ``overlay``).
    ``deadline_ms`` bounds the wait, counted from the server's receipt of the whole frame: then
    DEADLINE_EXCEEDED. Answered by :class:`OperatorAnswer`.
    """

    TYPE: ClassVar[MessageType] = MessageType.OPERATOR_CALL
    message: str = ""
    choices: tuple[str, ...] = OPERATOR_CHOICES
    inspection: str = ""
    skill: str = ""
    images: tuple[ImagePayload, ...] = ()
    deadline_ms: float | None = None
    result_id: int | None = None
    """The failed RESULT's ``result_id`` (its row in the server's result log), annotated with
    the person's answer."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.result_id is not None and self.result_id < 1:
            raise ValueError(f"result_id must be >= 1, got {self.result_id}")
        if not self.message:
            raise ValueError("OPERATOR_CALL needs a message for the operator")
        why = _check_choices(self.choices)
        if why is not None:
            raise ValueError(why)
        if self.deadline_ms is not None and not (
            math.isfinite(self.deadline_ms) and self.deadline_ms > 0
        ):
            raise ValueError(f"deadline_ms must be a positive number, got {self.deadline_ms}")
        for image in self.images:
            if image.role is ImageRole.DEPTH:
                raise ValueError("an operator call shows colour or overlay images, not depth")

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        descs, blobs = _images_to_wire(self.images)
        meta: dict[str, Any] = {"message": self.message, "choices": list(self.choices)}
        if self.inspection:
            meta["inspection"] = self.inspection
        if self.skill:
            meta["skill"] = self.skill
        if descs:
            meta["images"] = descs
        if self.deadline_ms is not None:
            meta["deadline_ms"] = self.deadline_ms
        if self.result_id is not None:
            meta["result_id"] = self.result_id
        return meta, blobs

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> OperatorCall:
        m, rid = frame.metadata, frame.request_id
        message = _get(m, "message", str, rid)
        if not message:
            raise BadMetadata("field 'message' must not be empty", request_id=rid)
        raw = _get(m, "choices", list, rid, default=list(OPERATOR_CHOICES))
        if not all(isinstance(c, str) for c in raw):
            raise BadMetadata("field 'choices' must be an array of strings", request_id=rid)
        choices = tuple(raw)
        why = _check_choices(choices)
        if why is not None:
            raise InvalidArgument(why, request_id=rid, details={"option": "choices"})
        images = _images_from_wire(m, frame.blobs, rid, ctx)
        for i, image in enumerate(images):
            if image.role is ImageRole.DEPTH:
                raise BadImage(
                    f"images[{i}]: an operator call shows colour or overlay images to a person, "
                    "not depth",
                    request_id=rid,
                )
        return cls(
            rid,
            message,
            choices,
            _get(m, "inspection", str, rid, default=""),
            _get(m, "skill", str, rid, default=""),
            images,
            _deadline(m, rid),
            _result_id(m, rid),
        )


@dataclass(frozen=True)
class OperatorAnswer(Message):
    """Server → client (version 1.1): the operator's answer to an OPERATOR_CALL (SPEC §6.6).

    ``choice`` is one of the call's choices; ``by`` names who answered (for the robot's log,
    e.g. the console's peer address); ``answered_at`` is the server's time of the answer, Unix
    seconds (None when the server did not say); ``operator`` the signed-in person's name and
    ``reason`` why they answered so ("" when the server did not say).
    """

    TYPE: ClassVar[MessageType] = MessageType.OPERATOR_ANSWER
    choice: str = ""
    by: str = ""
    answered_at: float | None = None
    reason: str = ""
    operator: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.choice not in OPERATOR_CHOICES:
            raise ValueError(
                f"choice must be one of {', '.join(OPERATOR_CHOICES)}, got {self.choice!r}"
            )

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {"choice": self.choice}
        if self.by:
            meta["by"] = self.by
        if self.answered_at is not None:
            meta["answered_at"] = self.answered_at
        if self.reason:
            meta["reason"] = self.reason
        if self.operator:
            meta["operator"] = self.operator
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> OperatorAnswer:
        m, rid = frame.metadata, frame.request_id
        choice = _get(m, "choice", str, rid)
        if choice not in OPERATOR_CHOICES:
            raise BadMetadata(
                f"field 'choice' must be one of {', '.join(OPERATOR_CHOICES)}, got {choice!r}",
                request_id=rid,
            )
        stamp = _get(m, "answered_at", (int, float), rid, default=None)
        answered_at = None if stamp is None else _as_float(stamp)
        if stamp is not None and answered_at is None:
            raise BadMetadata("field 'answered_at' must be a finite number", request_id=rid)
        return cls(
            rid,
            choice,
            _get(m, "by", str, rid, default=""),
            answered_at,
            _get(m, "reason", str, rid, default=""),
            _get(m, "operator", str, rid, default=""),
        )


@dataclass(frozen=True)
class Error(Message):
    """An error answering the request ``request_id`` (0: about the connection itself)."""

    TYPE: ClassVar[MessageType] = MessageType.ERROR
    code: int = ErrorCode.INTERNAL_ERROR
    message: str = ""
    fatal: bool = False
    details: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_exception(cls, exc: CellvisionError, *, request_id: int | None = None) -> Error:
        return cls(
            exc.request_id if request_id is None else request_id,
            # An UnknownErrorCode keeps the number it arrived with, so relaying it is lossless.
            int(getattr(exc, "wire_code", exc.code)),
            exc.message,
            exc.fatal,
            dict(exc.details),
        )

    def to_exception(self) -> CellvisionError:
        return error_from_code(
            self.code,
            self.message,
            request_id=self.request_id,
            details=self.details,
            fatal=self.fatal,
        )

    @property
    def name(self) -> str:
        try:
            return ErrorCode(self.code).name
        except ValueError:
            return f"UNKNOWN_{self.code}"

    def _encode(self) -> tuple[dict[str, Any], tuple[Blob, ...]]:
        meta: dict[str, Any] = {
            "code": int(self.code),
            "name": self.name,
            "message": self.message,
            "fatal": self.fatal,
        }
        if self.details:
            meta["details"] = dict(self.details)
        return meta, ()

    @classmethod
    def from_frame(cls, frame: Frame, ctx: DecodeContext) -> Error:
        m, rid = frame.metadata, frame.request_id
        return cls(
            rid,
            _get(m, "code", int, rid),
            _get(m, "message", str, rid, default=""),
            _get(m, "fatal", bool, rid, default=False),
            dict(_get(m, "details", dict, rid, default={})),
        )


MESSAGE_CLASSES: dict[MessageType, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        Hello,
        Welcome,
        Ping,
        Pong,
        Close,
        ListInspections,
        Inspections,
        Inspect,
        Result,
        Capture,
        Frames,
        Reload,
        Reloaded,
        OperatorCall,
        OperatorAnswer,
        Error,
    )
}

Parser = Callable[[Frame, DecodeContext], Message]


def message_from_frame(frame: Frame, ctx: DecodeContext) -> Message:
    """Build the typed message of a frame whose type is known (see MESSAGE_CLASSES)."""
    return MESSAGE_CLASSES[MessageType(frame.type)].from_frame(frame, ctx)
