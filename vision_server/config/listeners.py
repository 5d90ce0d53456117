"""The addresses the server's front-ends listen on, and the rule that no two of them share one.

Every front-end has a default port of its own (docs/configuration.md, "Ports"): the binary
protocol 7878, the line protocol 7879, the web console (and its ``/metrics``) 7880, Modbus TCP
5020. Two enabled front-ends on one host:port would make the second fail to listen only when
the server starts; :func:`check_distinct` refuses such a configuration before anything binds
(``check-config`` and ``serve`` both call it), naming both keys.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from dataclasses import dataclass

from .settings import (
    ConsoleSettings,
    LineSettings,
    ModbusSettings,
    OpcUaSettings,
    ServerSettings,
)

WILDCARD_HOSTS = frozenset({"", "0.0.0.0", "::"})
"""Hosts that mean "every interface": they overlap with any host on the same port."""


@dataclass(frozen=True)
class Listener:
    """One enabled front-end's listening address."""

    key: str
    """The configuration key of its port, e.g. ``line.port``."""
    frontend: str
    """What listens there, for messages: ``the line protocol``."""
    host: str
    port: int
    """0: any free port (never clashes)."""

    @property
    def address(self) -> str:
        return f"{self.host or '*'}:{self.port}"

    def overlaps(self, other: Listener) -> bool:
        """True when both cannot listen at once: the same port on the same or a wildcard host."""
        if self.port == 0 or self.port != other.port:
            return False
        hosts = {_normal(self.host), _normal(other.host)}
        return len(hosts) == 1 or bool(hosts & WILDCARD_HOSTS)


class PortClash(ValueError):
    """Two enabled front-ends on one host:port. ``second`` is the one to change."""

    def __init__(self, first: Listener, second: Listener) -> None:
        super().__init__(
            f"{second.key} {second.address} is also {first.key} ({first.address}): "
            f"{second.frontend} and {first.frontend} cannot listen on one port; "
            f"give each front-end its own port"
        )
        self.first = first
        self.second = second


class ListenError(OSError):
    """An enabled front-end could not listen (port taken, address not on this machine, no
    permission): ``str()`` names the front-end, its key and its own address once, and why."""

    def __init__(self, listener: Listener, cause: OSError) -> None:
        # asyncio's message repeats the address ("error while attempting to bind on address
        # ('127.0.0.1', 7885): address already in use"): the errno's text is the cause alone.
        reason = os.strerror(cause.errno) if cause.errno else str(cause)
        super().__init__(
            cause.errno,
            f"{listener.frontend} ({listener.key}) cannot listen on {listener.address}: {reason}",
        )
        self.listener = listener

    def __str__(self) -> str:
        return str(self.strerror)


def _normal(host: str) -> str:
    return "127.0.0.1" if host == "localhost" else host


def enabled_listeners(
    server: ServerSettings,
    *,
    console: ConsoleSettings | None = None,
    line: LineSettings | None = None,
    modbus: ModbusSettings | None = None,
    opcua: OpcUaSettings | None = None,
) -> list[Listener]:
    """The listening address of each enabled front-end, the binary protocol's first."""
    listeners = [Listener("server.port", "the binary protocol", server.host, server.port)]
    if console is not None and console.enabled:
        listeners.append(Listener("console.port", "the web console", console.host, console.port))
    if line is not None and line.enabled:
        listeners.append(Listener("line.port", "the line protocol", line.host, line.port))
    if modbus is not None and modbus.enabled:
        listeners.append(Listener("modbus.port", "Modbus TCP", modbus.host, modbus.port))
    if opcua is not None and opcua.enabled:
        listeners.append(Listener("opcua.port", "OPC UA", opcua.host, opcua.port))
    return listeners


def check_distinct(listeners: Iterable[Listener]) -> None:
    """Raise :class:`PortClash` for the first listener that overlaps an earlier one."""
    seen: list[Listener] = []
    for listener in listeners:
        for earlier in seen:
            if listener.overlaps(earlier):
                raise PortClash(earlier, listener)
        seen.append(listener)


__all__ = [
    "WILDCARD_HOSTS",
    "ListenError",
    "Listener",
    "PortClash",
    "check_distinct",
    "enabled_listeners",
]
