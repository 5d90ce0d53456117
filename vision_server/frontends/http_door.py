"""Which requests the console answers at all: the Host it is addressed to, and, for a request
that changes something, proof that the console's own page sent it.

- **Host allow-list (DNS rebinding).** A page on ``evil.example`` whose name an attacker then
  points at the cell PC reaches the console with ``Host: evil.example``. The console answers
  only Hosts that are an IP address, ``localhost``, this machine's own names, or a name in
  ``console: allowed_hosts``; others get 421 MISDIRECTED.
- **Same-origin proof (CSRF).** A browser sends another site's POST with the operator's
  cookie. Every request that is not GET, HEAD or OPTIONS needs both:

  - an ``Origin`` that is the console's own (``scheme://host:port`` of the request), when the
    browser sends one (they do, on every cross-site POST; ``null`` is refused);
  - a request no other site can make without the console's consent: a JSON body
    (``Content-Type: application/json``) or the header ``X-Cellvision: console``. Both need a
    CORS preflight, which the console never grants; an HTML form can send neither.

  Refusals are 403 CROSS_SITE naming the missing proof.
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Iterable
from functools import lru_cache
from urllib.parse import urlsplit

from aiohttp import web

CONSOLE_HEADER = "X-Cellvision"
"""The header the console's page sends with every request that changes something."""
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


@lru_cache(maxsize=1)
def own_names() -> frozenset[str]:
    """This machine's host names (short and fully qualified), lower case."""
    names = {"localhost"}
    for name in (socket.gethostname(), socket.getfqdn()):
        if name:
            names.add(name.lower().rstrip("."))
    return frozenset(names)


def split_host(host: str) -> tuple[str, str | None]:
    """``name[:port]`` or ``[v6][:port]`` → (name, port or None), the name lower case."""
    host = host.strip().lower()
    if host.startswith("["):
        end = host.find("]")
        if end < 0:
            return host, None
        rest = host[end + 1 :]
        return host[1:end], rest[1:] if rest.startswith(":") else None
    if host.count(":") == 1:
        name, port = host.split(":")
        return name.rstrip("."), port
    return host.rstrip("."), None


def host_allowed(host: str | None, allowed: Iterable[str]) -> bool:
    """Whether a request's Host names this console (see the module)."""
    if not host:
        return False
    name, port = split_host(host)
    if not name or (port is not None and not port.isdigit()):
        return False
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        pass
    return name in own_names() or name in {a.lower().rstrip(".") for a in allowed}


def cross_site_reason(request: web.Request) -> str | None:
    """Why a state-changing request is not proven to come from the console's own page, or
    None when it is (or changes nothing)."""
    if request.method in SAFE_METHODS:
        return None
    origins = request.headers.getall("Origin", [])
    if len(origins) > 1:
        return "the request has more than one Origin"
    origin = origins[0] if origins else None
    if origin is not None:
        parts = urlsplit(origin)
        if origin == "null" or not parts.scheme or not parts.netloc:
            return f"the request's Origin {origin!r} is not the console's"
        if parts.scheme != request.scheme or parts.netloc.lower() != request.host.lower():
            return f"the request comes from {origin}, not from the console's own page"
    json_body = request.content_type == "application/json"
    if not json_body and request.headers.get(CONSOLE_HEADER) != "console":
        return (
            f"a request that changes something needs a JSON body or the header "
            f"{CONSOLE_HEADER}: console (the console's page sends it)"
        )
    return None


__all__ = ["CONSOLE_HEADER", "cross_site_reason", "host_allowed", "own_names", "split_host"]
