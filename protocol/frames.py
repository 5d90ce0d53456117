"""Framing: one frame = a 24-byte header, a UTF-8 JSON metadata object, a blob table, blobs.

``Frame`` is the codec's unit: it knows nothing about message semantics. ``FrameDecoder`` turns
a byte stream into frames incrementally, enforcing the size limits as soon as a header arrives.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeAlias

import numpy as np

from .constants import BLOB_LENGTH, HEADER, HEADER_SIZE, MAGIC, MAX_U32
from .errors import BadMetadata, CellvisionError, FrameTooLarge, MalformedFrame


@dataclass(frozen=True)
class Limits:
    """Receive-side limits. Every size is in bytes, pixel counts in pixels."""

    max_frame_bytes: int = 64 * 1024 * 1024
    max_metadata_bytes: int = 1024 * 1024
    max_blobs: int = 64
    max_image_pixels: int = 4096 * 4096
    max_handshake_frame_bytes: int = 64 * 1024
    """A server's limit for frames before the handshake is complete (SPEC §3.4): a HELLO is a
    few hundred bytes, so nobody who has not authenticated can make the server buffer more."""

    def __post_init__(self) -> None:
        for name in (
            "max_frame_bytes",
            "max_metadata_bytes",
            "max_blobs",
            "max_image_pixels",
            "max_handshake_frame_bytes",
        ):
            value = getattr(self, name)
            if not isinstance(value, int) or value <= 0:
                raise ValueError(f"Limits.{name} must be a positive integer, got {value!r}")
        if self.max_frame_bytes > MAX_U32:
            raise ValueError("Limits.max_frame_bytes cannot exceed 2**32 - 1")


Blob: TypeAlias = bytes | bytearray | memoryview
"""A blob's bytes: any flat byte buffer. Received blobs are read-only memoryviews into their
frame's body (no copy per blob); sent ones may view the sender's array (no ``tobytes()``)."""


def blob_view(data: Blob) -> memoryview:
    """``data`` as a flat, read-only view of unsigned bytes (no copy); len() is its byte size."""
    view = memoryview(data)
    if view.ndim != 1 or view.format != "B":
        view = view.cast("B")  # a multi-dimensional or typed export (e.g. a numpy array)
    return view.toreadonly()


@dataclass(frozen=True)
class Frame:
    """One frame as it travels: header fields, parsed metadata, raw blobs."""

    type: int
    request_id: int
    metadata: dict[str, Any] = field(default_factory=dict)
    blobs: tuple[Blob, ...] = ()
    version: tuple[int, int] = (1, 0)
    flags: int = 0

    def serialize(self) -> bytes:
        """The frame's bytes. Metadata is compact JSON with sorted keys (deterministic)."""
        return b"".join(self.serialize_parts())

    def serialize_parts(self) -> list[Blob]:
        """The frame's bytes in order, as buffers to write one after the other: the header,
        metadata and blob table in one ``bytes``, then each blob as it is (never copied), for
        ``writelines`` / ``socket.sendmsg``."""
        meta = encode_metadata(self.metadata)
        blobs = [blob_view(b) for b in self.blobs]
        table = b"".join(BLOB_LENGTH.pack(len(b)) for b in blobs)
        body_length = len(meta) + len(table) + sum(len(b) for b in blobs)
        if body_length > MAX_U32:
            raise ValueError(f"frame body of {body_length} bytes does not fit a u32 length")
        header = HEADER.pack(
            MAGIC,
            self.version[0],
            self.version[1],
            self.type,
            self.flags,
            len(self.blobs),
            self.request_id,
            len(meta),
            body_length,
        )
        return [b"".join((header, meta, table)), *(b for b in blobs if len(b))]


_ENCODER = json.JSONEncoder(
    separators=(",", ":"), sort_keys=True, ensure_ascii=False, allow_nan=False
)
"""One encoder for every frame (``json.dumps`` with options makes a new one per call)."""


def encode_metadata(metadata: dict[str, Any]) -> bytes:
    """Compact UTF-8 JSON, keys sorted, no NaN; ``{}`` is sent as zero bytes."""
    if not metadata:
        return b""
    return _ENCODER.encode(metadata).encode("utf-8")


