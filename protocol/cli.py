"""What the two command-line tools (``vision-server`` and ``robot-client``) share, as pure
functions: the exit codes, where the server is and how to reach it (address, token, TLS), and
the shape of an error printed with ``--json``. Written once here because the two packages must not
import each other; nothing here does I/O (the environment comes in as a mapping, a token file is
read through a function the caller passes in, TLS contexts are the caller's).

The rule (docs/integrator-guide.md, "Finding and reaching the server"), field by field:
the command line, else the environment, else (``vision-server`` only) the server section of the
configuration, else the default.

===============  =======================  =================================================
what             command line             environment
===============  =======================  =================================================
address          ``--server HOST:PORT``   ``CELLVISION_SERVER``
token            ``--token-file PATH``    ``CELLVISION_TOKEN`` or ``CELLVISION_TOKEN_FILE``
TLS              ``--tls``, ``--ca FILE``  ``CELLVISION_TLS=1``, ``CELLVISION_CA``
===============  =======================  =================================================

A token is never empty: a set-but-empty source (``--token-file`` of an empty file,
``CELLVISION_TOKEN=""`` from an unset shell variable) is an error, not "no token". Leading and
trailing whitespace (a file's final newline) is never part of a token.
"""

from __future__ import annotations

import argparse
import enum
import importlib.metadata
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any, NoReturn

from .constants import DEFAULT_PORT, PROTOCOL_VERSION

SERVER_ENV = "CELLVISION_SERVER"
TOKEN_ENV = "CELLVISION_TOKEN"
TOKEN_FILE_ENV = "CELLVISION_TOKEN_FILE"
TLS_ENV = "CELLVISION_TLS"
CA_ENV = "CELLVISION_CA"
CONFIG_ENV = "CELLVISION_CONFIG"

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
"""Host names that are this machine only (besides the rest of 127.0.0.0/8)."""
ANY_ADDRESS = frozenset({"", "0.0.0.0", "::"})
"""Listening addresses meaning "every interface": a client on this machine uses loopback."""


class ExitCode(enum.IntEnum):
    """The exit status of every command of both tools."""

    OK = 0
    """Done; an inspection, skill, task or check passed."""
    FAILED = 1
    """The command worked and the verdict is fail (inspection, skill, task, golden case); an
    invalid configuration is USAGE, for check-config as for every command that reads one."""
    USAGE = 2
    """Bad arguments, environment or configuration: nothing was attempted."""
    CONNECTION = 3
    """The server could not be reached (refused, timeout, TLS, connection lost), or ``serve``
    could not listen."""
    SERVER = 4
    """The server answered with an ERROR (NOT_AUTHENTICATED, UNKNOWN_INSPECTION, BUSY, ...)."""
    INTERRUPTED = 130
    """Stopped by Ctrl-C (SIGINT); a shell's code for a command that SIGINT ended."""


class ErrorKind(enum.Enum):
    """What went wrong, as ``error.kind`` in ``--json`` output; each has its exit code."""

    USAGE = "usage"
    CONNECTION = "connection"
    SERVER = "server"
    DEVICE = "device"

    @property
    def exit_code(self) -> ExitCode:
        return _EXIT[self]


_EXIT = {
    ErrorKind.USAGE: ExitCode.USAGE,
    ErrorKind.CONNECTION: ExitCode.CONNECTION,
    ErrorKind.SERVER: ExitCode.SERVER,
    # A robot or gripper that cannot be reached or refuses a command is, like the vision
    # server, something outside this program that did not answer as asked.
    ErrorKind.DEVICE: ExitCode.CONNECTION,
}


def json_error(kind: ErrorKind, message: str, code: str | None = None) -> dict[str, Any]:
    """The one shape of an error on stdout with ``--json``:
    ``{"error": {"kind": ..., "message": ..., "code": <wire error code, server errors only>}}``.
    """
    error: dict[str, Any] = {"kind": kind.value, "message": message}
    if code is not None:
        error["code"] = code
    return {"error": error}


class UsageError(ValueError):
    """A bad argument, environment variable or file named by one: exit code 2."""


