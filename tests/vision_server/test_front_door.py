"""The front door (vision_server/service/door.py, frontends/listener.py, frontends/http_door.py):
connections counted per front-end and server-wide before TLS, stalled connections closed,
sign-in failures slowed down, and the console's Host and same-origin rules.

The console tests run the real server (``App`` with the console, as ``serve`` wires it) and
talk to it over loopback sockets as a browser, an attacker's page or a flood would."""

from __future__ import annotations

import asyncio
import contextlib
import json
import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from console_server import TOKEN, Browserless, RunningConsole, example_config, running_cell

from protocol import Busy, NotAuthenticated
from robot_client import ReconnectPolicy, SyncVisionClient
from vision_server.frontends.listener import Clock, Policy
from vision_server.service import FrontDoor, Pass, Refusal
from vision_server.service.door import AUTH_DELAY_MAX_S, AUTH_DELAY_MIN_S, AUTH_MEMORY_S

# ----------------------------------------------------------------------------- the door itself


def test_a_front_end_is_held_to_its_own_limit_and_all_to_the_total() -> None:
    door = FrontDoor(5)
    console = [door.enter("console", f"10.0.0.1:{n}", limit=3) for n in range(4)]
    assert all(isinstance(p, Pass) for p in console[:3])
    assert isinstance(console[3], Refusal)
    assert "console (3)" in console[3].reason
    binary = [door.enter("binary protocol", f"10.0.0.2:{n}", limit=64) for n in range(3)]
    assert isinstance(binary[0], Pass)
    assert isinstance(binary[1], Pass)
    assert isinstance(binary[2], Refusal)
    assert "5 in all" in binary[2].reason
    first = console[0]
    assert isinstance(first, Pass)
    first.leave()
    first.leave()  # twice is once
    assert door.connections == 4
    assert isinstance(door.enter("binary protocol", "10.0.0.2:9", limit=64), Pass)
    assert door.counts()["console"] == {"open": 2, "refused": 1}
    assert door.counts()["binary protocol"] == {"open": 3, "refused": 1}


def test_the_total_stays_below_the_descriptor_limit() -> None:
    from vision_server.service.door import DESCRIPTORS_KEPT, descriptor_limit

    assert FrontDoor(10**9).total == descriptor_limit() - DESCRIPTORS_KEPT


def test_failed_sign_ins_wait_longer_per_host_and_are_forgotten() -> None:
    now = [1000.0]
    door = FrontDoor(10, clock=lambda: now[0])
    delays = [door.auth_failed(f"192.0.2.7:{port}") for port in range(40000, 40010)]
    assert delays[0] == AUTH_DELAY_MIN_S
    assert delays[1] == 2 * AUTH_DELAY_MIN_S  # another port of the same host counts
    assert delays == sorted(delays)
    assert delays[-1] == AUTH_DELAY_MAX_S
    assert door.auth_failed("[2001:db8::1]:5000") == AUTH_DELAY_MIN_S  # another host
    now[0] += AUTH_MEMORY_S + 1
    assert door.auth_failed("192.0.2.7:40011") == AUTH_DELAY_MIN_S


def test_many_addresses_of_one_site_guess_as_one_and_a_flood_as_one() -> None:
    from vision_server.service.door import BUSY_FAILURES

    door = FrontDoor(10)
    assert door.auth_failed("[2001:db8:0:1::a]:1") == AUTH_DELAY_MIN_S
    assert door.auth_failed("[2001:db8:0:1::b]:1") == 2 * AUTH_DELAY_MIN_S  # the same /64
    assert door.auth_failed("[2001:db8:0:2::a]:1") == AUTH_DELAY_MIN_S  # another /64
    assert door.auth_failed("127.0.0.2:1") == AUTH_DELAY_MIN_S
    assert door.auth_failed("127.0.9.9:1") == 2 * AUTH_DELAY_MIN_S  # loopback is one host
    assert door.auth_failed("[::ffff:127.0.0.3]:1") == 4 * AUTH_DELAY_MIN_S
    delays = [door.auth_failed(f"10.0.{n >> 8}.{n & 255}:1") for n in range(BUSY_FAILURES)]
    assert delays[0] == AUTH_DELAY_MIN_S  # each a host of its own ...
    assert delays[-1] == AUTH_DELAY_MAX_S  # ... until failures come too fast from anywhere


