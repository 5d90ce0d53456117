"""protocol.cli: the one rule both command-line tools use to find and reach a server."""

from __future__ import annotations

import pytest

from protocol import DEFAULT_PORT
from protocol.cli import (
    Endpoint,
    ErrorKind,
    ExitCode,
    Layer,
    UsageError,
    client_host,
    env_layer,
    is_loopback,
    json_error,
    resolve_endpoint,
)

FILES = {"/secrets/token": "from-a-file\n", "/secrets/blank": " \n"}


def read_text(path: str) -> str:
    try:
        return FILES[path]
    except KeyError:
        raise FileNotFoundError(2, "No such file or directory", path) from None


def resolve(*layers: Layer) -> Endpoint:
    return resolve_endpoint(*layers, read_text=read_text)


def test_defaults() -> None:
    assert resolve(Layer("command line"), env_layer({})) == Endpoint("127.0.0.1", DEFAULT_PORT)


def test_command_line_then_environment_then_configuration_field_by_field() -> None:
    cli = Layer("command line", server="cli:1")
    env = env_layer({"CELLVISION_SERVER": "env:2", "CELLVISION_TOKEN": " env-token "})
    config = Layer("configuration", server="cfg:3", token="cfg-token", tls=True, ca_file="c.pem")
    endpoint = resolve(cli, env, config)
    assert (endpoint.host, endpoint.port) == ("cli", 1)
    assert endpoint.token == "env-token"
    assert endpoint.token_source == "$CELLVISION_TOKEN"
    assert (endpoint.tls, endpoint.ca_file) == (True, "c.pem")
    assert resolve(Layer("command line"), env_layer({}), config).token == "cfg-token"


def test_token_files_are_read_and_trimmed() -> None:
    cli = Layer("command line", token_file="/secrets/token")
    assert resolve(cli).token == "from-a-file"
    env = env_layer({"CELLVISION_TOKEN_FILE": "/secrets/token"})
    endpoint = resolve(Layer("command line"), env)
    assert endpoint.token == "from-a-file"
    assert endpoint.token_source == "the token file /secrets/token"


@pytest.mark.parametrize(
    ("layer", "message"),
    [
        (Layer("command line", token=""), "empty token"),
        (Layer("command line", token_file="/secrets/blank"), "empty token"),
        (Layer("command line", token_file="/secrets/missing"), "cannot read the token file"),
        (Layer("command line", token="a", token_file="/secrets/token"), "not both"),
    ],
)
def test_an_empty_or_unreadable_token_is_a_usage_error(layer: Layer, message: str) -> None:
    with pytest.raises(UsageError, match=message):
        resolve(layer)


@pytest.mark.parametrize(
    ("env", "message"),
    [
        ({"CELLVISION_TOKEN": ""}, "empty token"),
        ({"CELLVISION_TOKEN": "a", "CELLVISION_TOKEN_FILE": "/secrets/token"}, "not both"),
        ({"CELLVISION_TLS": "maybe"}, "must be 1 or 0"),
        ({"CELLVISION_CA": ""}, "set but empty"),
    ],
)
def test_bad_environment_is_a_usage_error(env: dict[str, str], message: str) -> None:
    with pytest.raises(UsageError, match=message):
        resolve(Layer("command line"), env_layer(env))


def test_tls_a_ca_implies_it_and_an_explicit_no_wins() -> None:
    assert resolve(env_layer({"CELLVISION_CA": "ca.pem"})).tls
    assert resolve(Layer("command line", tls=True)).ca_file is None  # the system's CAs
    no = env_layer({"CELLVISION_TLS": "0"})
    config = Layer("configuration", tls=True, ca_file="cert.pem", pin=True)
    assert not resolve(Layer("command line"), no, config).tls
    pinned = resolve(Layer("command line"), env_layer({}), config)
    assert (pinned.tls, pinned.ca_file, pinned.pin) == (True, "cert.pem", True)
    # A CA on the command line replaces the configuration's pinned certificate.
    own = resolve(Layer("command line", ca_file="ca.pem"), config)
    assert (own.ca_file, own.pin) == ("ca.pem", False)


def test_the_token_never_shows_in_a_repr() -> None:
    endpoint = resolve(Layer("command line", token="hunter2"))
    assert "hunter2" not in repr(endpoint)
    assert "hunter2" not in str(endpoint)


def test_loopback_and_client_host() -> None:
    assert all(is_loopback(h) for h in ("127.0.0.1", "127.3.4.5", "::1", "localhost"))
    assert not any(is_loopback(h) for h in ("0.0.0.0", "::", "", "10.0.0.5", "cell-pc"))
    assert client_host("0.0.0.0") == "127.0.0.1"
    assert client_host("::") == "::1"
    assert client_host("10.0.0.5") == "10.0.0.5"


def test_exit_codes_and_the_json_error_shape() -> None:
    assert [int(c) for c in ExitCode] == [0, 1, 2, 3, 4, 130]
    assert ErrorKind.SERVER.exit_code == ExitCode.SERVER
    assert json_error(ErrorKind.SERVER, "no", "BUSY") == {
        "error": {"kind": "server", "message": "no", "code": "BUSY"}
    }
    assert json_error(ErrorKind.CONNECTION, "refused") == {
        "error": {"kind": "connection", "message": "refused"}
    }