class ParserError(UsageError):
    """What :class:`Parser` raises for bad arguments, with the parser that found them (for
    its usage line)."""

    def __init__(self, parser: argparse.ArgumentParser, message: str) -> None:
        super().__init__(message)
        self.parser = parser


class Parser(argparse.ArgumentParser):
    """An ArgumentParser that raises :class:`ParserError` instead of printing and exiting, so
    that a tool reports bad arguments like every other error (as JSON with ``--json``)."""

    def error(self, message: str) -> NoReturn:
        raise ParserError(self, message)


def version_text(prog: str) -> str:
    """What ``--version`` prints: ``vision-server 0.1.0 (protocol 1.0)``."""
    try:
        version = importlib.metadata.version("cellvision")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree, not installed
        version = "(not installed)"
    return f"{prog} {version} (protocol {PROTOCOL_VERSION[0]}.{PROTOCOL_VERSION[1]})"


# ----------------------------------------------------------------------------- addresses


def parse_address(text: str, *, default_port: int = DEFAULT_PORT) -> tuple[str, int]:
    """``HOST:PORT``, ``HOST``, ``:PORT`` or ``[IPv6]:PORT`` → (host, port)."""
    text = text.strip()
    if not text:
        raise UsageError("empty server address")
    host, port_text = text, ""
    if text.startswith("["):
        end = text.find("]")
        if end < 0:
            raise UsageError(f"bad server address {text!r}: missing ']'")
        host, rest = text[1:end], text[end + 1 :]
        if rest:
            if not rest.startswith(":"):
                raise UsageError(f"bad server address {text!r}")
            port_text = rest[1:]
    elif text.count(":") == 1:
        host, port_text = text.split(":")
    host = host or "127.0.0.1"
    if not port_text:
        return host, default_port
    try:
        port = int(port_text)
    except ValueError:
        raise UsageError(f"bad port {port_text!r} in server address {text!r}") from None
    if not 0 < port < 65536:
        raise UsageError(f"port {port} out of range in server address {text!r}")
    return host, port


def is_loopback(host: str) -> bool:
    """Whether a listening or connecting address is this machine only (127.0.0.0/8, ::1,
    localhost). Other names count as reachable from the network."""
    return host in LOOPBACK_NAMES or host.startswith("127.")


def client_host(listen_host: str) -> str:
    """Where a client on the same machine reaches a server listening on ``listen_host``."""
    if listen_host in ANY_ADDRESS:
        return "::1" if listen_host == "::" else "127.0.0.1"
    return listen_host


# ----------------------------------------------------------------------------- tokens


def clean_token(text: str, *, source: str) -> str:
    """A token without surrounding whitespace; an empty one is a :class:`UsageError` naming
    ``source`` (an empty token must never mean "no token")."""
    token = text.strip()
    if not token:
        raise UsageError(f"{source} gives an empty token (an unset variable?)")
    return token


def _flag(text: str, *, source: str) -> bool:
    value = text.strip().lower()
    if value in ("1", "true", "yes", "on"):
        return True
    if value in ("0", "false", "no", "off"):
        return False
    raise UsageError(f"{source} must be 1 or 0, got {text!r}")


# ----------------------------------------------------------------------------- resolution


@dataclass(frozen=True)
class Layer:
    """What one source (command line, environment, configuration) says; None: nothing.

    ``token`` is a literal token, ``token_file`` a file holding one (never both in one layer);
    ``ca_file`` implies ``tls``; ``pin`` says that ``ca_file`` is the server's own certificate
    (from its configuration), trusted alone, so its names are not checked."""

    name: str
    server: str | None = None
    token: str | None = None
    token_file: str | None = None
    tls: bool | None = None
    ca_file: str | None = None
    pin: bool = False


@dataclass(frozen=True)
class Endpoint:
    """A server, resolved: where (``host``, ``port``), the token for HELLO (None: none) and TLS
    (``ca_file`` None: the system's trusted certificates; ``pin``: see :class:`Layer`)."""

    host: str
    port: int
    token: str | None = None
    tls: bool = False
    ca_file: str | None = None
    pin: bool = False
    token_source: str | None = None
    """Where the token came from, for messages (never the token itself)."""

    def __repr__(self) -> str:  # the token must not reach a log through a repr
        token = "None" if self.token is None else "'***'"
        return (
            f"Endpoint(host={self.host!r}, port={self.port}, token={token}, tls={self.tls}, "
            f"ca_file={self.ca_file!r}, pin={self.pin})"
        )