def test_failing_hosts_are_bounded() -> None:
    from vision_server.service.door import MAX_HOSTS_REMEMBERED

    door = FrontDoor(10)
    for n in range(MAX_HOSTS_REMEMBERED + 50):
        door.auth_failed(f"10.{n >> 16 & 255}.{n >> 8 & 255}.{n & 255}:1")
    assert door.failing_hosts() == MAX_HOSTS_REMEMBERED


class _StuckTransport(asyncio.WriteTransport):
    """A transport whose client reads nothing: its write buffer never shrinks."""

    def __init__(self, buffered: int) -> None:
        super().__init__()
        self.buffered = buffered

    def get_write_buffer_size(self) -> int:
        return self.buffered


def test_a_connection_that_reads_nothing_is_overdue_after_the_write_timeout() -> None:
    policy = Policy("console", 8, request_timeout_s=5, idle_timeout_s=60, write_timeout_s=10)
    transport = _StuckTransport(4 << 20)
    clock = Clock(started=0.0, transport=transport)
    clock.begin()  # an answer being written: no request deadline meanwhile
    assert clock.overdue(policy, 1.0) is None
    assert clock.overdue(policy, 10.5) is None
    transport.buffered -= 1 << 20  # it read a little: the clock starts again
    assert clock.overdue(policy, 11.0) is None
    assert clock.overdue(policy, 20.0) is None
    assert "read nothing for 10 s" in (clock.overdue(policy, 21.5) or "")


def test_a_signed_out_connection_gets_the_request_timeout_a_signed_in_one_the_idle() -> None:
    policy = Policy("console", 8, request_timeout_s=5, idle_timeout_s=60, write_timeout_s=10)
    clock = Clock(started=0.0)
    clock.deadline = 5.0
    assert "no complete request within 5 s" in (clock.overdue(policy, 5.5) or "")
    clock.begin()
    clock.end(policy, 10.0)
    assert clock.overdue(policy, 14.0) is None
    assert "no complete request" in (clock.overdue(policy, 15.5) or "")
    clock.signed_in = True
    clock.begin()
    clock.end(policy, 20.0)
    assert clock.overdue(policy, 79.0) is None
    assert "idle for 60 s" in (clock.overdue(policy, 80.5) or "")


# ----------------------------------------------------------------------------- the real server

CONSOLE_KEYS = "  max_connections: 3\n  request_timeout_s: 1\n  allowed_hosts: [cell-pc.example]\n"


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    folder = tmp_path_factory.mktemp("door")
    config = example_config(folder)
    text = config.read_text(encoding="utf-8")
    config.write_text(text.replace("  max_view_fps: 30\n", "  max_view_fps: 30\n" + CONSOLE_KEYS))
    with running_cell(config) as running:
        yield running


def _address(cell: RunningConsole) -> tuple[str, int]:
    assert cell.app.http is not None
    return cell.app.http.address


def _closed_by_server(sock: socket.socket, within_s: float = 15.0) -> bool:
    """Whether the server closes ``sock`` (EOF or reset) within ``within_s``; what it sent
    before closing is ignored."""
    sock.settimeout(within_s)
    try:
        while sock.recv(65536):
            pass
        return True
    except (ConnectionResetError, BrokenPipeError):
        return True
    except TimeoutError:
        return False


def _open(cell: RunningConsole) -> socket.socket:
    return socket.create_connection(_address(cell), timeout=5)


def _refused_at_once(cell: RunningConsole) -> bool:
    """Whether a new console connection is closed (reset) as soon as it is made; the reset may
    already reach the connecting call."""
    try:
        sock = _open(cell)
    except ConnectionResetError:
        return True
    with sock:
        return _closed_by_server(sock, within_s=5)


