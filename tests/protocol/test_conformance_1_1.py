"""The checks of protocol 1.1's rules fail against servers that break them.

Each rule is broken twice over where that is cheap: in the reference server (monkeypatched in
process: the 1.0 behaviour, or a lie in WELCOME) and in a scripted server that answers frame
by frame. That the reference server as shipped passes every check is tested in
``test_conformance_live.py``.
"""

from __future__ import annotations

import contextlib
import itertools
import socket
import socketserver
import threading
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from loopback import server_in_thread

import protocol.connection
import protocol.frames
import protocol.images
import vision_server.frontends.images
import vision_server.frontends.tcp
import vision_server.server
from protocol import (
    Close,
    Error,
    Frame,
    FrameDecoder,
    Frames,
    InvalidArgument,
    Message,
    MessageType,
    Pong,
    Result,
    Welcome,
    payload_from_array,
)
from protocol.conformance import CHECKS, CheckResult, Target, run_checks
from protocol.connection import TRANSITIONS, Connection, Role, State
from protocol.errors import ErrorCode, NotAuthenticated
from protocol.frames import Header
from vision_server import Catalog
from vision_server.frontends import TcpFrontend
from vision_server.service import OperatorDesk

T = MessageType

RULES_OF_1_1 = {
    "null_is_absent": "§3.2",
    "duplicate_member_names": "§3.2",
    "integer_beyond_2_53": "§3.2",
    "integral_number_as_integer": "§3.2",
    "version_1_0_client": "§5.3",
    "version_smaller_minor": "§5.3",
    "welcome_timeouts": "§5.2",
    "max_in_flight_honoured": "§6.1",
    "capture_within_client_limit": "§6.4",
    "client_fatal_error": "§7",
    "client_nonfatal_error": "§5.7",
    "inspect_server_camera_images": "§6.3",
    "unknown_option": "§6.3",
    "option_camera": "§6.3",
    "request_after_close": "§5.6",
    "refused_at_header": "§3.1",
    "operator_call": "§6.6",
}
"""Every rule protocol 1.1 added or sharpened, by the check that tests it and its section."""


def test_every_rule_of_protocol_1_1_has_a_check() -> None:
    sections = {c.name: c.section for c in CHECKS}
    assert {name: sections.get(name) for name in RULES_OF_1_1} == RULES_OF_1_1


def _only(port: int, name: str, timeout_s: float = 5.0) -> CheckResult:
    """Run the one check ``name`` against the server on ``port``."""
    results = run_checks(Target("127.0.0.1", port, timeout_s), select=name)
    assert [r.name for r in results] == [name]
    return results[0]


def _fails(port: int, name: str, because: str, timeout_s: float = 5.0) -> None:
    result = _only(port, name, timeout_s)
    assert result.status == "fail", result
    assert because in result.detail, result.detail


# ----------------------------------------------------------------------------- the reference
# server, broken on purpose


