"""The conformance suite against live servers: the real one passes, broken ones fail.

The real server runs in a background thread (the suite uses blocking sockets) or as the
``vision-server serve`` process; the broken ones are tiny threaded socket servers.
"""

from __future__ import annotations

import contextlib
import json
import socket
import socketserver
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from example_servers import example_cell, vision_server_process
from loopback import server_in_thread

from protocol import FrameDecoder, MessageType, Welcome
from protocol.conformance import CHECKS, PROFILES, Feature, Target, run_checks
from protocol.conformance.__main__ import _address
from protocol.conformance.__main__ import main as conformance_main
from protocol.conformance.checks import Context

REPO_ROOT = Path(__file__).resolve().parents[2]

SERVER_CAMERA_CHECKS = {
    "inspect_server_camera",
    "inspect_server_camera_images",
    "capture_server_camera",
    "capture_within_client_limit",
}
"""The checks the built-in demo has nothing for: it has no server-side camera."""


@pytest.mark.parametrize("auth_token", [None, "cell-7"])
def test_the_reference_server_passes_every_check(auth_token: str | None) -> None:
    with server_in_thread(auth_token=auth_token) as server:
        results = run_checks(Target("127.0.0.1", server.port, 10.0, auth_token))
    assert len(results) >= 61
    assert len(results) == len(CHECKS)
    assert len({r.name for r in results}) == len(results)
    not_passed = {r.name: (r.status, r.detail) for r in results if r.status != "pass"}
    assert not_passed == {
        "inspect_server_camera": (
            "skip",
            "the server offers no inspection on a server-side camera",
        ),
        "inspect_server_camera_images": (
            "skip",
            "the server offers no inspection on a server-side camera that takes no depth",
        ),
        "capture_server_camera": ("skip", "the server lists no server-side camera"),
        "capture_within_client_limit": ("skip", "the server lists no server-side camera"),
    }
    assert all(r.section.startswith("§") for r in results)
    # Without a configuration file the server refuses RELOAD, as §6.5 says it must.
    reload = next(r for r in results if r.name == "reload")
    assert reload.detail.startswith("INVALID_ARGUMENT: ")


def test_cli_text_report_against_the_reference_server(capsys: pytest.CaptureFixture[str]) -> None:
    with server_in_thread() as server:
        port = server.port
        code = conformance_main([f"127.0.0.1:{port}", "-k", "ping"])
    out = capsys.readouterr().out
    assert code == 0
    lines = out.strip().splitlines()
    assert lines[0].split() == ["check", "section", "result", "detail"]
    assert any(line.split()[:3] == ["ping_pong", "§5.5", "PASS"] for line in lines)
    assert lines[-1] == f"1 passed, 0 failed, 0 skipped against 127.0.0.1:{port}"


def _suite(address: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "protocol.conformance", address, *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=180,
    )


@pytest.mark.parametrize("configuration", ["built-in demo", "examples/cell.yaml"])
def test_cli_json_against_the_vision_server_process(configuration: str, tmp_path: Path) -> None:
    """The suite passes against the server as shipped: the built-in demo and the example cell
    (whose RGB-D camera declares 640x480, so depth must come in that size)."""
    demo = configuration == "built-in demo"
    # The example's console on port 0 too (examples/cell.yaml's 7880 may be taken): the file
    # is as shipped, the ports are the command line's (example_servers).
    with vision_server_process(None if demo else example_cell(tmp_path)) as address:
        checked = _suite(address, "--json")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    report = json.loads(checked.stdout)
    assert report["target"] == address
    assert report["profile"] == "full"
    failed = [(r["name"], r["detail"]) for r in report["results"] if r["status"] != "pass"]
    assert report["failed"] == 0, failed
    assert report["not_applicable"] == 0
    skipped = {r["name"] for r in report["results"] if r["status"] == "skip"}
    assert skipped == (SERVER_CAMERA_CHECKS if demo else set())
    assert report["skipped"] == len(skipped)
    assert report["passed"] == len(report["results"]) - len(skipped) >= 57
    first = report["results"][0]
    assert set(first) == {
        "name",
        "section",
        "description",
        "status",
        "detail",
        "duration_s",
    }
    if not demo:  # what the example cell offers was exercised, not skipped
        details = {r["name"]: r["detail"] for r in report["results"]}
        assert details["capture_server_camera"] == "color gray8 1024x768"
        assert details["inspect_server_camera"].startswith("magnet_check: verdict ")
        assert details["reload"].startswith("RELOADED, config_hash ")


