"""What ``serve`` warns about once it listens: a front-end reachable beyond loopback without
authentication (or, for the binary protocol and the console, without TLS).

One warning line per front-end and cause, in one form: where it listens, what is missing, what
anyone on the network may then do, and what to set. The binary protocol, the line protocol and
the console share the ``server:`` section's token; Modbus TCP has no authentication in the
standard, so it is warned about whenever it listens beyond loopback (protocol/MODBUS.md).
"""

from __future__ import annotations

from collections.abc import Iterable

from protocol.cli import is_loopback

from .listeners import Listener
from .settings import ServerSettings

SET_A_TOKEN = "set server.auth_token_file or $CELLVISION_TOKEN_FILE"


def exposure_warnings(server: ServerSettings, listeners: Iterable[Listener]) -> list[str]:
    """The warning lines for ``listeners`` (their bound addresses) served with ``server``'s
    token and TLS; none for those on loopback."""
    lines: list[str] = []
    for listener in listeners:
        if is_loopback(listener.host):
            continue
        where = f"{listener.frontend} listening on {listener.address} beyond loopback"
        if listener.key == "modbus.port":
            lines.append(
                f"{where} WITHOUT AUTHENTICATION (Modbus TCP has none in the standard): anyone "
                "on the network may trigger inspections and read results; set modbus.host to "
                "the cell network's interface only, or filter the port in a firewall"
            )
            continue
        # The console asks for a sign-in with any role's token or named user, not only the
        # admin's token.
        signs_in = listener.key == "console.port" and bool(
            server.users or server.operator_token or server.integrator_token
        )
        if server.auth_token is None and not signs_in:
            lines.append(f"{where} WITHOUT A TOKEN: {_open_to(listener, server)}; {SET_A_TOKEN}")
        if server.tls_cert is None and listener.key != "line.port":
            # The line protocol's controllers rarely speak TLS: its token is their only lock.
            lines.append(
                f"{where} WITHOUT TLS: images, results and the token cross the network in "
                "clear; set server.tls"
            )
    return lines


def _open_to(listener: Listener, server: ServerSettings) -> str:
    """What anyone on the network may do through ``listener`` without a token."""
    if listener.key == "line.port":
        return "anyone on the network may trigger inspections (controllers then send A <token>)"
    if listener.key == "console.port":
        save = " and save the configuration" if server.allow_reload else ""
        return f"anyone on the network may inspect, watch the cameras{save}"
    return "anyone on the network may inspect" + (" and reload" if server.allow_reload else "")


__all__ = ["SET_A_TOKEN", "exposure_warnings"]
