"""A controller that sends line-protocol text to the binary protocol's port is answered at
once, with a MALFORMED_FRAME that says which port this is and where the line protocol listens
(it got the handshake timeout's silence, then a CLOSE about a HELLO)."""

from __future__ import annotations

import asyncio

from loopback import run

from protocol import ErrorCode, FrameDecoder, MessageType
from vision_server.app import App
from vision_server.config import LineSettings, ServerSettings
from vision_server.service import builtin_catalog


async def _answer_to(app: App, data: bytes) -> dict[str, object]:
    """What the binary port answers ``data`` with: the one frame before it closes."""
    reader, writer = await asyncio.open_connection("127.0.0.1", app.port)
    try:
        writer.write(data)  # and nothing more: the write side stays open
        received = await reader.read()  # until the server closes the connection
    finally:
        writer.close()
    decoder = FrameDecoder()
    decoder.feed(received)
    frame = decoder.next_frame()
    assert frame is not None, received
    assert frame.type == MessageType.ERROR
    return frame.metadata


def test_line_text_on_the_binary_port_is_answered_at_once_naming_the_line_port() -> None:
    # A handshake timeout far beyond the test's own deadline: only an answer at the first
    # bytes can pass.
    settings = ServerSettings(port=0, workers=1, handshake_timeout_s=600.0)
    app = App(builtin_catalog(), settings, line=LineSettings(enabled=True, port=0))

    async def body() -> None:
        async with app:
            assert app.line is not None
            error = await _answer_to(app, b"T 1\n")
            assert error["code"] == ErrorCode.MALFORMED_FRAME
            assert error["fatal"] is True
            message = str(error["message"])
            assert message.startswith(
                "this is the binary protocol's port; the line protocol listens on "
                f"port {app.line.port} (bad magic b'T 1\\n', expected b'CVIS')"
            ), message
            # Binary garbage is refused as before, without the hint.
            garbage = await _answer_to(app, b"\x00\x01")
            assert str(garbage["message"]).startswith("bad magic b'\\x00"), garbage

    run(body(), timeout_s=30.0)
