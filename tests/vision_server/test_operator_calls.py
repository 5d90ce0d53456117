"""Operator calls (SPEC §6.6) end to end over real sockets: a robot posts OPERATOR_CALL to the
real server with its console (the example cell), a person answers it through the console's
API over real HTTP; timeouts, a robot that leaves, the desk's limits, shutdown, 1.0 sessions
and a server without console."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any

import cv2
import numpy as np
import pytest
from console_server import TOKEN, Browserless, RunningConsole, console_server
from loopback import server_in_thread

from protocol import (
    Busy,
    Close,
    DeadlineExceeded,
    Error,
    ErrorCode,
    Frame,
    FrameDecoder,
    Hello,
    ImageEncoding,
    ImagePayload,
    ImageRole,
    InvalidArgument,
    Message,
    MessageType,
    OperatorAnswer,
    OperatorCall,
    ShuttingDown,
    UnexpectedMessage,
    Welcome,
)
from protocol.messages import DecodeContext, message_from_frame
from robot_client import SyncVisionClient
from vision_server.service import OperatorDesk

WAIT_S = 20.0


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    with console_server(tmp_path_factory.mktemp("cell")) as running:
        yield running


@pytest.fixture
def person(server: RunningConsole) -> Browserless:
    """The operator's browser, signed in."""
    browser = Browserless(server.url)
    assert browser.login().status == 200
    return browser


@pytest.fixture
def robot(server: RunningConsole) -> Iterator[SyncVisionClient]:
    client = SyncVisionClient(
        "127.0.0.1", server.app.port, auth_token=TOKEN, request_timeout_s=WAIT_S
    )
    yield client
    client.close()


@pytest.fixture
def background() -> Iterator[ThreadPoolExecutor]:
    with ThreadPoolExecutor(max_workers=2) as pool:
        yield pool


