"""Sessions of the web console: the server's ``auth_token`` exchanged for a cookie.

The cookie holds ``SESSION_ID.MAC`` where MAC = HMAC-SHA256(key = the token, message = the
session id): never the token itself. A session is valid while its id is among the open ones
(logout and a restart end it) and its MAC matches the token the server has now. Every
comparison is constant-time.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections import OrderedDict

COOKIE = "cellvision_session"
MAX_SESSIONS = 256
"""Open sessions kept; the oldest is ended beyond (a login flood cannot grow memory)."""


class Sessions:
    """The open console sessions of a server whose token is ``token`` (None: no sign-in)."""

    def __init__(self, token: str | None) -> None:
        self._token = None if token is None else token.encode("utf-8")
        self._open: OrderedDict[str, None] = OrderedDict()

    @property
    def required(self) -> bool:
        return self._token is not None

    def token_matches(self, given: object) -> bool:
        """Whether ``given`` is the server's token (constant-time)."""
        if self._token is None or not isinstance(given, str):
            return False
        return hmac.compare_digest(given.encode("utf-8"), self._token)

    def open(self) -> str:
        """A new session; returns the cookie's value."""
        session_id = secrets.token_urlsafe(24)
        self._open[session_id] = None
        while len(self._open) > MAX_SESSIONS:
            self._open.popitem(last=False)
        return f"{session_id}.{self._mac(session_id)}"

    def valid(self, cookie: str | None) -> bool:
        """Whether ``cookie`` is an open session's (always true without a token)."""
        if self._token is None:
            return True
        session_id = self._session_id(cookie)
        return session_id is not None and session_id in self._open

    def close(self, cookie: str | None) -> None:
        session_id = self._session_id(cookie)
        if session_id is not None:
            self._open.pop(session_id, None)

    def _session_id(self, cookie: str | None) -> str | None:
        """The session id of a cookie whose MAC is right, else None."""
        if self._token is None or not cookie or cookie.count(".") != 1:
            return None
        session_id, mac = cookie.split(".")
        if not hmac.compare_digest(mac.encode("ascii", "replace"), self._mac(session_id).encode()):
            return None
        return session_id

    def _mac(self, session_id: str) -> str:
        assert self._token is not None
        return hmac.new(self._token, session_id.encode("utf-8"), hashlib.sha256).hexdigest()


__all__ = ["COOKIE", "MAX_SESSIONS", "Sessions"]
