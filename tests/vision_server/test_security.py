"""Security of the server (issue #8, item 4): where it listens, TLS, authentication, limits,
path confinement, YAML.

Path audit (every place a path could come from a message): INSPECT's ``inspection`` and
CAPTURE's ``camera`` are looked up by name in the catalog (never joined to a path); INSPECT's
``options`` are not used by the server; images travel as blobs and are decoded in memory; the
result log makes its image file names itself (``<date>/<uuid>.png``) and stores the client's
strings (peer, names from the catalog) as SQL parameters; camera and template paths, the token
file and TLS files come from the configuration file only, and RELOAD re-reads the file the server
was started with. The test below checks this from the outside with Python's audit hooks.
"""

from __future__ import annotations

import ast
import asyncio
import contextlib
import importlib
import json
import os
import signal
import socket
import ssl
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from certs import self_signed

from protocol import (
    Capture,
    ErrorCode,
    FrameDecoder,
    Hello,
    ImageEncoding,
    ImagePayload,
    Inspect,
    ListInspections,
    MessageType,
    Ping,
    Reload,
    payload_from_array,
)
from protocol.conformance import Target
from protocol.conformance.peer import CLOSED, Peer
from robot_client.client import ReconnectPolicy, VisionClient
from robot_client.errors import ConnectionLost
from vision_server.commands.program import build_parser
from vision_server.config import ConfigError, load_config
from vision_server.server import ServerSettings, VisionServer
from vision_server.service import builtin_catalog

REPO_ROOT = Path(__file__).resolve().parents[2]
GRAY = np.full((48, 64), 200, np.uint8)