# ----------------------------------------------------------------------------- profiles


def test_minimal_profile_reports_what_it_leaves_out_as_not_applicable(tmp_path: Path) -> None:
    with vision_server_process(example_cell(tmp_path)) as address:
        checked = _suite(address, "--json", "--profile", "minimal")
        text = _suite(address, "--profile", "minimal", "-k", "reload")
    assert checked.returncode == 0, checked.stdout + checked.stderr
    report = json.loads(checked.stdout)
    assert report["profile"] == "minimal"
    not_applicable = {r["name"]: r["detail"] for r in report["results"] if r["status"] == "n/a"}
    assert not_applicable == {
        **{
            name: "not applicable (profile minimal: no server cameras)"
            for name in SERVER_CAMERA_CHECKS
        },
        "reload": "not applicable (profile minimal: no reload)",
    }
    assert report["not_applicable"] == 5
    assert report["failed"] == report["skipped"] == 0
    assert report["passed"] == len(report["results"]) - 5
    # The text report says so too, and its closing line counts them apart from the passes.
    lines = text.stdout.strip().splitlines()
    assert lines[1].split()[:3] == ["reload", "§6.5", "N/A"]
    assert lines[-1] == f"0 passed, 0 failed, 0 skipped, 1 not applicable against {address} " + (
        "(profile minimal)"
    )


def test_profiles_leave_out_only_the_checks_that_need_what_they_omit() -> None:
    minimal = PROFILES["minimal"]
    assert minimal.omits == {Feature.SERVER_CAMERAS, Feature.RELOAD}
    assert PROFILES["full"].omits == frozenset()
    left_out = {c.name for c in CHECKS if c.needs & minimal.omits}
    assert left_out == SERVER_CAMERA_CHECKS | {"reload"}


def test_cli_help_documents_the_profiles(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        conformance_main(["--help"])
    assert exited.value.code == 0
    out = capsys.readouterr().out
    assert "--profile {full,minimal}" in out
    assert "minimal  no server-side cameras and no RELOAD" in out
    left_out = (
        "inspect_server_camera, inspect_server_camera_images, capture_within_client_limit, "
        "capture_server_camera, reload"
    )
    assert f"(checks left out: {left_out})" in out
    assert "not applicable" in out


# ----------------------------------------------------------------------------- image sizes


def _context(cameras: list[dict[str, Any]]) -> Context:
    return Context(Target("127.0.0.1", 1), {}, (), tuple(cameras))


@pytest.mark.parametrize(
    ("camera", "expected"),
    [
        ({"name": "c", "width": 640, "height": 480}, (640, 480)),
        ({"name": "c", "intrinsics": {"width": 1024, "height": 768}}, (1024, 768)),
        (
            {"name": "c", "width": 800, "height": 600, "intrinsics": {"width": 1, "height": 1}},
            (800, 600),
        ),
        ({"name": "c"}, (320, 240)),
        ({"name": "c", "width": True, "height": 480}, (320, 240)),
        ({"name": "c", "width": -640, "height": 480}, (320, 240)),
        ({"name": "c", "width": 640.0, "height": 480}, (320, 240)),
        ({"name": "c", "intrinsics": [640, 480]}, (320, 240)),
        ({"name": "other", "width": 640, "height": 480}, (320, 240)),
    ],
)
def test_requests_use_the_image_size_the_camera_declares(
    camera: dict[str, Any], expected: tuple[int, int]
) -> None:
    assert _context([camera]).image_size({"name": "i", "camera": "c"}) == expected


# ----------------------------------------------------------------------------- broken servers

Behaviour = Callable[[socket.socket], None]


@contextlib.contextmanager
def broken_server(behaviour: Behaviour) -> Iterator[int]:
    """A threaded TCP server that treats every connection with ``behaviour``."""

    class Handler(socketserver.BaseRequestHandler):
        def handle(self) -> None:
            self.request.settimeout(10.0)
            with contextlib.suppress(OSError):
                behaviour(self.request)

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


def _read_frame(sock: socket.socket, decoder: FrameDecoder) -> Any:
    while (frame := decoder.next_frame()) is None:
        data = sock.recv(65536)
        decoder.feed(data)
        if not data and decoder.next_frame() is None:
            return None
    return frame


def _garbage(sock: socket.socket) -> None:
    _read_frame(sock, FrameDecoder())
    sock.sendall(b"HTTP/1.1 400 Bad Request\r\n\r\n")


def _silent(sock: socket.socket) -> None:
    while sock.recv(65536):
        pass


def _welcome_then_silent(sock: socket.socket) -> None:
    decoder = FrameDecoder()
    hello = _read_frame(sock, decoder)
    if hello is None or hello.type != MessageType.HELLO:
        return
    welcome = Welcome(hello.request_id, (1, 0), "broken", "0", {"max_in_flight": 4})
    sock.sendall(welcome.to_frame((1, 0)).serialize())
    while sock.recv(65536):
        pass


def _conformance(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "protocol.conformance", f"127.0.0.1:{port}", *args],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )


@pytest.mark.parametrize("behaviour", [_garbage, _silent], ids=["garbage", "silent"])
def test_cli_fails_when_the_handshake_fails(behaviour: Behaviour) -> None:
    with broken_server(behaviour) as port:
        checked = _conformance(port, "--json", "--timeout", "0.5")
    assert checked.returncode == 2
    assert "cannot start" in checked.stderr
    assert checked.stdout == ""


def test_a_profile_does_not_pass_a_check_it_leaves_out() -> None:
    """The server only shakes hands: RELOAD gets no answer. Under the full profile that is a
    failure; under minimal the check is not run and not counted as passed."""
    with broken_server(_welcome_then_silent) as port:
        full = _conformance(port, "--json", "--timeout", "0.3", "-k", "reload")
        minimal = _conformance(port, "--json", "--profile", "minimal", "-k", "reload")
    assert full.returncode == 1, full.stderr
    assert [r["status"] for r in json.loads(full.stdout)["results"]] == ["fail"]
    assert minimal.returncode == 0, minimal.stderr
    report = json.loads(minimal.stdout)
    assert [r["status"] for r in report["results"]] == ["n/a"]
    assert report["passed"] == 0
    assert report["not_applicable"] == 1


def test_unknown_profile_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        conformance_main(["127.0.0.1:7878", "--profile", "tiny"])
    assert exited.value.code == 2
    assert "--profile" in capsys.readouterr().err


def test_cli_reports_failed_checks_of_a_server_that_only_shakes_hands() -> None:
    with broken_server(_welcome_then_silent) as port:
        checked = _conformance(port, "--json", "--timeout", "0.3", "-k", "ping")
    assert checked.returncode == 1, checked.stderr
    report = json.loads(checked.stdout)
    statuses = {r["name"]: r["status"] for r in report["results"]}
    assert statuses == {"ping_pong": "fail"}
    assert report["failed"] == 1
    assert report["passed"] == 0
    assert "no answer" in report["results"][0]["detail"]


def test_cli_fails_when_nothing_listens() -> None:
    holder = socket.socket()
    holder.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
    with holder:
        checked = _conformance(holder.getsockname()[1])
    assert checked.returncode == 2
    assert "cannot start" in checked.stderr


# ----------------------------------------------------------------------------- address


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("127.0.0.1:7000", ("127.0.0.1", 7000)),
        ("cell-3", ("cell-3", 7878)),
        (":7001", ("127.0.0.1", 7001)),
        ("[::1]:7002", ("::1", 7002)),
        ("[::1]", ("::1", 7878)),
        ("::1", ("::1", 7878)),
    ],
)
def test_address_forms(text: str, expected: tuple[str, int]) -> None:
    assert _address(text) == expected


@pytest.mark.parametrize("text", ["cell:port", "cell:0", "cell:70000", "[::1"])
def test_bad_address_is_a_usage_error(text: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        conformance_main([text])
    assert exited.value.code == 2
    assert "address" in capsys.readouterr().err