def _wait_for(predicate: object, within_s: float = 10.0) -> bool:
    end = time.monotonic() + within_s
    while time.monotonic() < end:
        if predicate():  # type: ignore[operator]
            return True
        time.sleep(0.05)
    return False


def _robot(cell: RunningConsole, token: str = TOKEN) -> SyncVisionClient:
    """A robot's client of the binary protocol, without retries."""
    return SyncVisionClient(
        "127.0.0.1", cell.app.tcp.port, auth_token=token, reconnect=ReconnectPolicy(attempts=0)
    )


def test_silent_and_trickling_connections_are_closed_before_they_sign_in(
    cell: RunningConsole,
) -> None:
    silent = _open(cell)
    trickling = _open(cell)
    trickling.sendall(b"GET /api/server HTTP/1.1\r\nHost: 127.0.0.1\r\n")
    started = time.monotonic()
    for _ in range(20):  # a header byte every 0.2 s: it never completes the request in time
        try:
            trickling.sendall(b"X")
        except OSError:
            break
        time.sleep(0.2)
        if time.monotonic() - started > 4:
            break
    assert _closed_by_server(trickling)
    assert _closed_by_server(silent)
    silent.close()
    trickling.close()
    assert _wait_for(lambda: cell.app.service.door.held("console") == 0)