@contextlib.contextmanager
def server_in_thread(**settings: Any) -> Iterator[VisionServer]:
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="test-server", daemon=True)
    thread.start()
    server = VisionServer(builtin_catalog(), ServerSettings(port=0, **settings))
    runs: list[int] = []
    server.service.subscribe(lambda record: runs.append(record.request.request_id))
    server.runs = runs  # type: ignore[attr-defined]
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(10.0)
        yield server
    finally:
        with contextlib.suppress(RuntimeError):
            asyncio.run_coroutine_threadsafe(server.stop(), loop).result(30.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        loop.close()


def peer_for(server: VisionServer) -> Peer:
    return Peer(Target("127.0.0.1", server.port, timeout_s=10.0))


# ----------------------------------------------------------------------------- listening


def test_the_server_listens_on_loopback_unless_told_otherwise(tmp_path: Path) -> None:
    assert ServerSettings().host == "127.0.0.1"
    config = tmp_path / "cell.yaml"
    config.write_text("cameras: {tool: {source: request}}\ninspections: []\n")
    assert load_config(config).server.host == "127.0.0.1"
    assert build_parser().parse_args(["serve"]).host is None  # the configuration decides

    async def bound_address() -> str:
        async with VisionServer(builtin_catalog(), ServerSettings(port=0)) as server:
            return server.tcp.address[0]

    assert asyncio.run(bound_address()) == "127.0.0.1"
    # Only the container listens on every interface, and says so on its command line.
    dockerfile = (REPO_ROOT / "Dockerfile").read_text()
    cmd = next(line for line in dockerfile.splitlines() if line.startswith("CMD"))
    assert '"--host", "0.0.0.0"' in cmd
    assert "host: 127.0.0.1" in (REPO_ROOT / "examples/cell.yaml").read_text()


# ----------------------------------------------------------------------------- TLS


def test_tls_from_the_configuration_file(tmp_path: Path) -> None:
    cert, key = self_signed(tmp_path)
    config = tmp_path / "cell.yaml"
    config.write_text(
        "server: {port: 0, tls: {cert: cert.pem, key: key.pem}}\n"
        "results: {enabled: false}\n"
        "cameras: {tool: {source: request}}\n"
        "inspections:\n"
        "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}\n"
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "vision_server", "serve", "--config", str(config)],
        cwd=REPO_ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert "listening on 127.0.0.1:" in line, proc.stderr.read() if proc.stderr else ""
        port = int(line.rsplit(":", 1)[1])

        async def body() -> None:
            trusted = ssl.create_default_context(cafile=str(cert))
            async with VisionClient("127.0.0.1", port, ssl=trusted) as client:
                assert await client.ping() >= 0.0
                result = await client.inspect("bright", GRAY)
                assert result.data["value"] == 200.0
            # A client that does not trust the certificate does not get in.
            with pytest.raises(ConnectionLost):
                await VisionClient(
                    "127.0.0.1",
                    port,
                    ssl=ssl.create_default_context(),
                    reconnect=ReconnectPolicy(attempts=0),
                ).connect()
            # Plain TCP gets no WELCOME: the server speaks only TLS.
            plain = VisionClient(
                "127.0.0.1", port, connect_timeout_s=10.0, reconnect=ReconnectPolicy(attempts=0)
            )
            with pytest.raises(ConnectionLost):
                await plain.connect()

        asyncio.run(body())
        # The conformance suite over TLS, verifying the certificate (given as the CA).
        suite = subprocess.run(
            [sys.executable, "-m", "protocol.conformance", f"127.0.0.1:{port}", "--tls"],
            cwd=REPO_ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            env={**os.environ, "SSL_CERT_FILE": str(cert)},
            check=False,
        )
        assert suite.returncode == 0, suite.stdout + suite.stderr
        assert " 0 failed" in suite.stdout
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            assert proc.wait(timeout=30) == 0
        finally:
            if proc.poll() is None:
                proc.kill()
            proc.communicate(timeout=30)


# ----------------------------------------------------------------------------- authentication


@pytest.mark.parametrize("token", [None, "s3cret"], ids=["no-token", "token"])
@pytest.mark.parametrize(
    "request_",
    [
        Ping(3),
        ListInspections(3),
        Inspect(3, "brightness", (payload_from_array(GRAY),)),
        Capture(3, "tool"),
        Reload(3),
    ],
    ids=lambda m: type(m).__name__,
)
def test_requests_before_hello_are_not_authenticated_and_close(
    token: str | None, request_: Any
) -> None:
    with server_in_thread(auth_token=token) as server, peer_for(server) as peer:
        peer.send(request_)
        error = peer.expect_error(ErrorCode.NOT_AUTHENTICATED, fatal=True)
        assert error.request_id == 3
        assert peer.recv_frame() is CLOSED
        assert server.runs == []  # type: ignore[attr-defined]


@pytest.mark.parametrize("given", [None, "", "wrong", "s3cret ", "S3CRET", "s3cre", "s3crét"])
def test_a_wrong_token_is_refused_and_what_follows_it_is_never_run(given: str | None) -> None:
    image = (payload_from_array(GRAY),)
    with server_in_thread(auth_token="s3cret") as server, peer_for(server) as peer:
        # The HELLO and an INSPECT pipelined behind it in one write.
        peer.send_raw(
            Hello(1, ((1, 0),), "intruder", given).to_frame((1, 0)).serialize()
            + Inspect(2, "brightness", image).to_frame((1, 0)).serialize()
        )
        error = peer.expect_error(ErrorCode.NOT_AUTHENTICATED, fatal=True)
        assert error.request_id == 1
        assert peer.recv_frame() is CLOSED
        assert server.runs == []  # type: ignore[attr-defined]
        with peer_for(server) as good:
            good.send(Hello(1, ((1, 0),), "robot", "s3cret"))
            good.expect(MessageType.WELCOME, request_id=1)
            good.send(Inspect(2, "brightness", image))
            good.expect(MessageType.RESULT, request_id=2)


def test_the_token_is_compared_in_constant_time() -> None:
    source = (REPO_ROOT / "vision_server/frontends/tcp.py").read_text()
    assert "hmac.compare_digest(" in source
    tree = ast.parse(source)
    for node in ast.walk(tree):  # no == / != on the token anywhere
        if isinstance(node, ast.Compare) and any(
            "auth_token" in ast.unparse(side) or ast.unparse(side) == "expected"
            for side in (node.left, *node.comparators)
        ):
            assert all(isinstance(op, ast.Is | ast.IsNot) for op in node.ops), ast.unparse(node)


# ----------------------------------------------------------------------------- limits


def test_frame_and_pixel_limits_are_enforced_before_the_data_is_used() -> None:
    with server_in_thread(max_frame_bytes=4096, max_image_pixels=1000) as server:
        with peer_for(server) as peer:
            peer.handshake()
            welcome_limits = {"max_frame_bytes": 4096, "max_image_pixels": 1000}
            # A header announcing 1 MiB: refused at once, without sending (or reading) the body.
            header = bytearray(Ping(2, "x").to_frame((1, 0)).serialize()[:24])
            header[20:24] = (1 << 20).to_bytes(4, "little")
            peer.send_raw(bytes(header))
            peer.expect_error(ErrorCode.FRAME_TOO_LARGE, fatal=True)
            assert peer.recv_frame() is CLOSED
        with peer_for(server) as peer:
            welcome = peer.handshake()
            assert welcome_limits.items() <= welcome.metadata["limits"].items()
            big_raw = payload_from_array(np.zeros((40, 40), np.uint8))  # 1600 pixels
            peer.send(Inspect(2, "brightness", (big_raw,)))
            error = peer.expect_error(ErrorCode.IMAGE_TOO_LARGE, request_id=2)
            assert error.metadata["details"]["pixels"] == 1600
            # A tiny PNG whose header announces 100,000 x 100,000 pixels: refused unopened.
            png = bytearray(cv2.imencode(".png", np.zeros((2, 2), np.uint8))[1].tobytes())
            png[16:24] = (100_000).to_bytes(4, "big") * 2
            bomb = ImagePayload(ImageEncoding.PNG, 0, 0, bytes(png))
            peer.send(Inspect(3, "brightness", (bomb,)))
            error = peer.expect_error(ErrorCode.IMAGE_TOO_LARGE, request_id=3)
            assert error.metadata["details"]["pixels"] == 10_000_000_000
            peer.send(Ping(4, "alive"))
            peer.expect(MessageType.PONG, request_id=4)


# ----------------------------------------------------------------------------- paths

AUDITED_SERVER = """
import json, os, sys, time
log = open(sys.argv[2], "a", buffering=1)
WATCHED = {"open", "os.remove", "os.rename", "os.mkdir", "os.rmdir", "os.symlink", "os.link",
           "os.truncate", "os.chmod", "os.listdir", "os.scandir", "shutil.rmtree",
           "sqlite3.connect", "os.chdir", "subprocess.Popen", "os.system", "os.exec"}

def hook(event, args):
    if event in WATCHED:
        target = args[0] if args else ""
        if isinstance(target, (str, bytes, os.PathLike)):
            log.write(json.dumps([time.time(), event, os.fsdecode(target)]) + "\\n")
        elif event not in ("open",):
            log.write(json.dumps([time.time(), event, repr(target)]) + "\\n")

sys.addaudithook(hook)
from vision_server.commands.program import main
sys.exit(main(["serve", "--config", sys.argv[1], "--port", "0"]))
"""

HOSTILE_NAMES = [
    "../outside/secret.png",
    "../../../../../../etc/passwd",
    "/etc/passwd",
    "frames/../../outside/secret.png",
    "..",
    ".",
    "~/secret",
    "/dev/zero",
    "%2e%2e%2foutside",
    "..\\..\\outside",
    "bright\x00../../outside",
    "results.sqlite3",
    "x" * 100_000,
]


def test_no_message_makes_the_server_touch_a_path_outside_its_directories(
    tmp_path: Path,
) -> None:
    cfg, data, frames, outside = (tmp_path / d for d in ("cfg", "data", "frames", "outside"))
    for d in (cfg, data, frames, outside):
        d.mkdir()
    cv2.imwrite(str(frames / "f0.png"), GRAY)
    cv2.imwrite(str(outside / "secret.png"), GRAY)
    config = cfg / "cell.yaml"
    config.write_text(
        "server: {port: 0, allow_reload: true}\n"
        f"results: {{path: {data / 'results.sqlite3'}, store_images: all}}\n"
        f"cameras: {{tool: {{source: request}}, replay: {{source: folder, path: {frames}}}}}\n"
        "inspections:\n"
        "  - {name: bright, type: presence, camera: tool, measure: mean_intensity, min: 0}\n"
        "  - {name: dim, type: presence, camera: tool, measure: mean_intensity, max: 10}\n"
        "  - {name: replayed, type: presence, camera: replay, measure: mean_intensity, min: 0}\n"
    )
    events = tmp_path / "events.jsonl"
    proc = subprocess.Popen(
        [sys.executable, "-c", AUDITED_SERVER, str(config), str(events)],
        cwd=outside,  # even relative to its working directory nothing may be touched
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO_ROOT)},
    )
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline().rsplit(":", 1)[1])
        image = (payload_from_array(GRAY),)
        png = (payload_from_array(GRAY, encoding=ImageEncoding.PNG),)

        def session(messages: list[Any]) -> list[tuple[int, Any]]:
            with Peer(Target("127.0.0.1", port, timeout_s=20.0)) as peer:
                peer.handshake()
                answers = []
                for message in messages:
                    peer.send(message)
                    frame = peer.recv_frame()
                    assert frame is not CLOSED
                    answers.append((frame.type, frame.metadata.get("code")))  # type: ignore[attr-defined]
                return answers

        # Warm-up: every kind of work once, so that lazy imports and the log's files are done.
        session(
            [
                Inspect(2, "bright", image, overlay=True),
                Inspect(3, "dim", png),
                Inspect(4, "replayed"),
                Capture(5, "replay", 2),
                Capture(6, "replay", 1, False, "png"),
                ListInspections(7),
                Reload(8),
            ]
        )
        started = time.time()
        rid = 10
        hostile: list[Any] = []
        for name in HOSTILE_NAMES:
            options = {"path": name, "template": name, "image": name, "file": name, "dir": name}
            hostile += [
                Inspect(rid, name, image),
                Inspect(rid + 1, name),
                Capture(rid + 2, name),
                Inspect(rid + 3, "bright", image, options=options),
                Inspect(rid + 4, "dim", image, options=options),
                Inspect(rid + 5, "dim", image),  # fails: its image goes to the result log
            ]
            rid += 6
        answers = session(hostile)
        ended = time.time()
        codes = {code for _, code in answers}
        # Options that name files are refused (INVALID_ARGUMENT), never opened.
        assert codes <= {
            None,
            ErrorCode.UNKNOWN_INSPECTION,
            ErrorCode.UNKNOWN_CAMERA,
            ErrorCode.INVALID_ARGUMENT,
        }
        assert {t for t, _ in answers} <= {MessageType.RESULT, MessageType.ERROR}
        with Peer(Target("127.0.0.1", port, timeout_s=20.0)) as peer:
            peer.send_raw(Hello(1, ((1, 0),), "../../outside/evil").to_frame((1, 0)).serialize())
            peer.expect(MessageType.WELCOME, request_id=1)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    allowed = (data.resolve(), frames.resolve())
    touched = []
    for line in events.read_text().splitlines():
        when, event, target = json.loads(line)
        if not started <= when <= ended:
            continue
        path = Path(target)
        if not path.is_absolute():
            path = outside / path
        if not any(path.resolve().is_relative_to(d) for d in allowed):
            touched.append((event, target))
    assert touched == []
    # The hook did see the server at work in the window: the result log's image files.
    assert any(
        started <= json.loads(line)[0] <= ended and str(data) in json.loads(line)[2]
        for line in events.read_text().splitlines()
    )
    assert sorted(p.name for p in outside.iterdir()) == ["secret.png"]
    assert sorted(p.name for p in cfg.iterdir()) == ["cell.yaml"]


