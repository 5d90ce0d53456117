"""Where the vision server is: ``--server HOST:PORT``, else ``$CELLVISION_SERVER``, else
localhost on the default port."""

from __future__ import annotations

import os

from protocol import DEFAULT_PORT

ENV_VAR = "CELLVISION_SERVER"


def parse_address(text: str, *, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT`` or ``[IPv6]:PORT`` → (host, port)."""
    text = text.strip()
    if not text:
        raise ValueError("empty server address")
    host, port_text = text, ""
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise ValueError(f"bad server address {text!r}: missing ']'")
        host, rest = text[1:end], text[end + 1 :]
        if rest:
            if not rest.startswith(":"):
                raise ValueError(f"bad server address {text!r}")
            port_text = rest[1:]
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    host = host or "127.0.0.1"
    if not port_text:
        return host, default_port
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"bad port {port_text!r} in server address {text!r}") from None
    if not 0 < port < 65536:
        raise ValueError(f"port {port} out of range in server address {text!r}")
    return host, port


def resolve_server(cli_value: str | None = None) -> tuple[str, int]:
    """The server address from the command line, the environment, or the default."""
    if cli_value:
        return parse_address(cli_value)
    env = os.environ.get(ENV_VAR)
    if env:
        return parse_address(env)
    return "127.0.0.1", DEFAULT_PORT