def _last_duplicate_wins(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    return dict(pairs)  # protocol 1.0's parser (Python's json): the last duplicate wins


def _null_is_a_wrong_type(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A strict 1.0 reader: null is no string, number or object, so the field is wrong."""
    nulls = [key for key, value in pairs if value is None]
    if nulls:
        raise ValueError(f"{nulls[0]} is null")
    return dict(pairs)


def _strict_integer(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def test_null_is_absent_fails_when_null_is_a_value(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(protocol.frames, "_object_without_nulls", _null_is_a_wrong_type)
    with server_in_thread() as server:
        _fails(server.port, "null_is_absent", "expected RESULT, got type 0x00ff")


def test_duplicate_names_fails_when_the_last_one_wins(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(protocol.frames, "_object_without_nulls", _last_duplicate_wins)
    with server_in_thread() as server:
        _fails(server.port, "duplicate_member_names", "expected ERROR, got PONG")


def test_large_integers_fail_when_accepted(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(protocol.frames, "MAX_SAFE_INTEGER", 2**64)
    with server_in_thread() as server:
        _fails(server.port, "integer_beyond_2_53", "expected ERROR, got PONG")


def test_integral_numbers_fail_when_only_integer_literals_pass(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(protocol.images, "as_integer", _strict_integer)
    with server_in_thread() as server:
        _fails(server.port, "integral_number_as_integer", "expected RESULT, got type 0x00ff")


def test_a_1_0_client_fails_when_the_server_insists_on_1_1(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(vision_server.frontends.tcp, "negotiate_version", lambda *_: (1, 1))
    with server_in_thread() as server:
        _fails(server.port, "version_1_0_client", "WELCOME.version is [1, 1], expected [1, 0]")


def test_welcome_timeouts_fails_without_the_handshake_timeout(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    announced = TcpFrontend.welcome_limits

    def without(frontend: TcpFrontend) -> dict[str, int]:
        limits = announced(frontend)
        del limits["handshake_timeout_ms"]
        return limits

    monkeypatch.setattr(TcpFrontend, "welcome_limits", without)
    with server_in_thread() as server:
        _fails(server.port, "welcome_timeouts", "WELCOME.limits.handshake_timeout_ms is None")


def test_max_in_flight_fails_when_the_server_announces_more_than_it_runs(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    announced = TcpFrontend.welcome_limits
    monkeypatch.setattr(
        TcpFrontend, "welcome_limits", lambda f: announced(f) | {"max_in_flight": 8}
    )
    # It runs one at a time on a connection: the second of eight pipelined requests is BUSY.
    with server_in_thread(max_in_flight=1) as server:
        _fails(
            server.port,
            "max_in_flight_honoured",
            "was answered BUSY although WELCOME announced max_in_flight 8",
        )


def test_client_fatal_error_fails_when_the_server_answers_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Protocol 1.0's server: a client's ERROR is not in its table, so it is answered."""
    for state in (State.HANDSHAKE, State.HELLO_RECEIVED, State.OPEN, State.CLOSING):
        monkeypatch.delitem(
            TRANSITIONS,
            (Role.SERVER, state, protocol.connection.Direction.RECEIVE, T.ERROR),
        )
    with server_in_thread() as server:
        _fails(server.port, "client_fatal_error", "server sent ERROR 6 UNEXPECTED_MESSAGE")


def test_options_fail_when_the_server_ignores_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """Protocol 1.0: unknown options were ignored, and nothing kept a request off the camera."""
    monkeypatch.setattr(Catalog, "tuned", lambda self, inspection, *_, **__: inspection)
    with server_in_thread() as server:
        _fails(server.port, "unknown_option", "expected ERROR, got RESULT")
        _fails(server.port, "option_camera", "expected ERROR, got RESULT")


@pytest.mark.parametrize(
    ("message", "details", "verdict"),
    [
        ("options -> {key}: unknown key", {"option": "{key}"}, "pass"),
        ("takes no options", {}, "pass"),  # the same refusal for any option
        ("options -> {key}: unknown key", {}, "does not name the option"),
        ("request {rid}: bad options", {}, "does not name the option"),
        ("options -> {key}: unknown key", {"option": "roi"}, "details.option is 'roi'"),
    ],
    ids=["named", "no-options", "message-only", "unnamed", "wrong-name"],
)
def test_unknown_option_wants_the_key_in_details_option(
    monkeypatch: pytest.MonkeyPatch, message: str, details: dict[str, str], verdict: str
) -> None:
    requests = itertools.count(50)  # a message that differs per request names no option

    def refuse(self: Catalog, inspection: Any, options: Any) -> Any:
        key = next(iter(options))
        raise InvalidArgument(
            message.format(key=key, rid=next(requests)),
            details={k: v.format(key=key) for k, v in details.items()},
        )

    monkeypatch.setattr(Catalog, "tuned", refuse)
    with server_in_thread() as server:
        result = _only(server.port, "unknown_option")
    if verdict == "pass":
        assert result.status == "pass", result
    else:
        assert result.status == "fail", result
        assert verdict in result.detail, result.detail


def test_refused_at_header_fails_when_the_server_waits_for_the_body(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without the check at the header, the server waits for a body that never comes."""
    monkeypatch.setattr(Connection, "_check_header", lambda self, header: None)
    with server_in_thread() as server:
        _fails(server.port, "refused_at_header", "no answer within 0.5 s", timeout_s=0.5)


def test_refused_at_header_fails_when_only_large_bodies_are_refused_early(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A server that refuses at the header only what it would not buffer, and waits for a
    small body before it applies the state machine."""

    def too_large_only(self: Connection, header: Header) -> None:
        if header.frame_length > self.limits.max_handshake_frame_bytes:
            raise NotAuthenticated("not before HELLO", request_id=header.request_id)

    monkeypatch.setattr(Connection, "_check_header", too_large_only)
    with server_in_thread() as server:
        _fails(server.port, "refused_at_header", "no answer within 0.5 s", timeout_s=0.5)


# ----------------------------------------------------------------------------- scripted servers

HANG_UP = object()
"""In a script's replies: close the connection after what came before."""

Reply = Message | Frame | object
Script = Callable[[Frame], list[Reply]]
"""Answers one frame after the handshake."""

SERVER_CAMERA_WELCOME: dict[str, Any] = {
    # A type of the server's own: its RESULT data is free-form (SPEC §6.3.1).
    "inspections": (
        {"name": "fixed", "type": "scripted", "camera": "qc", "camera_source": "sim"},
        {"name": "tool_check", "type": "scripted", "camera": "tool", "camera_source": "request"},
    ),
    "cameras": (
        {"name": "qc", "source": "sim", "depth": False, "width": 64, "height": 48},
        {"name": "tool", "source": "request", "depth": False},
    ),
}


def polite(frame: Frame) -> list[Reply]:
    """What a correct server says to the requests the checks below send."""
    rid = frame.request_id
    if frame.type == T.PING:
        return [Pong(rid, frame.metadata.get("data", ""))]
    if frame.type == T.INSPECT:
        return [Result(rid, frame.metadata["inspection"], True)]
    if frame.type == T.CLOSE:
        return [Close(reason="bye"), HANG_UP]
    if frame.type == T.ERROR:
        return [HANG_UP] if frame.metadata.get("fatal") else [_error(rid, 6, "not from a client")]
    return [_error(rid, int(ErrorCode.UNEXPECTED_MESSAGE), "not scripted")]


def _error(rid: int, code: int, message: str, **details: Any) -> Error:
    return Error(rid, code, message, False, details)


Version = tuple[int, int]


def speaks_1_1(offer: Version) -> Version | None:
    """The version a server of 1.1 agrees on for a client's ``offer`` (None: refused)."""
    return (1, min(offer[1], 1)) if offer[0] == 1 else None


@contextlib.contextmanager
def scripted_server(
    script: Callable[[], Script], *, agree: Callable[[Version], Version | None] = speaks_1_1
) -> Iterator[int]:
    """A server that shakes hands (the version ``agree`` picks for the HELLO's first offer;
    None: UNSUPPORTED_VERSION listing 1.1), then answers each frame as a fresh ``script()``
    for the connection says. Yields its port."""

    class Handler(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            sock: socket.socket = self.request
            sock.settimeout(10.0)
            with contextlib.suppress(OSError):
                self._serve(sock, script())

        def _serve(self, sock: socket.socket, answer: Script) -> None:
            decoder = FrameDecoder()
            hello = _read_frame(sock, decoder)
            if hello is None:
                return
            first = hello.metadata["versions"][0]
            agreed = agree((first[0], first[1]))
            if agreed is None:
                refusal = Error(hello.request_id, 2, "no", True, {"supported": [[1, 1]]})
                sock.sendall(refusal.to_frame(hello.version).serialize())
                return
            welcome = Welcome(
                hello.request_id,
                agreed,
                "scripted",
                "0",
                {"max_in_flight": 4},
                SERVER_CAMERA_WELCOME["inspections"],
                SERVER_CAMERA_WELCOME["cameras"],
            )
            sock.sendall(welcome.to_frame(agreed).serialize())
            while (frame := _read_frame(sock, decoder)) is not None:
                for reply in answer(frame):
                    if reply is HANG_UP:
                        return
                    assert isinstance(reply, Message)
                    sock.sendall(reply.to_frame(agreed).serialize())

    class Server(socketserver.ThreadingTCPServer):
        daemon_threads = True
        allow_reuse_address = True

    with Server(("127.0.0.1", 0), Handler) as server:
        thread = threading.Thread(target=server.serve_forever, daemon=True)
        thread.start()
        try:
            yield server.server_address[1]
        finally:
            server.shutdown()
            thread.join(10.0)


def _read_frame(sock: socket.socket, decoder: FrameDecoder) -> Frame | None:
    while (frame := decoder.next_frame()) is None:
        data = sock.recv(65536)
        if not data:
            return None
        decoder.feed(data)
    return frame


def test_the_polite_script_passes_what_the_broken_ones_fail() -> None:
    """The control: the failures below come from what each script breaks."""
    with scripted_server(lambda: polite) as port:
        for name in (
            "request_after_close",
            "inspect_server_camera_images",
            "client_nonfatal_error",
            "client_fatal_error",
            "version_smaller_minor",
        ):
            assert _only(port, name).status == "pass", name


def test_request_after_close_fails_when_the_late_request_is_run() -> None:
    def script() -> Script:
        closing = False

        def answer(frame: Frame) -> list[Reply]:
            nonlocal closing
            if frame.type == T.CLOSE:
                closing = True  # and keep reading, which a server must not act on
                return []
            replies = polite(frame)
            return [*replies, Close(reason="bye"), HANG_UP] if closing else replies

        return answer

    with scripted_server(script) as port:
        _fails(
            port, "request_after_close", "the request sent after CLOSE was answered: type 0x0004"
        )


def test_request_after_close_fails_when_the_late_request_is_refused() -> None:
    """SPEC §5.6 (1.1): reading stops at CLOSE, so not even UNEXPECTED_MESSAGE comes back."""

    def script() -> Script:
        closing = False

        def answer(frame: Frame) -> list[Reply]:
            nonlocal closing
            if frame.type == T.CLOSE:
                closing = True
                return []
            if closing:
                refusal = _error(frame.request_id, 6, "after CLOSE")
                return [refusal, Close(reason="bye"), HANG_UP]
            return polite(frame)

        return answer

    with scripted_server(script) as port:
        _fails(port, "request_after_close", "answered: ERROR 6")


def test_request_after_close_fails_when_close_comes_before_the_answer() -> None:
    def answer(frame: Frame) -> list[Reply]:
        return [Close(reason="bye"), HANG_UP] if frame.type == T.INSPECT else polite(frame)

    with scripted_server(lambda: answer) as port:
        _fails(port, "request_after_close", "CLOSE without answering the INSPECT in flight")


def test_server_camera_images_fail_when_refused_as_in_protocol_1_0() -> None:
    def answer(frame: Frame) -> list[Reply]:
        if frame.type == T.INSPECT and frame.metadata.get("images"):
            return [_error(frame.request_id, 16, "the request must not carry images")]
        return polite(frame)

    with scripted_server(lambda: answer) as port:
        _fails(port, "inspect_server_camera_images", "expected RESULT, got type 0x00ff")


def test_client_nonfatal_error_fails_when_the_server_hangs_up() -> None:
    def answer(frame: Frame) -> list[Reply]:
        return [HANG_UP] if frame.type == T.ERROR else polite(frame)

    with scripted_server(lambda: answer) as port:
        _fails(port, "client_nonfatal_error", "expected ERROR, the server closed the connection")


def test_client_fatal_error_fails_when_the_server_says_close() -> None:
    def answer(frame: Frame) -> list[Reply]:
        return [Close(reason="bye"), HANG_UP] if frame.type == T.ERROR else polite(frame)

    with scripted_server(lambda: answer) as port:
        _fails(port, "client_fatal_error", "server sent type 0x0005")


def test_version_smaller_minor_fails_when_the_server_answers_its_own_minor() -> None:
    with scripted_server(lambda: polite, agree=lambda offer: (1, 9)) as port:
        _fails(port, "version_smaller_minor", "WELCOME.version is [1, 9], expected [1, 1]")


def test_version_smaller_minor_fails_when_the_server_takes_the_clients_minor() -> None:
    """Right for 1.1, wrong for 1.9: the server lists 1.1 as what it speaks."""
    with scripted_server(lambda: polite, agree=lambda o: o if o[0] == 1 else None) as port:
        _fails(
            port,
            "version_smaller_minor",
            "WELCOME.version is [1, 9] for an offer of 1.9 to a server of 1.1, expected [1, 1]",
        )


def _frames_of(size_bytes: int) -> Callable[[Frame], list[Reply]]:
    image = payload_from_array(np.zeros((1, size_bytes), np.uint8))

    def answer(frame: Frame) -> list[Reply]:
        if frame.type == T.CAPTURE:
            return [Frames(frame.request_id, "qc", (image,))]
        return polite(frame)

    return answer


def test_capture_within_client_limit_fails_when_a_frame_is_larger() -> None:
    with scripted_server(lambda: _frames_of(100_000)) as port:
        _fails(port, "capture_within_client_limit", "to a client that accepts 65536")


def test_capture_within_client_limit_accepts_frames_that_fit() -> None:
    with scripted_server(lambda: _frames_of(1000)) as port:
        result = _only(port, "capture_within_client_limit")
    assert result.status == "pass", result
    assert result.detail.startswith("16 frame(s) from 'qc' fit in ")


@pytest.mark.parametrize(
    ("details", "verdict"),
    [
        ({"size": 1_000_000, "max_size": 65536}, "pass"),
        ({"size": 1_000_000}, "fail"),
        ({"size": 1_000_000, "max_size": 67108864}, "fail"),
    ],
)
def test_capture_within_client_limit_wants_the_clients_limit_in_details(
    details: dict[str, int], verdict: str
) -> None:
    def answer(frame: Frame) -> list[Reply]:
        if frame.type == T.CAPTURE:
            return [_error(frame.request_id, 16, "too large for you", **details)]
        return polite(frame)

    with scripted_server(lambda: answer) as port:
        result = _only(port, "capture_within_client_limit")
    assert result.status == verdict, result
    if verdict == "fail":
        assert "expected max_size 65536" in result.detail


# ----------------------------------------------------------------------------- §4.1 and §5.4


def test_the_role_and_connection_limit_checks_pass_against_the_reference_server() -> None:
    with server_in_thread(max_connections=4) as server:
        for name in ("two_colour_images", "connection_limit_busy_is_fatal"):
            result = _only(server.port, name)
            assert result.status == "pass", result


def test_connection_limit_check_fails_on_a_non_fatal_busy(monkeypatch: pytest.MonkeyPatch) -> None:
    """The 1.0 prose: a non-fatal BUSY and a new HELLO on the same connection."""
    original = vision_server.frontends.tcp.Busy

    def non_fatal(message: str, **kwargs: Any) -> Any:
        kwargs["fatal"] = False
        return original(message, **kwargs)

    monkeypatch.setattr(vision_server.frontends.tcp, "Busy", non_fatal)
    with server_in_thread(max_connections=3) as server:
        _fails(server.port, "connection_limit_busy_is_fatal", "must be fatal")


def test_two_colour_images_check_fails_when_the_second_is_ignored(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    original = vision_server.frontends.images.decode_payloads

    def first_colour_only(payloads: Any, *args: Any, **kwargs: Any) -> Any:
        return original(payloads[:1], *args, **kwargs)

    monkeypatch.setattr(vision_server.frontends.images, "decode_payloads", first_colour_only)
    with server_in_thread() as server:
        _fails(server.port, "two_colour_images", "expected")


# ----------------------------------------------------------------------------- operator calls


def test_operator_call_passes_on_a_server_that_offers_none_and_on_one_that_does() -> None:
    with server_in_thread() as server:  # no console: UNEXPECTED_MESSAGE, which §6.6 allows
        result = _only(server.port, "operator_call")
        assert result.status == "pass", result
        assert "not offered (UNEXPECTED_MESSAGE)" in result.detail
        server.tcp.operator_desk = OperatorDesk()
        result = _only(server.port, "operator_call")
        assert result.status == "pass", result
        assert "DEADLINE_EXCEEDED" in result.detail


def test_operator_call_fails_when_the_deadline_is_ignored(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    waits = OperatorDesk.wait

    async def forever(self: OperatorDesk, call: Any, **kwargs: Any) -> Any:
        return await waits(self, call, **{**kwargs, "timeout_s": None})

    monkeypatch.setattr(OperatorDesk, "wait", forever)
    with server_in_thread() as server:
        server.tcp.operator_desk = OperatorDesk()
        _fails(server.port, "operator_call", "no answer", timeout_s=1.0)


def test_operator_call_fails_when_a_1_0_connection_gets_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(protocol.connection, "INTRODUCED_IN", {})
    with server_in_thread() as server:
        server.tcp.operator_desk = OperatorDesk()
        _fails(server.port, "operator_call", "expected error code 4")
