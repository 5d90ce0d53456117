"""A minimal blocking client for the server's own command line: health checks (PING) and
administration, in plain TCP or TLS, with a token. (The full client lives in robot_client, which
the server must not import.)

Where the server is comes from :mod:`protocol.cli`'s rule, with the configuration file as the
last layer: a ``vision-server ping`` beside a server reaches it with that server's own port,
token and certificate."""

from __future__ import annotations

import os
import socket
import ssl
import time
from collections.abc import Callable, Mapping
from pathlib import Path

from protocol import (
    NEED_DATA,
    SUPPORTED_VERSIONS,
    CellvisionError,
    Connection,
    ConnectionClosed,
    Error,
    Hello,
    Message,
    Role,
)
from protocol.cli import Endpoint, Layer, UsageError, client_host, env_layer, resolve_endpoint

from ..config import ConfigError, load_server_settings


class AdminError(Exception):
    """The server could not be reached or did not answer as expected."""


def config_layer(path: str | None) -> Layer:
    """What the configuration file at ``path`` says about reaching its server (nothing without
    a path): its address (``0.0.0.0`` → loopback), its token, and its own certificate, trusted
    alone (pinned). Raises :class:`UsageError` for a file that cannot be read."""
    if path is None:
        return Layer("configuration")
    try:
        settings = load_server_settings(path)
    except ConfigError as exc:
        raise UsageError(f"invalid configuration: {exc}") from None
    host = client_host(settings.host)
    server = None
    if settings.port != 0:  # port 0: the server took any port; the file does not say which
        server = f"[{host}]:{settings.port}" if ":" in host else f"{host}:{settings.port}"
    return Layer(
        "configuration",
        server=server,
        token=settings.auth_token,
        tls=True if settings.tls_cert else None,
        ca_file=settings.tls_cert,
        pin=settings.tls_cert is not None,
    )


def resolve(cli: Layer, config_path: str | None, env: Mapping[str, str] | None = None) -> Endpoint:
    """The endpoint: command line > environment > configuration file > default. A
    configuration whose ``server.port`` is 0 does not say where its server listens: without
    ``--server`` or ``$CELLVISION_SERVER`` that is a usage error, not the default port (which may
    be another server's)."""
    environment = env_layer(os.environ if env is None else env)
    configured = config_layer(config_path)
    if (
        config_path is not None
        and configured.server is None
        and not (cli.server or environment.server)
    ):
        raise UsageError(
            f"{config_path} has server.port 0 (any free port): it does not say which port its "
            "server took; give --server HOST:PORT (serve prints it as 'listening on')"
        )
    return resolve_endpoint(
        cli,
        environment,
        configured,
        read_text=lambda path: Path(path).read_text(encoding="utf-8"),
    )


def ssl_context(endpoint: Endpoint) -> ssl.SSLContext | None:
    """The client TLS context for ``endpoint`` (None without TLS). A pinned certificate (the
    server's own, from its configuration) is the only trust anchor and its names are not
    checked: ``call`` compares the certificate the server shows with it instead."""
    if not endpoint.tls:
        return None
    try:
        context = ssl.create_default_context(cafile=endpoint.ca_file)
    except (OSError, ssl.SSLError) as exc:
        raise UsageError(f"cannot load the CA file {endpoint.ca_file}: {exc}") from None
    if endpoint.pin:
        context.check_hostname = False
        # The configured file may be a chain whose first certificate is the server's: let that
        # certificate be an anchor without its issuers.
        context.verify_flags |= ssl.VERIFY_X509_PARTIAL_CHAIN
    return context


def _pinned_der(ca_file: str) -> bytes:
    """The first certificate of a PEM file, in DER (the server's own certificate)."""
    text = Path(ca_file).read_text(encoding="ascii", errors="replace")
    end_marker = "-----END CERTIFICATE-----"
    start = text.find("-----BEGIN CERTIFICATE-----")
    end = text.find(end_marker, start)
    if start < 0 or end < 0:
        raise UsageError(f"{ca_file}: no PEM certificate in it")
    return ssl.PEM_cert_to_DER_cert(text[start : end + len(end_marker)])


