"""Where the server is: address parsing and the CLI > environment > default precedence."""

from __future__ import annotations

import pytest

from protocol import DEFAULT_PORT
from robot_client.address import ENV_VAR, parse_address, resolve_server


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("cell-3.local:7000", ("cell-3.local", 7000)),
        ("10.0.0.5", ("10.0.0.5", DEFAULT_PORT)),
        (":7001", ("127.0.0.1", 7001)),
        ("[::1]:7002", ("::1", 7002)),
        ("[fe80::1]", ("fe80::1", DEFAULT_PORT)),
        ("::1", ("::1", DEFAULT_PORT)),
        ("  cell:1  ", ("cell", 1)),
        ("cell:65535", ("cell", 65535)),
    ],
)
def test_parse_address(text: str, expected: tuple[str, int]) -> None:
    assert parse_address(text) == expected


def test_parse_address_default_port_is_an_argument() -> None:
    assert parse_address("cell", default_port=9000) == ("cell", 9000)
    assert parse_address("cell:7000", default_port=9000) == ("cell", 7000)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "empty"),
        ("   ", "empty"),
        ("cell:http", "bad port 'http'"),
        ("cell:0", "out of range"),
        ("cell:65536", "out of range"),
        ("cell:-1", "out of range"),
        ("[::1", "missing ']'"),
        ("[::1]7000", "bad server address"),
    ],
)
def test_parse_address_rejects(text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse_address(text)


def test_resolve_server_precedence(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(ENV_VAR, raising=False)
    assert resolve_server(None) == ("127.0.0.1", DEFAULT_PORT)
    assert resolve_server("") == ("127.0.0.1", DEFAULT_PORT)
    monkeypatch.setenv(ENV_VAR, "from-env:7100")
    assert resolve_server(None) == ("from-env", 7100)
    assert resolve_server("from-cli:7200") == ("from-cli", 7200)
    monkeypatch.setenv(ENV_VAR, "")
    assert resolve_server(None) == ("127.0.0.1", DEFAULT_PORT)
    monkeypatch.setenv(ENV_VAR, "from-env:bad")
    with pytest.raises(ValueError, match="bad port"):
        resolve_server(None)
    assert resolve_server("from-cli") == ("from-cli", DEFAULT_PORT)  # the CLI wins, env unused
