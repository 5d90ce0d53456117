"""Errors the client raises that are not wire errors (those are protocol.CellvisionError)."""

from __future__ import annotations


class ClientError(Exception):
    """Base of the client's local errors."""


class ConnectionLost(ClientError, ConnectionError):
    """The connection broke (or could not be made) before the answer came.

    A request in flight when this is raised may or may not have been done by the server; it is
    never re-sent automatically (a physical action must not be repeated on stale vision).
    """


class NotCellvision(ConnectionLost):
    """The address answered in another protocol (HTTP: the web console's port; the line
    protocol's text): a wrong port, not a broken connection or a TLS server."""


class RequestTimeout(ClientError, TimeoutError):
    """No answer within the client-side timeout."""


class ClientClosed(ClientError):
    """The client was closed by this program."""
