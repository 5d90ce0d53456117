"""Where the vision server is and how to reach it, for ``robot-client``: the command line, else
the environment (``CELLVISION_SERVER``, ``CELLVISION_TOKEN`` / ``CELLVISION_TOKEN_FILE``,
``CELLVISION_TLS``, ``CELLVISION_CA``), else 127.0.0.1:7878 without token or TLS. The rule itself
is :mod:`protocol.cli`, shared with ``vision-server``."""

from __future__ import annotations

import argparse
import os
import ssl
import sys
from collections.abc import Mapping
from pathlib import Path

from protocol import DEFAULT_PORT
from protocol.cli import SERVER_ENV, Endpoint, Layer, env_layer, parse_address, resolve_endpoint

ENV_VAR = SERVER_ENV

__all__ = [
    "ENV_VAR",
    "add_connection_options",
    "endpoint_from_args",
    "parse_address",
    "resolve_server",
    "ssl_context",
]


def resolve_server(cli_value: str | None = None) -> tuple[str, int]:
    """The server address from the command line, the environment, or the default."""
    if cli_value:
        return parse_address(cli_value)
    env = os.environ.get(ENV_VAR)
    if env and env.strip():
        return parse_address(env)
    return "127.0.0.1", DEFAULT_PORT


def add_connection_options(parser: argparse.ArgumentParser, *, top: bool) -> None:
    """``--server``, ``--token-file``, ``--tls``, ``--ca``, ``--timeout`` (and the deprecated
    ``--auth-token``). Added to the main parser (``top``) and to every subcommand, so that they
    may come before or after the subcommand; a subcommand's copy has no default, so that it
    never hides a value given before the subcommand."""
    unset = None if top else argparse.SUPPRESS
    group = parser.add_argument_group("server")
    group.add_argument(
        "--server", default=unset, help=f"HOST:PORT of the vision server (default ${ENV_VAR})"
    )
    group.add_argument(
        "--token-file",
        default=unset,
        metavar="PATH",
        help="file holding the token for HELLO (default $CELLVISION_TOKEN(_FILE))",
    )
    group.add_argument(
        "--tls",
        action="store_true",
        default=None if top else argparse.SUPPRESS,
        help="connect with TLS (default $CELLVISION_TLS)",
    )
    group.add_argument(
        "--ca",
        default=unset,
        metavar="FILE",
        help="trust this CA or certificate (PEM) for TLS; implies --tls (default $CELLVISION_CA)",
    )
    group.add_argument(
        "--timeout",
        type=float,
        default=unset,
        help="seconds per request, and for retrying a busy server (default 10)",
    )
    # Deprecated: a token on the command line is visible to every user through ps.
    group.add_argument("--auth-token", default=unset, help=argparse.SUPPRESS)


def endpoint_from_args(args: argparse.Namespace, env: Mapping[str, str] | None = None) -> Endpoint:
    """The endpoint for parsed arguments: command line > environment > default."""
    literal = getattr(args, "auth_token", None)
    if literal is not None:
        print(
            "robot-client: warning: --auth-token is deprecated (the token shows in ps); "
            "use --token-file PATH or $CELLVISION_TOKEN_FILE",
            file=sys.stderr,
        )
    cli = Layer(
        "command line",
        server=getattr(args, "server", None),
        token=literal,
        token_file=getattr(args, "token_file", None),
        tls=getattr(args, "tls", None),
        ca_file=getattr(args, "ca", None),
    )
    return resolve_endpoint(
        cli,
        env_layer(os.environ if env is None else env),
        read_text=lambda path: Path(path).read_text(encoding="utf-8"),
    )


def ssl_context(endpoint: Endpoint) -> ssl.SSLContext | None:
    """The TLS context for ``endpoint`` (None without TLS): the system's trusted CAs, or
    ``ca_file``; the server's name is checked against its certificate."""
    if not endpoint.tls:
        return None
    try:
        return ssl.create_default_context(cafile=endpoint.ca_file)
    except (OSError, ssl.SSLError) as exc:
        raise ValueError(f"cannot load the CA file {endpoint.ca_file}: {exc}") from None
