"""A deliberately simple blocking TCP peer for the conformance checks.

It speaks frames, not the state machine: the checks must be able to send what a correct client
never would (garbage, truncated frames, wrong versions).
"""

from __future__ import annotations

import contextlib
import socket
import ssl
import time
from dataclasses import dataclass
from typing import Any

from ..constants import MessageType
from ..errors import CellvisionError
from ..frames import Frame, FrameDecoder, Limits
from ..messages import Hello, Message
from .validation import FrameValidator

CLOSED = object()
"""Returned by recv_frame when the server closed the connection."""


class CheckFailed(AssertionError):
    """A conformance check saw something the spec does not allow."""


@dataclass(frozen=True)
class Target:
    host: str
    port: int
    timeout_s: float = 5.0
    auth_token: str | None = None
    tls: bool = False
    tls_verify: bool = True


class Peer:
    """One TCP connection to the server under test."""

    def __init__(self, target: Target) -> None:
        self.target = target
        raw = socket.create_connection((target.host, target.port), timeout=target.timeout_s)
        raw.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        if target.tls:
            context = ssl.create_default_context()
            if not target.tls_verify:
                context.check_hostname = False
                context.verify_mode = ssl.CERT_NONE
            raw = context.wrap_socket(raw, server_hostname=target.host)
        self.sock = raw
        # Generous limits: the peer must be able to read whatever the server sends.
        self.decoder = FrameDecoder(Limits(max_frame_bytes=1 << 31, max_metadata_bytes=1 << 26))
        self.welcome: Frame | None = None
        self.validator = FrameValidator()  # every received frame against protocol/schema

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()

    def __enter__(self) -> Peer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def send_raw(self, data: bytes) -> None:
        self.sock.sendall(data)

    def send(self, message: Message, version: tuple[int, int] = (1, 0)) -> None:
        self.sock.sendall(message.to_frame(version).serialize())

    def send_frame(self, frame: Frame) -> None:
        self.sock.sendall(frame.serialize())

    def shutdown_write(self) -> None:
        self.sock.shutdown(socket.SHUT_WR)

    def recv_frame(self, timeout_s: float | None = None) -> Frame | object:
        """The next frame, or CLOSED. Raises CheckFailed on a timeout or undecodable bytes."""
        deadline = time.monotonic() + (timeout_s or self.target.timeout_s)
        while True:
            try:
                frame = self.decoder.next_frame()
            except CellvisionError as exc:
                raise CheckFailed(
                    f"the server sent bytes that are not a valid frame: {exc}"
                ) from exc
            if frame is not None:
                problem = self.validator.problem(frame)
                if problem is not None:
                    raise CheckFailed(problem)
                return frame
            if self.decoder.eof:
                return CLOSED
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise CheckFailed(f"no answer within {timeout_s or self.target.timeout_s:g} s")
            self.sock.settimeout(remaining)
            try:
                data = self.sock.recv(1 << 20)
            except TimeoutError:
                continue
            except (ConnectionResetError, BrokenPipeError, ssl.SSLError):
                data = b""
            self.decoder.feed(data)

    def expect(
        self, mtype: MessageType, *, request_id: int | None = None, timeout_s: float | None = None
    ) -> Frame:
        frame = self.recv_frame(timeout_s)
        if frame is CLOSED:
            raise CheckFailed(f"expected {mtype.name}, the server closed the connection")
        assert isinstance(frame, Frame)
        if frame.type != mtype:
            raise CheckFailed(f"expected {mtype.name}, got {_describe(frame)}")
        if request_id is not None and frame.request_id != request_id:
            raise CheckFailed(
                f"{mtype.name} carries request id {frame.request_id}, expected {request_id}"
            )
        return frame

    def expect_error(
        self, code: int, *, request_id: int | None = None, fatal: bool | None = None
    ) -> Frame:
        frame = self.expect(MessageType.ERROR, request_id=request_id)
        got = frame.metadata.get("code")
        if got != int(code):
            raise CheckFailed(f"expected error code {int(code)}, got {_describe(frame)}")
        if not isinstance(frame.metadata.get("message", ""), str):
            raise CheckFailed("ERROR.message must be a string")
        if fatal is not None and frame.metadata.get("fatal") is not fatal:
            raise CheckFailed(
                f"ERROR {got} must have fatal={fatal}, got {frame.metadata.get('fatal')!r}"
            )
        return frame

    def expect_closed(self, timeout_s: float | None = None) -> None:
        """The server must close the connection (any frames before that are ignored)."""
        while True:
            frame = self.recv_frame(timeout_s)
            if frame is CLOSED:
                return

    def handshake(self, request_id: int = 1) -> Frame:
        self.send(Hello(request_id, ((1, 0),), "cellvision-conformance", self.target.auth_token))
        self.welcome = self.expect(MessageType.WELCOME, request_id=request_id)
        return self.welcome


def _describe(frame: Frame) -> str:
    try:
        name = MessageType(frame.type).name
    except ValueError:
        name = f"type 0x{frame.type:04x}"
    if frame.type == MessageType.ERROR:
        meta: dict[str, Any] = frame.metadata
        return f"ERROR {meta.get('code')} {meta.get('name')}: {meta.get('message')}"
    return f"{name} (id {frame.request_id})"
