"""WireStream over real loopback sockets (plain and TLS): bodies land in their frame buffer,
reading waits for the owner (and for its pause), EOF reaches the connection.

The stream under test carries a server-side :class:`protocol.Connection`; the peer is either a
raw asyncio connection (to cut frames where the test wants) or a client-side WireStream.
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
from collections.abc import AsyncIterator
from pathlib import Path

import numpy as np
import pytest
from certs import self_signed
from copies import exporter, is_frame_body
from loopback import run, wait_until

from protocol import (
    NEED_DATA,
    ConnectionClosed,
    Error,
    Hello,
    Inspect,
    InvalidArgument,
    Message,
    Role,
    Welcome,
    payload_from_array,
)
from protocol.connection import Connection
from protocol.constants import HEADER_SIZE
from wireio import READ_BUFFER_BYTES, WireStream, open_connection, serve

V10 = (1, 0)
LIMITS = {"max_frame_bytes": 64 << 20, "max_image_pixels": 50_000_000, "max_in_flight": 4}
IMAGE = np.random.default_rng(3).integers(0, 256, (768, 1024), np.uint8)


@contextlib.asynccontextmanager
async def listening(
    tls: ssl.SSLContext | None = None,
) -> AsyncIterator[tuple[int, asyncio.Queue[WireStream]]]:
    """A wireio server whose accepted streams (TLS started, a server Connection attached) go
    to the queue; each stays open until the test is done with it."""
    accepted: asyncio.Queue[WireStream] = asyncio.Queue()
    done = asyncio.Event()

    async def on_connect(stream: WireStream) -> None:
        stream.attach(Connection(Role.SERVER))
        if tls is not None:
            await stream.start_tls(tls, server_side=True, ssl_handshake_timeout=10.0)
        await accepted.put(stream)
        await done.wait()
        stream.close()

    server = await serve(on_connect, "127.0.0.1", 0)
    try:
        yield server.sockets[0].getsockname()[1], accepted
    finally:
        done.set()
        server.close()


async def next_message(stream: WireStream) -> Message | ConnectionClosed:
    conn = stream.conn
    assert conn is not None
    while True:
        event = conn.next_event()
        if event is not NEED_DATA:
            assert isinstance(event, Message | ConnectionClosed)
            return event
        await stream.receive()


async def handshake(server: WireStream, client: WireStream) -> None:
    assert client.conn is not None
    assert server.conn is not None
    client.writelines(client.conn.send_parts(Hello(1, (V10,), "test")))
    await client.drain()
    assert isinstance(await next_message(server), Hello)
    server.writelines(server.conn.send_parts(Welcome(1, V10, "s", "0", LIMITS)))
    await server.drain()
    assert isinstance(await next_message(client), Welcome)


@pytest.fixture(scope="module")
def tls_contexts(tmp_path_factory: pytest.TempPathFactory) -> tuple[ssl.SSLContext, ...]:
    cert, key = self_signed(Path(tmp_path_factory.mktemp("certs")))
    server = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    server.load_cert_chain(cert, key)
    client = ssl.create_default_context(cafile=str(cert))
    return server, client


@pytest.mark.parametrize("use_tls", [False, True], ids=["tcp", "tls"])
def test_an_image_is_received_into_its_frame_body_and_answered(
    use_tls: bool, tls_contexts: tuple[ssl.SSLContext, ...]
) -> None:
    """Over TLS too: asyncio's TLS layer of 3.11 decrypts into the BufferedProtocol's buffer."""
    server_tls, client_tls = tls_contexts if use_tls else (None, None)

    async def body() -> None:
        async with listening(server_tls) as (port, accepted):
            client = await open_connection(
                "127.0.0.1", port, Connection(Role.CLIENT), ssl=client_tls
            )
            server = await accepted.get()
            assert (server.get_extra_info("sslcontext") is not None) is use_tls
            await handshake(server, client)
            assert client.conn is not None
            assert server.conn is not None
            copied_before = server.conn.copied_bytes  # the HELLO's small body was copied
            client.writelines(client.conn.send_parts(Inspect(2, "x", (payload_from_array(IMAGE),))))
            await client.drain()
            request = await next_message(server)
            assert isinstance(request, Inspect)
            pixels = np.frombuffer(request.images[0].data, np.uint8).reshape(IMAGE.shape)
            assert np.array_equal(pixels, IMAGE)
            body = exporter(request.images[0].data)
            assert is_frame_body(body)
            assert IMAGE.nbytes < len(body) < IMAGE.nbytes + 1024  # the frame's body itself
            assert server.conn.copied_bytes - copied_before <= READ_BUFFER_BYTES
            server.writelines(
                server.conn.send_parts(Error.from_exception(InvalidArgument("no", request_id=2)))
            )
            await server.drain()
            answer = await next_message(client)
            assert isinstance(answer, Error)
            assert answer.request_id == 2
            client.close()
            await client.wait_closed()

    run(body())


def test_nothing_is_read_before_the_owner_asks_nor_while_it_pauses() -> None:
    async def body() -> None:
        async with listening() as (port, accepted):
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            server = await accepted.get()
            assert server.transport is not None
            assert not server.transport.is_reading()  # TLS could still be started
            writer.write(Hello(1, (V10,), "raw").to_frame(V10).serialize())
            asking = asyncio.ensure_future(server.receive())
            await wait_until(lambda: asking.done(), "the HELLO is read once asked for")
            server.pause_reading()
            assert server.reading_paused
            assert not server.transport.is_reading()
            server.resume_reading()
            assert server.transport.is_reading()  # between small frames it reads on
            writer.close()

    run(body())


def test_a_large_body_waits_for_its_header_to_be_seen_then_is_read_in_place() -> None:
    """The body's first bytes, read with its header, are held (not buffered in the decoder)
    and copied once into the body; the rest is read into the body directly."""

    async def body() -> None:
        async with listening() as (port, accepted):
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            server = await accepted.get()
            conn = server.conn
            assert conn is not None
            writer.write(Hello(1, (V10,), "raw").to_frame(V10).serialize())
            assert isinstance(await next_message(server), Hello)
            server.writelines(conn.send_parts(Welcome(1, V10, "s", "0", LIMITS)))
            copied = conn.copied_bytes  # the HELLO's small body was copied
            frame = Inspect(2, "x", (payload_from_array(IMAGE),)).to_frame(V10).serialize()
            first = HEADER_SIZE + 1000
            writer.write(frame[:first])
            assert await server.receive() == first
            assert server.transport is not None
            assert not server.transport.is_reading()  # the owner must admit the header first
            assert conn.copied_bytes == copied  # the 1000 body bytes are held, not buffered
            assert conn.next_event() is NEED_DATA  # header parsed, body buffer made
            writer.write(frame[first:])
            request = await next_message(server)
            assert isinstance(request, Inspect)
            assert conn.copied_bytes == copied + 1000  # held bytes, copied once into the body
            assert np.array_equal(
                np.frombuffer(request.images[0].data, np.uint8).reshape(IMAGE.shape), IMAGE
            )
            writer.close()
            with contextlib.suppress(ConnectionError):
                await reader.read()

    run(body())


def test_the_peers_eof_reaches_the_connection() -> None:
    async def body() -> None:
        async with listening() as (port, accepted):
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            server = await accepted.get()
            writer.write_eof()
            assert isinstance(await next_message(server), ConnectionClosed)
            assert await server.receive() == 0  # and stays told
            writer.close()

    run(body())
