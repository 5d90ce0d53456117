"""Issue 13: holes in the connection timeouts found by the attack soak (scripts/attack.py).

- A connection that sent a request and then went silent was never closed as idle: while a
  request was in flight the read loop waited without a timeout, and nothing woke it when the
  answer went out.
- A frame dribbled a few bytes at a time was never closed by the frame timeout: each chunk
  restarted the clock, which must count from the frame's first byte.

Through real sockets on loopback, against the server in a thread; no verdict depends on a sleep
(the waits are generous bounds on conditions).
"""

from __future__ import annotations

import threading

import numpy as np
from loopback import run, server_in_thread, wait_until

from protocol import Inspect, MessageType, Ping, payload_from_array
from protocol.conformance import Target
from protocol.conformance.peer import Peer
from vision_server.server import VisionServer


def peer_for(server: VisionServer) -> Peer:
    return Peer(Target("127.0.0.1", server.port, timeout_s=20.0))


def test_a_connection_silent_after_a_request_is_closed_as_idle() -> None:
    with server_in_thread(idle_timeout_s=0.3) as server, peer_for(server) as peer:
        peer.handshake()
        image = payload_from_array(np.full((8, 8), 9, np.uint8))
        peer.send(Inspect(2, "brightness", (image,)))
        peer.expect(MessageType.RESULT, request_id=2)
        close = peer.expect(MessageType.CLOSE, timeout_s=20.0)
        assert "idle" in close.metadata["reason"]
        peer.expect_closed(timeout_s=20.0)
        run(wait_until(lambda: not server.tcp.connections, "the slot is free", 20.0))


def test_a_frame_dribbled_byte_by_byte_is_closed_at_the_frame_timeout() -> None:
    frame = Ping(2, "x" * 20_000).to_frame((1, 0)).serialize()
    stop = threading.Event()
    with server_in_thread(frame_timeout_s=0.5) as server, peer_for(server) as peer:
        peer.handshake()

        def dribble() -> None:
            # Slower than a whole frame may take, faster than the timeout between two bytes.
            for at in range(len(frame) - 1):
                if stop.wait(0.01):
                    return
                try:
                    peer.send_raw(frame[at : at + 1])
                except OSError:
                    return

        sender = threading.Thread(target=dribble, daemon=True)
        sender.start()
        try:
            close = peer.expect(MessageType.CLOSE, timeout_s=20.0)
            assert "not complete" in close.metadata["reason"]
        finally:
            stop.set()
            sender.join(10.0)