MAX_SAFE_INTEGER = 2**53 - 1
"""I-JSON (RFC 7493): integers beyond +/-(2**53 - 1) are not exchanged exactly by every JSON
implementation (JavaScript, .NET's double), so they are refused."""


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def _finite_float(text: str) -> float:
    # json turns 1e400 into inf, which could never be sent back (allow_nan=False).
    value = float(text)
    if math.isinf(value):
        raise ValueError(f"number {text} is out of the float range")
    return value


def _safe_int(text: str) -> int:
    value = int(text)
    if abs(value) > MAX_SAFE_INTEGER:
        raise ValueError(f"integer {text} is outside +/-(2**53 - 1) (I-JSON, RFC 7493)")
    return value


def _object_without_nulls(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object from its members: a duplicate name is an error (I-JSON), and a member whose
    value is null is absent (SPEC §3.2), at every level of nesting."""
    result: dict[str, Any] = {}
    seen: set[str] = set()
    for key, value in pairs:
        if key in seen:
            raise ValueError(f"duplicate member name {key!r} (I-JSON, RFC 7493)")
        seen.add(key)
        if value is not None:
            result[key] = value
    return result


_DECODER = json.JSONDecoder(
    parse_constant=_reject_constant,
    parse_float=_finite_float,
    parse_int=_safe_int,
    # Looked up per object, so that the conformance suite's tests can swap the rule.
    object_pairs_hook=lambda pairs: _object_without_nulls(pairs),
)
"""One decoder for every frame (``json.loads`` with options makes a new one per call)."""

# A \uD800-\uDFFF escape may leave a lone surrogate, which no UTF-8 encoder can send back.
_SURROGATE_ESCAPE = re.compile(r"\\u[dD][89a-fA-F]")


def decode_metadata(data: bytes, *, request_id: int) -> dict[str, Any]:
    """Parse a metadata section; zero bytes means ``{}``.

    The JSON profile is I-JSON (RFC 7493): no duplicate member names, integers within
    +/-(2**53 - 1), no NaN/Infinity, no lone surrogates; and a member whose value is ``null``
    is dropped at every level (SPEC §3.2: null counts as absent).
    """
    if not data:
        return {}
    try:
        text = data.decode("utf-8")
        value = _DECODER.decode(text)
        if _SURROGATE_ESCAPE.search(text):
            # Cheap test first; only then the full check that every string encodes.
            json.dumps(value, ensure_ascii=False).encode("utf-8")
    except (UnicodeError, ValueError, RecursionError) as exc:
        raise BadMetadata(f"metadata is not UTF-8 JSON: {exc}", request_id=request_id) from None
    if not isinstance(value, dict):
        raise BadMetadata(
            f"metadata must be a JSON object, got {type(value).__name__}", request_id=request_id
        )
    return value


def as_integer(value: Any) -> int | None:
    """``value`` as an integer when it is a JSON number without a fractional part (``3`` or
    ``3.0``: .NET and URScript serialisers write the latter); None otherwise (also for bools)."""
    if isinstance(value, bool):
        return None
    if isinstance(value, int):
        return value
    if isinstance(value, float) and value.is_integer() and abs(value) <= MAX_SAFE_INTEGER:
        return int(value)
    return None


@dataclass(frozen=True)
class Header:
    major: int
    minor: int
    type: int
    flags: int
    blob_count: int
    request_id: int
    metadata_length: int
    body_length: int

    @property
    def frame_length(self) -> int:
        return HEADER_SIZE + self.body_length


def check_magic(prefix: bytes | bytearray | memoryview) -> None:
    """Raise MALFORMED_FRAME when the first bytes of a frame (any number, up to the whole
    header) cannot begin :data:`MAGIC` (SPEC §3.1): a peer that speaks another protocol is
    refused at its first byte, not after 24 of them (a line-protocol ``T 1\n`` has 4).

    ``details["text"]`` is True when those bytes are printable ASCII (another text protocol,
    such as the line protocol or HTTP, sent to this port), so that the receiver can say so."""
    received = bytes(prefix[: len(MAGIC)])
    if MAGIC.startswith(received):
        return
    text = all(0x20 <= byte < 0x7F or byte in b"\t\r\n" for byte in received)
    raise MalformedFrame(f"bad magic {received!r}, expected {MAGIC!r}", details={"text": text})


def parse_header(data: bytes | bytearray | memoryview, limits: Limits) -> Header:
    """Parse and check the first 24 bytes of a frame (``data`` may be longer)."""
    check_magic(data)
    _, major, minor, mtype, flags, blobs, rid, meta_len, body_len = HEADER.unpack_from(data)
    header = Header(major, minor, mtype, flags, blobs, rid, meta_len, body_len)
    limit = limits.max_frame_bytes
    if header.frame_length > limit:
        raise FrameTooLarge(
            f"frame of {header.frame_length} bytes exceeds the limit of {limit} bytes",
            request_id=rid,
            details={"size": header.frame_length, "max_size": limit},
        )
    if blobs > limits.max_blobs:
        raise MalformedFrame(
            f"{blobs} blobs exceed the limit of {limits.max_blobs}", request_id=rid
        )
    if meta_len > limits.max_metadata_bytes:
        raise FrameTooLarge(
            f"metadata of {meta_len} bytes exceeds the limit of {limits.max_metadata_bytes} bytes",
            request_id=rid,
            details={"size": meta_len, "max_size": limits.max_metadata_bytes},
        )
    if meta_len + BLOB_LENGTH.size * blobs > body_len:
        raise MalformedFrame(
            f"metadata ({meta_len} bytes) and blob table ({blobs} entries) do not fit in a "
            f"body of {body_len} bytes",
            request_id=rid,
        )
    return header


def parse_body(
    header: Header, body: Blob, metadata: dict[str, Any] | None = None
) -> tuple[dict[str, Any], tuple[memoryview, ...]]:
    """Split a complete body into (metadata, blobs). ``body`` is exactly body_length bytes;
    ``metadata``: the body's metadata when it was already decoded (at admission).

    The blobs are read-only views into ``body`` (no copy): they keep it alive, and it must not
    change while they are in use.
    """
    rid = header.request_id
    view = blob_view(body)
    offset = header.metadata_length
    table_end = offset + BLOB_LENGTH.size * header.blob_count
    lengths = [
        BLOB_LENGTH.unpack_from(view, offset + BLOB_LENGTH.size * i)[0]
        for i in range(header.blob_count)
    ]
    if table_end + sum(lengths) != header.body_length:
        raise MalformedFrame(
            f"blob lengths {lengths} do not add up to the body length {header.body_length}",
            request_id=rid,
        )
    blobs = []
    position = table_end
    for length in lengths:
        blobs.append(view[position : position + length])
        position += length
    if metadata is None:
        metadata = decode_metadata(bytes(view[: header.metadata_length]), request_id=rid)
    return metadata, tuple(blobs)


HeaderCheck = Callable[[Header], None]
"""Called with each frame's header as soon as it has arrived, before any of its body is kept.

It raises a :class:`~protocol.errors.CellvisionError` to refuse the frame: a fatal one breaks
the stream; a non-fatal one makes the decoder skip the body without buffering it (the frame is
consumed) and is raised from :meth:`FrameDecoder.next_frame`.
"""


class AdmitLater(Exception):  # noqa: N818 - a signal, not an error
    """Raised by an :data:`AdmitCheck` that cannot take a frame now but may later (a server
    whose workers are all busy): the decoder keeps the frame unread and reports
    :attr:`FrameDecoder.paused`; the next :meth:`FrameDecoder.next_frame` asks again."""


AdmitCheck = Callable[[Header, dict[str, Any]], None]
"""Called with a frame's header and its decoded metadata once both have arrived, before its
blobs are kept (so the owner knows what the frame asks for: an inspection's name, a deadline).

It raises a non-fatal :class:`~protocol.errors.CellvisionError` to refuse the frame (its body
is then skipped, never buffered), a fatal one to break the stream, or :class:`AdmitLater`.
"""


SCRATCH_BYTES = 64 * 1024
"""Size of the decoder's reused receive buffer for bytes outside a known body (headers, small
frames); a body is received straight into its own buffer."""


UNZEROED_BODY_MIN = 64 * 1024
"""A body of at least this many bytes gets memory that is not zeroed first (it is filled
from the socket at once): zeroing an image-sized bytearray costs as much as reading it."""


def new_body(size: int) -> bytearray | memoryview:
    """A writable buffer of ``size`` bytes for a frame body, every byte of which the caller
    overwrites before it is read: a bytearray, or a view of a flat uint8 array."""
    if size < UNZEROED_BODY_MIN:
        return bytearray(size)
    return np.empty(size, dtype=np.uint8).data


class FrameDecoder:
    """Incremental frame parser: feed bytes, take complete frames.

    A fatal error (bad magic, too large, inconsistent lengths) leaves the decoder broken: every
    later call raises the same error. A BadMetadata error consumes its frame and the stream goes on.
    A frame refused by ``check_header`` with a non-fatal error is skipped: its body is read and
    dropped as it arrives, never held in memory.

    Once a frame's header is admitted, its body gets one buffer of exactly ``body_length`` bytes,
    and its blobs are views into it (an image's pixels are never copied after that). Bytes
    arrive either by :meth:`feed` (copied once, into that buffer) or, with no copy at all, by
    reading into :meth:`get_buffer` and calling :meth:`buffer_updated` (asyncio's
    ``BufferedProtocol`` shape, ``socket.recv_into``).
    """

    def __init__(self, limits: Limits | None = None) -> None:
        self.limits = limits or Limits()
        self.check_header: HeaderCheck | None = None
        self.admit: AdmitCheck | None = None
        """Admission with the metadata in hand (see :data:`AdmitCheck`); None admits every
        frame at its header."""
        self.paused = False
        """True when the latest :meth:`next_frame` stopped at a frame :attr:`admit` deferred
        (:class:`AdmitLater`): its owner should stop reading from the peer until it can admit
        it, then call :meth:`next_frame` again."""
        # A header that passed check_header and waits for its metadata or its admission.
        self._checked: Header | None = None
        self._metadata: dict[str, Any] | None = None
        # Bytes received and not yet in a body: a header, or what follows a complete body.
        self._buffer = bytearray()
        self._header: Header | None = None
        self._body: bytearray | memoryview | None = None
        self._filled = 0
        self._skip = 0
        self._scratch = bytearray(SCRATCH_BYTES)
        self._into_body = False
        self._broken: MalformedFrame | FrameTooLarge | CellvisionError | None = None
        self._eof = False
        self.last_header: Header | None = None
        """The header of the latest frame parsed, also when its body was bad."""
        self.copied_bytes = 0
        """Body bytes copied into a body buffer from elsewhere (fed data, the scratch buffer);
        bytes read straight into the body through :meth:`get_buffer` are not counted."""

    @property
    def buffered(self) -> int:
        """Bytes received but not yet returned as frames (a skipped body is not kept)."""
        return len(self._buffer) + self._filled

    @property
    def in_frame(self) -> bool:
        """True between the first byte of a frame and the frame's last byte."""
        return bool(self._buffer) or self._header is not None or self._skip > 0

    @property
    def eof(self) -> bool:
        return self._eof

    def feed(self, data: Blob) -> None:
        """Take received bytes (``b""`` = end of stream). ``data`` is copied, never kept."""
        if not len(data):
            self._eof = True
            return
        view = blob_view(data)
        if self._skip and not self._buffer:
            # Drop the body of a refused frame as it arrives; keep only what follows it.
            dropped = min(self._skip, len(view))
            self._skip -= dropped
            view = view[dropped:]
        elif self._body is not None and not self._buffer:
            taken = min(len(self._body) - self._filled, len(view))
            self._body[self._filled : self._filled + taken] = view[:taken]
            self._filled += taken
            self.copied_bytes += taken
            view = view[taken:]
        if len(view):
            self._buffer += view

    def get_buffer(self) -> memoryview:
        """Where the next received bytes should go; then call :meth:`buffer_updated`.

        The rest of the current body when one is being received (no copy), else a reused
        scratch buffer. Valid until the next call that changes the decoder.
        """
        self._into_body = (
            self._body is not None and self._filled < len(self._body) and not self._buffer
        )
        if self._into_body:
            assert self._body is not None
            return memoryview(self._body)[self._filled :]
        return memoryview(self._scratch)

    def buffer_updated(self, nbytes: int) -> None:
        """``nbytes`` were written at the start of the latest :meth:`get_buffer` view."""
        if self._into_body:
            self._into_body = False
            self._filled += nbytes
        elif nbytes:
            self.feed(memoryview(self._scratch)[:nbytes])

    def next_frame(self) -> Frame | None:
        """The next complete frame, or None when more bytes are needed."""
        if self._broken is not None:
            raise self._broken
        try:
            return self._next_frame()
        except CellvisionError as exc:
            if exc.fatal:
                self._broken = exc
                self._buffer.clear()
                self._body = None
                self._filled = 0
            raise

    def _next_frame(self) -> Frame | None:
        if self._skip:
            dropped = min(self._skip, len(self._buffer))
            del self._buffer[:dropped]
            self._skip -= dropped
            if self._skip:
                if self._eof:
                    raise MalformedFrame(
                        f"connection closed {self._skip} bytes before the end of a frame"
                    )
                return None
        if self._header is None:
            if self._checked is None:
                if len(self._buffer) < HEADER_SIZE:
                    check_magic(self._buffer)  # another protocol: refused at its first byte
                    if self._eof and self._buffer:
                        raise MalformedFrame(
                            f"connection closed after {len(self._buffer)} bytes of a 24-byte header"
                        )
                    return None
                header = parse_header(self._buffer, self.limits)
                self.last_header = header
                if self.check_header is not None:
                    try:
                        self.check_header(header)
                    except CellvisionError as exc:
                        if not exc.fatal:
                            self._skip_frame(header)
                        raise
                self._checked = header
            header = self._checked
            if self.admit is not None and not self._admit(header):
                return None
            self._checked = None
            self._start_body(header)
        pending, body = self._header, self._body
        assert pending is not None
        assert body is not None
        header = pending
        if self._filled < header.body_length:
            if self._eof:
                raise MalformedFrame(
                    f"connection closed after {HEADER_SIZE + self._filled} of "
                    f"{header.frame_length} bytes of a frame",
                    request_id=header.request_id,
                )
            return None
        self._header = None
        self._body = None
        self._filled = 0
        metadata, self._metadata = self._metadata, None
        metadata, blobs = parse_body(header, body, metadata)
        return Frame(
            type=header.type,
            request_id=header.request_id,
            metadata=metadata,
            blobs=blobs,
            version=(header.major, header.minor),
            flags=header.flags,
        )

    def _admit(self, header: Header) -> bool:
        """Ask :attr:`admit` about ``header`` once its metadata has arrived; False when more
        bytes are needed or the frame was deferred (:attr:`paused`)."""
        assert self.admit is not None
        self.paused = False
        end = HEADER_SIZE + header.metadata_length
        if len(self._buffer) < end:
            if self._eof:
                raise MalformedFrame(
                    f"connection closed after {len(self._buffer)} of {header.frame_length} "
                    "bytes of a frame",
                    request_id=header.request_id,
                )
            return False
        try:
            metadata = decode_metadata(
                bytes(self._buffer[HEADER_SIZE:end]), request_id=header.request_id
            )
            self.admit(header, metadata)
        except AdmitLater:
            self.paused = True
            return False
        except CellvisionError as exc:
            if not exc.fatal:
                self._checked = None
                self._skip_frame(header)
            raise
        self._metadata = metadata
        return True

    def _skip_frame(self, header: Header) -> None:
        """Consume a refused frame: its header now, its body as it arrives (never kept)."""
        del self._buffer[:HEADER_SIZE]
        self._skip = header.body_length
        dropped = min(self._skip, len(self._buffer))
        del self._buffer[:dropped]
        self._skip -= dropped

    def _start_body(self, header: Header) -> None:
        """Give an admitted frame its body buffer, with the body bytes already received."""
        self._header = header
        self._body = new_body(header.body_length)
        taken = min(len(self._buffer) - HEADER_SIZE, header.body_length)
        self._body[:taken] = memoryview(self._buffer)[HEADER_SIZE : HEADER_SIZE + taken]
        del self._buffer[: HEADER_SIZE + taken]
        self._filled = taken
        self.copied_bytes += taken
