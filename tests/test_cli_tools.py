"""The two command-line tools as a user runs them (subprocesses), against ``vision-server serve``
processes: one rule to find and reach a server (issue 14 point 4), a secured server (TLS and a
token) reached by both tools and by the container's health check (point 5), one exit-code table
and one JSON shape for results and errors (point 6)."""

from __future__ import annotations

import json
import re
import shlex
import socket
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from certs import self_signed
from cli_tools import INSPECTIONS, REPO_ROOT, TOOLS, Server, _serve, tool


@pytest.fixture(scope="module")
def plain(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server on loopback without token or TLS, that allows RELOAD."""
    directory = tmp_path_factory.mktemp("plain")
    config = directory / "cell.yaml"
    config.write_text(
        "server: {port: 0, allow_reload: true}\nresults: {enabled: false}\n" + INSPECTIONS
    )
    yield from _serve(config)


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server with TLS (a self-signed certificate for 127.0.0.1) and a token file."""
    directory = tmp_path_factory.mktemp("secured")
    cert, _ = self_signed(directory)
    token_file = directory / "token"
    token_file.write_text("correct-horse-battery\n")
    config = directory / "cell.yaml"
    config.write_text(
        "server:\n  port: 0\n  allow_reload: true\n  auth_token_file: token\n"
        "  tls: {cert: cert.pem, key: key.pem}\n"
        "results: {enabled: false}\n" + INSPECTIONS
    )
    for server in _serve(config):
        yield Server(server.address, config, token_file, cert)


@pytest.fixture(scope="module")
def images(tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    directory = tmp_path_factory.mktemp("images")
    out = {}
    for name, level in (("bright", 200), ("dark", 10)):
        path = directory / f"{name}.png"
        cv2.imwrite(str(path), np.full((32, 32), level, np.uint8))
        out[name] = str(path)
    return out


def _dead_address() -> Iterator[str]:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
        yield f"127.0.0.1:{holder.getsockname()[1]}"


@pytest.fixture
def dead() -> Iterator[str]:
    yield from _dead_address()


PING = {"vision-server": ["ping"], "robot-client": ["ping"]}


# ----------------------------------------------------------------------------- point 4


@pytest.mark.parametrize(
    "command",
    [
        ["vision-server", "ping"],
        ["vision-server", "reload"],
        ["robot-client", "ping"],
        ["robot-client", "inspections"],
    ],
)
def test_the_server_address_comes_from_the_environment(command: list[str], plain: Server) -> None:
    """``vision-server ping|reload`` ignored $CELLVISION_SERVER (a reload went elsewhere)."""
    done = tool(command[0], *command[1:], "--json", CELLVISION_SERVER=plain.address)
    assert done.returncode == 0, done.stdout + done.stderr
    answer = json.loads(done.stdout)
    if command[0] == "vision-server":
        assert answer["server"] == plain.address
    if command[1] == "reload":
        assert answer["inspections"] == ["bright"]


@pytest.mark.parametrize("name", sorted(TOOLS))
@pytest.mark.parametrize("where", ["before", "after"])
def test_options_come_before_or_after_the_command(name: str, where: str, plain: Server) -> None:
    options = ["--server", plain.address, "--timeout", "20"]
    args = [*options, "ping"] if where == "before" else ["ping", *options]
    done = tool(name, *args)
    assert done.returncode == 0, done.stderr


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_the_command_line_beats_the_environment(name: str, plain: Server, dead: str) -> None:
    done = tool(name, "ping", "--server", plain.address, CELLVISION_SERVER=dead)
    assert done.returncode == 0, done.stderr
    done = tool(name, "ping", "--timeout", "5", CELLVISION_SERVER=dead)
    assert done.returncode == 3, done.stderr  # the environment beats the default


def test_run_reads_the_configuration_from_the_environment(
    plain: Server, images: dict[str, str]
) -> None:
    """``vision-server run`` ignored $CELLVISION_CONFIG."""
    done = tool(
        "vision-server",
        "run",
        "bright",
        "--image",
        images["bright"],
        "--json",
        CELLVISION_CONFIG=str(plain.config),
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["verdict"] == "pass"


# ----------------------------------------------------------------------------- point 5


def test_both_tools_reach_a_secured_server(secured: Server, images: dict[str, str]) -> None:
    assert secured.cert is not None
    assert secured.token_file is not None
    options = ["--server", secured.address, "--ca", str(secured.cert)]
    options += ["--token-file", str(secured.token_file)]
    for command in (["ping"], ["reload"]):
        done = tool("vision-server", *command, *options)
        assert done.returncode == 0, done.stderr
    done = tool("robot-client", *options, "--tls", "ping", "--json")
    assert done.returncode == 0, done.stderr
    # The same from the environment, the token in a variable (as a secret store would set it).
    env = {
        "CELLVISION_SERVER": secured.address,
        "CELLVISION_CA": str(secured.cert),
        "CELLVISION_TOKEN": secured.token_file.read_text().strip(),
    }
    done = tool("robot-client", "inspect", "bright", "--image", images["bright"], "--json", **env)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["verdict"] == "pass"
    done = tool("vision-server", "ping", **env)
    assert done.returncode == 0, done.stderr


def test_vision_server_reaches_its_server_through_its_configuration(secured: Server) -> None:
    """Beside the server, ``ping`` and ``reload`` take the port, token and certificate from the
    configuration file the server runs (the certificate pinned: its name is not checked)."""
    beside = secured.config.with_name("beside.yaml")
    port = secured.address.rsplit(":", 1)[1]
    beside.write_text(secured.config.read_text().replace("port: 0", f"port: {port}"))
    for command in ("ping", "reload"):
        done = tool("vision-server", command, CELLVISION_CONFIG=str(beside))
        assert done.returncode == 0, done.stderr
        done = tool("vision-server", command, "--config", str(beside))
        assert done.returncode == 0, done.stderr


def test_the_container_health_check_works_on_a_secured_server(secured: Server) -> None:
    """The Dockerfile's HEALTHCHECK command, with the environment the Dockerfile sets (the
    configuration at $CELLVISION_CONFIG), against a server with TLS and a token."""
    dockerfile = (REPO_ROOT / "Dockerfile").read_text()
    check = re.search(r"^HEALTHCHECK .*?CMD (\[.*?\])$", dockerfile, re.M | re.S)
    assert check, "no HEALTHCHECK ... CMD [...] in the Dockerfile"
    argv = [a.replace("127.0.0.1:7878", secured.address) for a in json.loads(check[1])]
    assert argv[:2] == ["vision-server", "ping"]
    env_config = re.search(r"^ENV CELLVISION_CONFIG=(\S+)$", dockerfile, re.M)
    assert env_config, "the Dockerfile sets no CELLVISION_CONFIG"
    done = tool("vision-server", *argv[1:], CELLVISION_CONFIG=str(secured.config))
    assert done.returncode == 0, f"{shlex.join(argv)}: {done.stderr}"


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_a_secured_server_refuses_plain_tcp_and_clients_without_the_token(
    name: str, secured: Server
) -> None:
    assert secured.cert is not None
    assert secured.token_file is not None
    base = ["ping", "--server", secured.address, "--timeout", "10"]
    plain_tcp = tool(name, *base, "--token-file", str(secured.token_file))
    assert plain_tcp.returncode == 3, plain_tcp.stderr
    assert "requires TLS" in plain_tcp.stderr  # the message says what it may mean
    untrusted = tool(name, *base, "--tls", "--token-file", str(secured.token_file))
    assert untrusted.returncode == 3, untrusted.stderr  # the system CAs do not know the cert
    no_token = tool(name, *base, "--ca", str(secured.cert), "--json")
    assert no_token.returncode == 4, no_token.stderr
    assert json.loads(no_token.stdout)["error"]["code"] == "NOT_AUTHENTICATED"


@pytest.mark.parametrize("name", sorted(TOOLS))
@pytest.mark.parametrize("variable", ["CELLVISION_TOKEN", "CELLVISION_TOKEN_FILE", "CELLVISION_CA"])
def test_an_empty_variable_is_a_usage_error(name: str, variable: str, plain: Server) -> None:
    """``CELLVISION_TOKEN="$UNSET"`` must not quietly mean "no token"."""
    done = tool(name, "ping", "--server", plain.address, "--json", **{variable: " "})
    assert done.returncode == 2, done.stdout + done.stderr
    error = json.loads(done.stdout)["error"]
    assert error["kind"] == "usage"
    assert variable in error["message"] or "empty" in error["message"]


# ----------------------------------------------------------------------------- point 6


@pytest.mark.parametrize("name", sorted(TOOLS))
def test_exit_codes_and_json_errors(name: str, secured: Server, dead: str) -> None:
    """2 usage, 3 connection, 4 server; with --json the error is a JSON object on stdout."""
    usage = tool(name, "ping", "--no-such-option", "--json")
    refused = tool(name, "ping", "--server", dead, "--timeout", "5", "--json")
    assert secured.cert is not None
    server = tool(name, "ping", "--server", secured.address, "--ca", str(secured.cert), "--json")
    for done, code, kind in (
        (usage, 2, "usage"),
        (refused, 3, "connection"),
        (server, 4, "server"),
    ):
        assert done.returncode == code, done.stdout + done.stderr
        error = json.loads(done.stdout)["error"]
        assert error["kind"] == kind
        assert error["message"]
        assert "Traceback" not in done.stderr
    assert json.loads(server.stdout)["error"]["code"] == "NOT_AUTHENTICATED"


def test_one_result_shape_and_the_fail_verdict_is_exit_1(
    plain: Server, images: dict[str, str]
) -> None:
    """``robot-client inspect`` and ``vision-server run`` answer alike: ``verdict``, exit 1 on
    fail."""
    online = tool(
        "robot-client",
        "--server",
        plain.address,
        "inspect",
        "bright",
        "--image",
        images["dark"],
        "--json",
    )
    offline = tool(
        "vision-server",
        "run",
        "--config",
        str(plain.config),
        "bright",
        "--image",
        images["dark"],
        "--json",
    )
    answers = []
    for done in (online, offline):
        assert done.returncode == 1, done.stderr
        answers.append(json.loads(done.stdout))
    shape = {"inspection", "verdict", "camera", "image", "data", "timing"}
    assert set(answers[0]) == set(answers[1]) == shape
    assert answers[0]["image"] == answers[1]["image"] == images["dark"]
    assert [a["verdict"] for a in answers] == ["fail", "fail"]
    unknown = tool("robot-client", "--server", plain.address, "inspect", "nope", "--json")
    assert unknown.returncode == 4
    assert json.loads(unknown.stdout)["error"]["code"] == "UNKNOWN_INSPECTION"
    missing = tool(
        "vision-server",
        "run",
        "--config",
        str(plain.config),
        "nope",
        "--image",
        images["dark"],
        "--json",
    )
    assert missing.returncode == 2
    assert json.loads(missing.stdout)["error"]["kind"] == "usage"