# ----------------------------------------------------------------------------- YAML

UNSAFE_CALLS = {"unsafe_load", "unsafe_load_all", "full_load", "full_load_all"}
UNSAFE_LOADERS = {"Loader", "UnsafeLoader", "FullLoader"}


def _python_files() -> Iterator[Path]:
    for package in (
        "protocol",
        "vision_server",
        "robot_client",
        "simulation",
        "geometry",
        "yamlfile",
    ):
        yield from (REPO_ROOT / package).rglob("*.py")
    yield from (REPO_ROOT / "bench").rglob("*.py")
    yield from (REPO_ROOT / "scripts").rglob("*.py")


def test_yaml_is_only_read_with_safe_loaders() -> None:
    """Every yaml.load/load_all/compose call names a SafeLoader subclass; no unsafe helpers."""
    checked = 0
    for path in _python_files():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Attribute):
                continue
            if not (isinstance(node.func.value, ast.Name) and node.func.value.id == "yaml"):
                continue
            where = f"{path.relative_to(REPO_ROOT)}:{node.lineno}"
            assert node.func.attr not in UNSAFE_CALLS, where
            if node.func.attr in ("load", "load_all", "compose", "compose_all", "parse"):
                loaders = [k.value for k in node.keywords if k.arg == "Loader"]
                loaders += node.args[1:2]
                assert loaders, f"{where}: yaml.{node.func.attr} without a Loader"
                loader = loaders[0]
                text = ast.unparse(loader)
                assert text.split(".")[-1] not in UNSAFE_LOADERS, where
                module_name = ".".join(path.relative_to(REPO_ROOT).with_suffix("").parts)
                module = importlib.import_module(module_name)
                resolved = (
                    getattr(yaml, text.split(".", 1)[1])
                    if text.startswith("yaml.")
                    else (getattr(module, text))
                )
                assert issubclass(resolved, yaml.SafeLoader), f"{where}: {text}"
                checked += 1
    assert checked >= 1  # the configuration reader's strict SafeLoader