def test_console_connections_past_its_limit_are_closed_and_the_robot_is_served(
    tmp_path: Path,
) -> None:
    config = example_config(tmp_path)
    text = config.read_text(encoding="utf-8")
    config.write_text(
        text.replace(
            "  max_view_fps: 30\n",
            # the held connections must outlive a slow machine's test: a long request timeout
            "  max_view_fps: 30\n  max_connections: 3\n  request_timeout_s: 120\n",
        )
    )
    with running_cell(config) as cell:
        held = [_open(cell) for _ in range(3)]
        assert _wait_for(lambda: cell.app.service.door.held("console") == 3)
        assert _refused_at_once(cell)
        with _robot(cell) as robot:
            assert robot.ping() >= 0
        # The held ones were not touched: a browser on one of them is answered.
        held[0].sendall(b"GET /api/server HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert held[0].recv(12).startswith(b"HTTP/1.1 401")
        for sock in held:
            sock.close()
        counts = cell.app.service.door.counts()["console"]
        assert counts["refused"] >= 1


def test_the_server_wide_total_refuses_the_robot_politely_when_the_console_holds_it(
    tmp_path: Path,
) -> None:
    """The total is below the front-ends' own limits only when the descriptor limit lowered
    it (a configuration cannot ask for that); then the robot is refused politely."""
    with running_cell(example_config(tmp_path)) as cell:
        cell.app.service.door.total = 3  # as a descriptor limit of 131 would make it
        held = [_open(cell) for _ in range(3)]
        assert _wait_for(lambda: cell.app.service.door.connections == 3)
        with (
            pytest.raises(Busy, match="too many connections to the server"),
            _robot(cell) as robot,
        ):
            robot.ping()
        for sock in held:
            sock.close()
        assert _wait_for(lambda: cell.app.service.door.connections == 0)
        with _robot(cell) as robot:
            assert robot.ping() >= 0


def _raw(cell: RunningConsole, head: bytes, body: bytes = b"") -> tuple[int, bytes]:
    with _open(cell) as sock:
        sock.sendall(head + body)
        sock.settimeout(15)
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
        status = int(data.split(b" ", 2)[1]) if data.startswith(b"HTTP/") else 0
        return status, data


def test_sign_in_reads_a_small_body_in_time_or_refuses(cell: RunningConsole) -> None:
    status, data = _raw(
        cell,
        b"POST /api/login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Content-Length: 67108864\r\n\r\n",
    )
    assert status == 413, data
    status, data = _raw(
        cell,
        b"POST /api/login HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
        b"Content-Length: 40\r\n\r\n",
        b'{"token": ',  # and then nothing
    )
    assert status == 408, data
    assert b"did not arrive within 1 s" in data


def test_a_wrong_token_is_slowed_down_on_every_front_end(cell: RunningConsole) -> None:
    door = cell.app.service.door
    before = door.failing_hosts()
    client = Browserless(cell.url)
    assert client.login("wrong").status == 401
    assert door.failing_hosts() == before + 1  # loopback is now a failing host
    with pytest.raises(NotAuthenticated), _robot(cell, "wrong") as robot:
        robot.ping()
    assert client.login(TOKEN).status == 200  # the right token is never delayed


@pytest.mark.parametrize(
    ("host", "status"),
    [
        ("evil.example", 421),
        ("evil.example:80", 421),
        ("127.0.0.1", 401),  # answered (401: signed out)
        ("localhost", 401),
        ("[::1]:7880", 401),
        ("CELL-PC.example.", 401),  # allowed_hosts, any case, trailing dot
    ],
)
def test_the_console_answers_only_hosts_that_name_it(
    cell: RunningConsole, host: str, status: int
) -> None:
    got, data = _raw(cell, f"GET /api/server HTTP/1.1\r\nHost: {host}\r\n\r\n".encode())
    assert got == status, data


def _post(
    cell: RunningConsole, path: str, headers: dict[str, str], body: bytes = b"{}"
) -> tuple[int, bytes]:
    host, port = _address(cell)
    lines = [f"POST {path} HTTP/1.1", f"Host: {host}:{port}"]
    if "Content-Length" not in headers:
        lines.append(f"Content-Length: {len(body)}")
    lines += [f"{k}: {v}" for k, v in headers.items()]
    return _raw(cell, ("\r\n".join(lines) + "\r\n\r\n").encode(), body)


def test_changes_need_proof_that_the_consoles_own_page_sent_them(cell: RunningConsole) -> None:
    host, port = _address(cell)
    own = f"http://{host}:{port}"
    form = {"Content-Type": "multipart/form-data; boundary=zz"}
    as_json = {"Content-Type": "application/json"}
    refused = [
        _post(cell, "/api/logout", {**as_json, "Origin": "http://evil.example"}),
        _post(cell, "/api/logout", {**as_json, "Origin": "null"}),
        _post(cell, "/api/logout", {**as_json, "Origin": f"http://{host}:{port + 1}"}),
        _post(cell, "/api/inspections/magnet_check/try", form),  # what an HTML form can send
        _post(cell, "/api/logout", {"Content-Type": "text/plain"}),
    ]
    for status, data in refused:
        assert status == 403, data
        assert json.loads(data.split(b"\r\n\r\n", 1)[1] or b"{}") or b"CROSS_SITE" in data
    sign_in = json.dumps({"token": TOKEN}).encode()
    assert _post(cell, "/api/login", {**as_json, "Origin": own}, sign_in)[0] == 200
    assert _post(cell, "/api/login", as_json, sign_in)[0] == 200  # no Origin: not a browser's
    # The page's own header passes the proof (then the sign-in rule answers).
    status, _ = _post(
        cell, "/api/inspections/magnet_check/try", {**form, "X-Cellvision": "console"}
    )
    assert status == 401


def test_a_try_has_a_deadline(tmp_path: Path) -> None:
    """A try that cannot finish in time answers DEADLINE_EXCEEDED instead of running on."""
    config = example_config(tmp_path)
    text = config.read_text(encoding="utf-8")
    config.write_text(
        text.replace("  max_view_fps: 30\n", "  max_view_fps: 30\n  try_deadline_s: 0.000001\n")
    )
    with running_cell(config) as cell:
        client = Browserless(cell.url)
        assert client.login().status == 200
        reply = client.try_("magnet_check", {"source": "camera"})
        assert reply.status == 504, reply.body
        assert reply.json()["error"]["code"] == "DEADLINE_EXCEEDED"


# ----------------------------------------------------------------------------- line protocol

LINE_CELL = """\
server: {port: 0, auth_token: line-door-token, handshake_timeout_s: 1}
results: {enabled: false}
cameras:
  shelf: {source: folder, path: imgs}
inspections:
  - name: bright
    type: presence
    camera: shelf
    measure: mean_intensity
    min: 10
line: {enabled: true, port: 0, max_connections: 2, write_timeout_s: 1}
console: {enabled: true, port: 0}
"""


@pytest.fixture
def line_cell(tmp_path: Path) -> Iterator[RunningConsole]:
    import cv2
    import numpy as np

    (tmp_path / "imgs").mkdir()
    cv2.imwrite(str(tmp_path / "imgs" / "a.png"), np.full((48, 64), 100, np.uint8))
    config = tmp_path / "cell.yaml"
    config.write_text(LINE_CELL, encoding="utf-8")
    with running_cell(config) as running:
        yield running


def _line(cell: RunningConsole) -> socket.socket:
    assert cell.app.line is not None
    return socket.create_connection(("127.0.0.1", cell.app.line.port), timeout=5)


def test_lines_before_the_token_do_not_keep_a_controller_connection(
    line_cell: RunningConsole,
) -> None:
    """Blank, wrong and over-long lines before ``A <token>`` do not move its deadline: the
    connection is closed about ``handshake_timeout_s`` (1 s) after it was made, with
    ``ER 8 no A <token> ...`` (unless the close overtook that line), while lines keep coming."""
    sock = _line(line_cell)
    answers = b""
    closed = False
    started = time.monotonic()
    sock.settimeout(0.2)
    while not closed and time.monotonic() - started < 20:
        try:
            sock.sendall(b"\r\n" if int(time.monotonic() * 5) % 2 else b"X" * 300 + b"\n")
            chunk = sock.recv(4096)
        except TimeoutError:
            continue
        except OSError:  # reset: the server closed while lines were still coming
            closed = True
            break
        answers += chunk
        closed = not chunk
    assert closed, answers
    assert b"OK" not in answers
    if b"no A" in answers:
        assert b"ER 8 no A <token> within 1 s; closing" in answers
    sock.close()
    assert _wait_for(lambda: line_cell.app.service.door.held("line protocol") == 0)


def test_a_controller_past_the_limit_is_told_and_closed_at_once(line_cell: RunningConsole) -> None:
    held = [_line(line_cell) for _ in range(2)]
    for sock in held:
        sock.sendall(b"A line-door-token\n")
        assert sock.recv(64).startswith(b"OK")
    extra = _line(line_cell)
    extra.settimeout(5)
    assert extra.recv(256).startswith(b"ER 20 too many connections to the line protocol (2)")
    assert _closed_by_server(extra, within_s=5)
    for sock in [*held, extra]:
        sock.close()


def test_a_controller_that_stops_reading_is_dropped_at_the_write_timeout(
    line_cell: RunningConsole,
) -> None:
    """It sent many requests and then went quiet without reading: its answers fill the
    sockets' buffers, and the server drops it after ``write_timeout_s`` (1 s here) instead of
    holding them until the idle timeout (300 s)."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    assert line_cell.app.line is not None
    sock.connect(("127.0.0.1", line_cell.app.line.port))
    sock.sendall(b"A line-door-token\n")
    # About 17 KB of answers: more than this socket's receive buffer holds, less than makes
    # the server wait for it to read (it answers them all, then waits for the next line).
    sock.sendall(b"L\n" * 1000)
    assert _wait_for(lambda: line_cell.app.service.door.held("line protocol") == 0, 30)
    sock.close()


# ----------------------------------------------------------------------------- tries


def test_tries_learn_their_own_cost_in_a_lane_of_their_own(cell: RunningConsole) -> None:
    client = Browserless(cell.url)
    assert client.login().status == 200
    assert client.try_("magnet_check", {"source": "camera"}).status == 200
    pool = cell.app.service.pool
    costs = pool.costs.snapshot()
    assert "try:magnet_check" in costs
    assert "magnet_check" not in costs  # production's estimate is not taught by a try
    assert pool.tries.name == "try"
    assert pool.tries not in pool.lanes


def test_tries_hold_at_most_their_share_of_the_byte_budget(tmp_path: Path) -> None:
    """A try whose body would take more than half of the budget is BUSY before it is read;
    production keeps the rest."""
    config = example_config(
        tmp_path, extra_server="  max_buffered_bytes: 4194304\n  max_frame_bytes: 4194304\n"
    )
    with running_cell(config) as cell:
        client = Browserless(cell.url)
        assert client.login().status == 200
        cookie = "; ".join(f"{c.name}={c.value}" for c in client.jar)
        status, data = _post(
            cell,
            "/api/inspections/magnet_check/try",
            {
                "Content-Type": "multipart/form-data; boundary=zz",
                "X-Cellvision": "console",
                "Cookie": cookie,
                "Content-Length": str(3 << 20),
            },
            b"",
        )
        assert status == 503, data
        assert b"tries' request bodies" in data
        assert cell.app.service.budget.used == 0


def test_a_stalled_upload_gives_its_bytes_back(cell: RunningConsole) -> None:
    client = Browserless(cell.url)
    assert client.login().status == 200
    cookie = "; ".join(f"{c.name}={c.value}" for c in client.jar)
    host, port = _address(cell)
    head = (
        f"POST /api/inspections/magnet_check/try HTTP/1.1\r\nHost: {host}:{port}\r\n"
        f"Content-Type: multipart/form-data; boundary=zz\r\nX-Cellvision: console\r\n"
        f"Cookie: {cookie}\r\nContent-Length: {1 << 20}\r\n\r\n"
    ).encode()
    with _open(cell) as sock:
        sock.sendall(head + b"--zz\r\n")  # and then nothing: the upload stalls
        assert _wait_for(lambda: cell.app.service.budget.used > 0, 5)
        sock.settimeout(20)
        answer = sock.recv(4096)
    assert answer.startswith(b"HTTP/1.1 408"), answer
    assert b"did not arrive within" in answer
    assert _wait_for(lambda: cell.app.service.budget.used == 0, 5)


def test_modbus_counts_at_the_front_door(tmp_path: Path) -> None:
    """Modbus connections are counted with the others: when the console holds the server's
    total, a PLC's connection is closed at once and counted as refused."""
    config = example_config(tmp_path)
    text = config.read_text(encoding="utf-8")
    config.write_text(text + "\nmodbus: {enabled: true, port: 0}\n", encoding="utf-8")
    with running_cell(config) as cell:
        cell.app.service.door.total = 3  # as a descriptor limit of 131 would make it
        assert cell.app.modbus is not None
        plc = socket.create_connection(("127.0.0.1", cell.app.modbus.port), timeout=5)
        assert _wait_for(lambda: cell.app.service.door.held("Modbus") == 1)
        held = [_open(cell) for _ in range(2)]
        assert _wait_for(lambda: cell.app.service.door.connections == 3)
        late = socket.create_connection(("127.0.0.1", cell.app.modbus.port), timeout=5)
        assert _closed_by_server(late, within_s=5)
        assert cell.app.service.door.counts()["Modbus"]["refused"] == 1
        for sock in [plc, *held, late]:
            sock.close()
        assert _wait_for(lambda: cell.app.service.door.connections == 0)


# ----------------------------------------------------------------------------- roles

OPERATOR, INTEGRATOR = "operator-tablet-token-1", "integrator-laptop-token-2"


@pytest.fixture(scope="module")
def roles(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningConsole]:
    folder = tmp_path_factory.mktemp("roles")
    config = example_config(
        folder, extra_server=f"  operator_token: {OPERATOR}\n  integrator_token: {INTEGRATOR}\n"
    )
    with running_cell(config) as running:
        yield running


def _signed_in(cell: RunningConsole, token: str) -> Browserless:
    client = Browserless(cell.url)
    reply = client.login(token)
    assert reply.status == 200, reply.body
    return client


def test_the_operator_views_and_cannot_try_or_save(roles: RunningConsole) -> None:
    operator = _signed_in(roles, OPERATOR)
    assert operator.get("/api/server").json()["role"] == "operator"
    assert operator.get("/api/inspections").status == 200
    assert operator.get("/api/results").status == 200
    tried = operator.try_("magnet_check", {"source": "camera"})
    assert tried.status == 403
    assert "integrator" in tried.json()["error"]["message"]
    saved = operator.post_json("/api/inspections/magnet_check/save", {"options": {"threshold": 1}})
    assert saved.status == 403
    assert saved.json()["error"]["code"] == "FORBIDDEN"
    assert "threshold: 1" not in roles.config.read_text(encoding="utf-8")


@pytest.mark.parametrize("token", [INTEGRATOR, TOKEN])
def test_the_integrator_and_the_admin_try(roles: RunningConsole, token: str) -> None:
    client = _signed_in(roles, token)
    assert client.get("/api/server").json()["role"] == ("admin" if token == TOKEN else "integrator")
    assert client.try_("magnet_check", {"source": "camera"}).status == 200


def test_the_robot_protocols_take_only_the_admins_token(roles: RunningConsole) -> None:
    with pytest.raises(NotAuthenticated), _robot(roles, OPERATOR) as robot:
        robot.ping()
    with _robot(roles) as robot:
        assert robot.ping() >= 0


def test_roles_need_tokens_of_their_own(tmp_path: Path) -> None:
    from vision_server.config import ConfigError, load_config

    config = example_config(tmp_path, extra_server=f"  operator_token: {TOKEN}\n")
    with pytest.raises(ConfigError, match="operator_token: each role needs a token of its own"):
        load_config(config)


def test_the_total_must_hold_every_enabled_front_ends_own_limit(tmp_path: Path) -> None:
    """Else a flood of the others could take the places the robot's front-end was promised."""
    from vision_server.config import ConfigError, load_config

    config = example_config(tmp_path, extra_server="  max_connections_total: 100\n")
    with pytest.raises(ConfigError, match=r"server -> max_connections_total: 100 is less than"):
        load_config(config)
    assert "console.max_connections 64" in str(
        pytest.raises(ConfigError, load_config, config).value
    )


def test_sign_in_bodies_that_break_parsers_are_refused_not_crashes(cell: RunningConsole) -> None:
    nested = b"[" * 2000 + b"]" * 2000
    status, data = _post(cell, "/api/login", {"Content-Type": "application/json"}, nested)
    assert status == 400, data
    # A lone surrogate is no text at all (no file, log or database can write it): refused
    # as such on every path, before any handler keeps it (docs/console.md, "Authentication").
    lone = b'{"token": "\\ud800"}'
    status, data = _post(cell, "/api/login", {"Content-Type": "application/json"}, lone)
    assert status == 400, data
    assert b"not valid Unicode" in data


def test_two_origins_or_a_host_with_a_name_for_a_port_are_refused(cell: RunningConsole) -> None:
    host, port = _address(cell)
    own = f"http://{host}:{port}"
    head = (
        f"POST /api/logout HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n"
        f"Origin: {own}\r\nOrigin: http://evil.example\r\nContent-Length: 2\r\n\r\n{{}}"
    )
    assert _raw(cell, head.encode())[0] == 403
    got, _ = _raw(cell, f"GET /api/server HTTP/1.1\r\nHost: {host}:{port}.evil\r\n\r\n".encode())
    assert got == 421


def test_one_roles_sign_ins_do_not_end_anothers_sessions() -> None:
    from vision_server.frontends.http_auth import MAX_SESSIONS, Sessions

    sessions = Sessions({"admin": "a-token", "operator": "o-token"})
    admin = sessions.open("admin")
    for _ in range(MAX_SESSIONS + 10):
        sessions.open("operator")
    assert sessions.role(admin) == "admin"


def test_a_flood_of_unparsable_http_is_logged_once_not_per_connection(
    cell: RunningConsole, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level("DEBUG", logger="vision_server.console.http")
    for _ in range(30):
        with _open(cell) as sock:
            sock.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX: " + b"a" * 20000 + b"\r\n\r\n")
            sock.settimeout(10)
            with contextlib.suppress(OSError):
                assert sock.recv(12).endswith(b" 400")
    records = [r for r in caplog.records if r.name == "vision_server.console.http"]
    assert 1 <= len(records) <= 4  # once per 10 s, however many connections
    assert all(r.exc_info is None for r in records)