def wait_for(predicate: Callable[[], Any], what: str) -> Any:
    """Poll until ``predicate()`` is truthy (a condition, not a timing: the limit only ends a
    broken test)."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


def open_calls(person: Browserless) -> list[dict[str, Any]]:
    reply = person.get("/api/operator/calls")
    assert reply.status == 200, reply.body
    calls: list[dict[str, Any]] = reply.json()["calls"]
    return calls


def recent(person: Browserless, call_id: int) -> dict[str, Any]:
    closed = person.get("/api/operator/calls").json()["recent"]
    return next(c for c in closed if c["id"] == call_id)


def overlay_png() -> bytes:
    image = np.zeros((48, 64, 3), np.uint8)
    cv2.circle(image, (32, 24), 10, (0, 0, 255), 2)
    ok, png = cv2.imencode(".png", image)
    assert ok
    return png.tobytes()


# ----------------------------------------------------------------------------- a raw robot


class RawRobot:
    """A protocol client on a plain blocking socket, for what VisionClient would not do (leave
    with a call in flight, speak 1.0)."""

    def __init__(self, port: int, versions: tuple[tuple[int, int], ...] = ((1, 1),)) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=WAIT_S)
        self.decoder = FrameDecoder()
        self.version = versions[0]
        self.send(Hello(1, versions, "raw-robot", TOKEN))
        welcome = self.receive()
        assert isinstance(welcome, Welcome), welcome
        self.version = welcome.version

    def send(self, message: Message) -> None:
        self.sock.sendall(message.to_frame(self.version).serialize())

    def send_raw(self, frame: Frame) -> None:
        self.sock.sendall(frame.serialize())

    def receive(self) -> Message:
        """The next message from the server, read without the client's state machine (a
        raw robot also sends frames its Connection would refuse to)."""
        while True:
            frame = self.decoder.next_frame()
            if frame is not None:
                return message_from_frame(frame, DecodeContext(max_image_pixels=1 << 24))
            data = self.sock.recv(65536)
            assert data, "the server closed the connection"
            self.decoder.feed(data)

    def close(self) -> None:
        self.sock.close()


# ----------------------------------------------------------------------------- answered


def test_a_call_is_shown_on_the_console_and_the_answer_reaches_the_robot(
    server: RunningConsole,
    person: Browserless,
    robot: SyncVisionClient,
    background: ThreadPoolExecutor,
) -> None:
    png = overlay_png()
    gray = np.arange(12, dtype=np.uint8).reshape(3, 4)
    overlay = ImagePayload(ImageEncoding.PNG, 64, 48, png, ImageRole.OVERLAY)
    asked: Future[OperatorAnswer] = background.submit(
        robot.operator_call,
        "inspection 'magnet_check' failed 3 time(s)",
        choices=("retry", "abort"),
        inspection="magnet_check",
        skill="quality_control",
        images=(overlay, gray),
        deadline_s=600.0,
    )
    (call,) = wait_for(lambda: open_calls(person), "the call on the console")
    assert call["message"] == "inspection 'magnet_check' failed 3 time(s)"
    assert call["choices"] == ["retry", "abort"]
    assert (call["inspection"], call["skill"]) == ("magnet_check", "quality_control")
    assert call["peer"].startswith("127.0.0.1:")
    assert call["waiting_s"] >= 0
    assert call["expires_at"] > call["posted_at"]
    shown = [(i["width"], i["height"], i["role"]) for i in call["images"]]
    assert shown == [(64, 48, "overlay"), (4, 3, "color")]
    first = person.get(call["images"][0]["url"])
    assert (first.status, first.headers["Content-Type"], first.body) == (200, "image/png", png)
    second = person.get(call["images"][1]["url"])
    decoded = cv2.imdecode(np.frombuffer(second.body, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(decoded, gray)  # a raw image is shown as a lossless PNG
    assert not asked.done()

    reply = person.post_json(f"/api/operator/calls/{call['id']}/answer", {"choice": "retry"})
    assert reply.status == 200, reply.body
    answer = asked.result(WAIT_S)
    assert answer.choice == "retry"
    assert answer.by.startswith("admin (console 127.0.0.1:")  # the role of the token signed in
    assert answer.answered_at == pytest.approx(reply.json()["answered_at"])
    assert open_calls(person) == []
    assert recent(person, call["id"])["outcome"] == "answered"
    # A second person answering the same call is told it is closed, and by whom.
    late = person.post_json(f"/api/operator/calls/{call['id']}/answer", {"choice": "abort"})
    assert late.status == 409
    assert late.json()["error"]["code"] == "CALL_CLOSED"
    assert "already answered 'retry'" in late.json()["error"]["message"]


def test_an_answer_must_be_one_the_call_offers(
    person: Browserless, robot: SyncVisionClient, background: ThreadPoolExecutor
) -> None:
    asked = background.submit(robot.operator_call, "choose", choices=("retry", "abort"))
    (call,) = wait_for(lambda: open_calls(person), "the call")
    path = f"/api/operator/calls/{call['id']}/answer"
    refused = person.post_json(path, {"choice": "continue"})
    assert refused.status == 400
    assert "offers retry, abort" in refused.json()["error"]["message"]
    assert person.post_json(path, {"choice": 3}).status == 400
    assert person.request("POST", path, b"not json").status == 400
    assert person.post_json("/api/operator/calls/999999/answer", {"choice": "retry"}).status == 404
    assert person.post_json(path, {"choice": "abort"}).status == 200
    assert asked.result(WAIT_S).choice == "abort"


def test_the_operator_api_needs_the_token(server: RunningConsole) -> None:
    stranger = Browserless(server.url)
    assert stranger.get("/api/operator/calls").status == 401
    assert stranger.post_json("/api/operator/calls/1/answer", {"choice": "retry"}).status == 401


# ----------------------------------------------------------------------------- not answered


def test_an_unanswered_call_ends_with_deadline_exceeded(
    person: Browserless, robot: SyncVisionClient
) -> None:
    with pytest.raises(DeadlineExceeded, match="nobody answered"):
        robot.operator_call("anyone?", deadline_s=0.05)
    assert open_calls(person) == []
    closed = person.get("/api/operator/calls").json()["recent"][0]
    assert (closed["message"], closed["outcome"]) == ("anyone?", "expired")


def test_a_robot_that_leaves_takes_its_call_off_the_console(
    server: RunningConsole, person: Browserless
) -> None:
    raw = RawRobot(server.app.port)
    raw.send(OperatorCall(2, "I will vanish"))
    (call,) = wait_for(lambda: open_calls(person), "the call")
    raw.sock.shutdown(socket.SHUT_WR)  # end of stream, as a robot program that exits
    wait_for(lambda: not open_calls(person), "the call withdrawn")
    assert recent(person, call["id"])["outcome"] == "withdrawn"
    raw.close()


def test_a_robot_that_closes_gets_its_call_answered_before_close(
    server: RunningConsole, person: Browserless
) -> None:
    raw = RawRobot(server.app.port)
    raw.send(OperatorCall(2, "closing soon"))
    wait_for(lambda: open_calls(person), "the call")
    raw.send(Close())
    answer = raw.receive()
    assert isinstance(answer, Error)
    assert answer.request_id == 2
    assert answer.code == ErrorCode.DEADLINE_EXCEEDED
    assert "withdrawn" in answer.message
    assert isinstance(raw.receive(), Close)
    raw.close()
    assert open_calls(person) == []


# ----------------------------------------------------------------------------- limits


def test_the_desk_is_bounded_in_calls_and_image_bytes(
    server: RunningConsole, person: Browserless, robot: SyncVisionClient
) -> None:
    desk = server.app.tcp.operator_desk
    assert desk is not None
    limits = desk.max_calls, desk.max_image_bytes
    raw = RawRobot(server.app.port)
    try:
        server.call(lambda: setattr(desk, "max_calls", 1))
        raw.send(OperatorCall(2, "first"))
        wait_for(lambda: open_calls(person), "the first call")
        with pytest.raises(Busy, match="already holds 1 open calls"):
            robot.operator_call("second")
        server.call(lambda: setattr(desk, "max_image_bytes", 1000))
        server.call(lambda: setattr(desk, "max_calls", 4))
        big = np.random.default_rng(1).integers(0, 255, (40, 40), dtype=np.uint8)
        with pytest.raises(InvalidArgument, match="more than the 1000 bytes"):
            robot.operator_call("too big", images=(big,))
        assert [c["message"] for c in open_calls(person)] == ["first"]
    finally:
        server.call(lambda: (setattr(desk, "max_calls", limits[0]), None)[1])
        server.call(lambda: setattr(desk, "max_image_bytes", limits[1]))
        raw.close()
    wait_for(lambda: not open_calls(person), "the first call withdrawn")


def test_a_depth_image_or_a_bad_png_is_refused_naming_the_image(
    server: RunningConsole, person: Browserless
) -> None:
    raw = RawRobot(server.app.port)
    meta = {
        "message": "look",
        "images": [{"blob": 0, "encoding": "png", "width": 0, "height": 0, "role": "overlay"}],
    }
    raw.send_raw(Frame(MessageType.OPERATOR_CALL, 2, meta, (b"not a png",), version=(1, 1)))
    refused = raw.receive()
    assert isinstance(refused, Error)
    assert refused.code == ErrorCode.BAD_IMAGE
    depth = {**meta, "images": [{"blob": 0, "encoding": "depth16", "width": 1, "height": 1}]}
    raw.send_raw(Frame(MessageType.OPERATOR_CALL, 3, depth, (b"\0\0",), version=(1, 1)))
    refused = raw.receive()
    assert isinstance(refused, Error)
    assert refused.code == ErrorCode.BAD_IMAGE
    assert "depth" in refused.message
    raw.close()
    assert open_calls(person) == []


# ----------------------------------------------------------------------------- who may call


def test_a_1_0_session_never_sees_the_operator_call(server: RunningConsole) -> None:
    raw = RawRobot(server.app.port, versions=((1, 0),))
    assert raw.version == (1, 0)
    raw.send_raw(Frame(MessageType.OPERATOR_CALL, 2, {"message": "x"}, version=(1, 0)))
    refused = raw.receive()
    assert isinstance(refused, Error)
    assert refused.code == ErrorCode.UNKNOWN_MESSAGE_TYPE
    raw.close()


def test_a_server_without_console_refuses_operator_calls() -> None:
    with server_in_thread() as plain:
        client = SyncVisionClient("127.0.0.1", plain.port, request_timeout_s=WAIT_S)
        try:
            with pytest.raises(UnexpectedMessage, match="no operator console"):
                client.operator_call("anyone?")
            client.ping()  # the connection goes on
        finally:
            client.close()


def test_shutdown_answers_an_open_call_with_shutting_down(
    background: ThreadPoolExecutor,
) -> None:
    desk = OperatorDesk()
    with server_in_thread() as plain:
        plain.tcp.operator_desk = desk
        client = SyncVisionClient("127.0.0.1", plain.port, request_timeout_s=WAIT_S)
        asked = background.submit(client.operator_call, "waiting for a stop")
        wait_for(desk.open_calls, "the call")
    # Leaving the block stopped the server with the call open.
    with pytest.raises(ShuttingDown):
        asked.result(WAIT_S)
    client.close()
    assert desk.open_calls() == []