def test_yaml_tags_that_run_code_are_refused(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    payloads = [
        f"!!python/object/apply:os.mkdir [{marker}]",
        f"server: !!python/object/apply:os.mkdir [{marker}]",
        "server: !!python/name:os.system",
        "server: !!python/object:collections.OrderedDict {}",
    ]
    for text in payloads:
        config = tmp_path / "cell.yaml"
        config.write_text(text + "\n")
        with pytest.raises(ConfigError):
            load_config(config)
    from robot_client.tasks import task_from_text
    from simulation._yaml import parse_yaml

    for loader in (task_from_text, parse_yaml):
        with pytest.raises(Exception):  # noqa: B017, PT011 - each reader has its own error class
            loader(f"!!python/object/apply:os.mkdir [{marker}]\n")
    assert not marker.exists()


def test_silent_connections_cannot_hold_every_connection_slot() -> None:
    """Connections that never send HELLO are closed after ``handshake_timeout_s``; otherwise
    ``max_connections`` of them would lock every robot out of the cell."""
    with server_in_thread(max_connections=3, handshake_timeout_s=0.5) as server:
        silent = [socket.create_connection(("127.0.0.1", server.port)) for _ in range(3)]
        try:
            for sock in silent:
                sock.settimeout(20.0)
                decoder = FrameDecoder()
                data = sock.recv(65536)
                while data:
                    decoder.feed(data)
                    data = sock.recv(65536)
                decoder.feed(b"")
                close = decoder.next_frame()
                assert close is not None
                assert close.type == MessageType.CLOSE
                assert "HELLO" in close.metadata["reason"]
            with peer_for(server) as peer:
                peer.handshake()
                peer.send(Ping(2))
                peer.expect(MessageType.PONG, request_id=2)
        finally:
            for sock in silent:
                sock.close()