def env_token_layer(env: Mapping[str, str]) -> Layer:
    """The environment's token, alone (what ``serve`` reads). A variable that is set counts,
    even if empty (then it is an error where it is used), so that ``CELLVISION_TOKEN=$UNSET``
    never means "no token"."""
    if TOKEN_ENV in env and TOKEN_FILE_ENV in env:
        raise UsageError(f"set {TOKEN_ENV} or {TOKEN_FILE_ENV}, not both")
    return Layer("environment", token=env.get(TOKEN_ENV), token_file=env.get(TOKEN_FILE_ENV))


def env_layer(env: Mapping[str, str]) -> Layer:
    """The environment's layer: address, token (see :func:`env_token_layer`) and TLS."""
    tokens = env_token_layer(env)
    tls = _flag(env[TLS_ENV], source=f"${TLS_ENV}") if TLS_ENV in env else None
    ca = env.get(CA_ENV)
    if ca is not None and not ca.strip():
        raise UsageError(f"${CA_ENV} is set but empty")
    server = env.get(SERVER_ENV)
    if server is not None and not server.strip():
        server = None  # an empty address means the default, which is harmless
    return replace(tokens, server=server, tls=tls, ca_file=ca)


def resolve_token(*layers: Layer, read_text: Callable[[str], str]) -> tuple[str | None, str | None]:
    """(token, where it came from) from the first layer that gives one; (None, None) if none
    does. ``read_text(path)`` reads a token file (its OSError becomes a :class:`UsageError`)."""
    for layer in layers:
        if layer.token is not None and layer.token_file is not None:
            raise UsageError(f"{layer.name}: give a token or a token file, not both")
        if layer.token is not None:
            source = f"${TOKEN_ENV}" if layer.name == "environment" else f"the {layer.name}"
            return clean_token(layer.token, source=source), source
        if layer.token_file is not None:
            if not layer.token_file.strip():
                raise UsageError(f"{layer.name}: the token file name is empty")
            try:
                text = read_text(layer.token_file)
            except OSError as exc:
                raise UsageError(f"cannot read the token file {layer.token_file}: {exc}") from None
            source = f"the token file {layer.token_file}"
            return clean_token(text, source=source), source
    return None, None


def resolve_endpoint(
    *layers: Layer, read_text: Callable[[str], str], default_port: int = DEFAULT_PORT
) -> Endpoint:
    """The endpoint from ``layers`` in precedence order (first wins, field by field)."""
    host, port = "127.0.0.1", default_port
    for layer in layers:
        if layer.server:
            host, port = parse_address(layer.server, default_port=default_port)
            break
    token, source = resolve_token(*layers, read_text=read_text)
    endpoint = Endpoint(host, port, token, token_source=source)
    for layer in layers:
        if layer.tls is not None or layer.ca_file is not None:
            # --ca or $CELLVISION_CA alone means TLS; an explicit "no" wins over a CA below.
            endpoint = replace(endpoint, tls=layer.tls if layer.tls is not None else True)
            break
    if endpoint.tls:
        for layer in layers:
            if layer.ca_file is not None:
                endpoint = replace(endpoint, ca_file=layer.ca_file, pin=layer.pin)
                break
    return endpoint


__all__ = [
    "CA_ENV",
    "CONFIG_ENV",
    "SERVER_ENV",
    "TLS_ENV",
    "TOKEN_ENV",
    "TOKEN_FILE_ENV",
    "Endpoint",
    "ErrorKind",
    "ExitCode",
    "Layer",
    "Parser",
    "ParserError",
    "UsageError",
    "clean_token",
    "client_host",
    "env_layer",
    "env_token_layer",
    "is_loopback",
    "json_error",
    "parse_address",
    "resolve_endpoint",
    "resolve_token",
    "version_text",
]