def call_endpoint(
    endpoint: Endpoint, build: Callable[[int], Message], *, timeout_s: float = 5.0
) -> Message:
    """:func:`call` on a resolved endpoint (its token and TLS); a bad CA file raises
    :class:`protocol.cli.UsageError`."""
    context = ssl_context(endpoint)
    pinned = _pinned_der(endpoint.ca_file) if endpoint.pin and endpoint.ca_file else None
    return call(
        endpoint.host,
        endpoint.port,
        build,
        auth_token=endpoint.token,
        timeout_s=timeout_s,
        context=context,
        pinned=pinned,
    )


def call(
    host: str,
    port: int,
    build: Callable[[int], Message],
    *,
    auth_token: str | None = None,
    timeout_s: float = 5.0,
    context: ssl.SSLContext | None = None,
    pinned: bytes | None = None,
) -> Message:
    """Connect (with TLS given a ``context``; ``pinned``: the DER certificate the server must
    show), handshake, send ``build(request_id)``, return its answer. An ERROR answer raises the
    matching :class:`protocol.CellvisionError`; no connection, TLS or answer :class:`AdminError`.
    """
    conn = Connection(Role.CLIENT, versions=SUPPORTED_VERSIONS)
    deadline = time.monotonic() + timeout_s
    try:
        raw = socket.create_connection((host, port), timeout=timeout_s)
    except OSError as exc:
        raise AdminError(f"cannot connect to {host}:{port}: {exc}") from None
    try:
        sock: socket.socket = raw
        if context is not None:
            sock = context.wrap_socket(raw, server_hostname=host)
            if pinned is not None and sock.getpeercert(binary_form=True) != pinned:
                raise AdminError(f"{host}:{port} shows another certificate than the configured one")
        with sock:
            sock.sendall(conn.send(Hello(1, SUPPORTED_VERSIONS, "vision-server-admin", auth_token)))
            try:
                _answer(sock, conn, deadline)
            except AdminError as exc:
                if context is None and "closed" in str(exc):
                    # A TLS server drops a plain-TCP HELLO without a word.
                    raise AdminError(
                        f"{exc} (before answering HELLO: if {host}:{port} requires TLS, "
                        "connect with --tls)"
                    ) from None
                raise
            sock.sendall(conn.send(build(2)))
            return _answer(sock, conn, deadline)
    except ssl.SSLError as exc:
        raise AdminError(f"TLS with {host}:{port} failed: {exc}") from None
    except OSError as exc:
        raise AdminError(f"connection to {host}:{port} failed: {exc}") from None
    finally:
        raw.close()


def _answer(sock: socket.socket, conn: Connection, deadline: float) -> Message:
    while True:
        try:
            event = conn.next_event()
        except CellvisionError as exc:
            # Raised here, not answered by the server: bytes that are no cellvision frames, or
            # a connection closed midway (e.g. a TLS server spoken to in plain TCP).
            raise AdminError(f"no valid answer: {exc.message}") from None
        if isinstance(event, Error):
            raise event.to_exception()
        if isinstance(event, Message):
            return event
        if isinstance(event, ConnectionClosed):
            raise AdminError("the server closed the connection without answering")
        assert event is NEED_DATA
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise AdminError("no answer in time")
        sock.settimeout(remaining)
        try:
            data = sock.recv(1 << 20)
        except TimeoutError:
            raise AdminError("no answer in time") from None
        try:
            conn.receive_data(data)
        except CellvisionError as exc:
            raise AdminError(f"no valid answer: {exc.message}") from None


__all__ = ["AdminError", "call", "call_endpoint", "config_layer", "resolve", "ssl_context"]
